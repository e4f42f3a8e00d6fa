"""DreamSim (Fu et al. 2023), optional: needs the ``dreamsim`` package and a local weights folder.

Install with ``pip install 'camo-toolkit[dreamsim]'``. The folder is DreamSim's ``cache_dir`` as its own
downloader leaves it: for the default ``"ensemble"`` model ``ensemble_lora/``, ``dino_vitb16_pretrain.pth``,
``clip_vitb16_pretrain.pth.tar``, ``open_clip_vitb16_pretrain.pth.tar``, plus (DINO backbones are built through
``torch.hub``) ``facebookresearch_dino_main/`` and ``checkpoints/dino_vitbase16_pretrain.pth``. Prepare it once
on a machine with network access (``dreamsim.dreamsim(cache_dir=FOLDER)``) and copy it. Loading here never
downloads: the files are checked first, and any download attempt during loading raises CamoError.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional, Union

import torch
import torch.nn.functional as F

from camo_base.errors import CamoError

from evaluation.metrics._common import ImageLike, Metric, prepare_pair
from evaluation.metrics.weights import weights_sha256

PathLike = Union[str, os.PathLike]

DREAMSIM_TYPE = "ensemble"
DREAMSIM_IMG_SIZE = 224

#: Files DreamSim's ``download_weights`` checks, plus the torch.hub pieces of the DINO backbones.
DREAMSIM_REQUIRED_FILES = {
    "ensemble": ("ensemble_lora", "dino_vitb16_pretrain.pth", "clip_vitb16_pretrain.pth.tar",
                 "open_clip_vitb16_pretrain.pth.tar", "facebookresearch_dino_main",
                 "checkpoints/dino_vitbase16_pretrain.pth"),
    "dino_vitb16": ("dino_vitb16_single_lora", "dino_vitb16_pretrain.pth", "facebookresearch_dino_main",
                    "checkpoints/dino_vitbase16_pretrain.pth"),
    "clip_vitb32": ("clip_vitb32_single_lora", "clip_vitb32_pretrain.pth.tar"),
    "open_clip_vitb32": ("open_clip_vitb32_single_lora", "open_clip_vitb32_pretrain.pth.tar"),
}


@contextlib.contextmanager
def _no_downloads() -> Iterator[None]:
    """Make torch.hub downloads raise CamoError and put Hugging Face hubs offline; restore everything after."""
    old_dl = torch.hub.download_url_to_file
    old_hub_dir = getattr(torch.hub, "_hub_dir", None)
    old_env = {k: os.environ.get(k) for k in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")}

    def refuse(url: str, *args: Any, **kwargs: Any) -> None:
        raise CamoError(f"DreamSim tried to download {url}; put that file into its weights folder")

    torch.hub.download_url_to_file = refuse
    os.environ.update({"HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"})
    try:
        yield
    finally:
        torch.hub.download_url_to_file = old_dl
        if hasattr(torch.hub, "_hub_dir"):
            torch.hub._hub_dir = old_hub_dir  # dreamsim calls torch.hub.set_dir(cache_dir)
        for k, v in old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def load_dreamsim(weights_dir: Optional[PathLike], dreamsim_type: str = DREAMSIM_TYPE, device: str = "cpu") -> Any:
    """Load DreamSim from a local folder; CamoError when the folder, its files or the package are missing.

    Returns the DreamSim model (``model(a, b)`` -> distances) with ``camo_weights_sha256`` (SHA-256 over the
    folder, see :func:`~evaluation.metrics.weights.weights_sha256`) and ``camo_dreamsim_type`` attributes.
    """
    if dreamsim_type not in DREAMSIM_REQUIRED_FILES:
        raise CamoError(f"unknown DreamSim type {dreamsim_type!r}; expected one of {sorted(DREAMSIM_REQUIRED_FILES)}")
    if weights_dir is None:
        raise CamoError("DreamSim needs a local weights folder (weights are never downloaded); see "
                        "evaluation.metrics.dreamsim for its layout")
    folder = Path(weights_dir).expanduser()
    if not folder.is_dir():
        raise CamoError(f"DreamSim weights folder not found: {folder}")
    missing = [f for f in DREAMSIM_REQUIRED_FILES[dreamsim_type] if not (folder / f).exists()]
    if missing:
        raise CamoError(f"DreamSim weights folder {folder} lacks: {', '.join(missing)}")
    if importlib.util.find_spec("dreamsim") is None:
        raise CamoError("DreamSim needs the 'dreamsim' package: pip install 'camo-toolkit[dreamsim]'")
    try:
        with _no_downloads():
            from dreamsim import dreamsim as build

            model, _ = build(pretrained=True, device=device, cache_dir=str(folder), dreamsim_type=dreamsim_type)
    except CamoError:
        raise
    except Exception as exc:  # whatever the optional package raises becomes one user-facing line
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CamoError(f"cannot load DreamSim from {folder}: {msg}") from None
    model.camo_weights_sha256 = weights_sha256(folder)
    model.camo_dreamsim_type = dreamsim_type
    return model


def dreamsim_distance(x: ImageLike, y: ImageLike, model: Any) -> torch.Tensor:
    """DreamSim distance of each pair (lower is better), ``(N,)`` float32, cosine distance in ``[0, 2]``.

    Images (sRGB ``[0, 1]``, H, W >= 32) are resized to 224x224 (bicubic, antialiased, aspect not kept) as
    DreamSim's own preprocessing does (it resizes the PIL image; values may differ from it by resampling only).
    """
    x, y = prepare_pair(x, y, "dreamsim", same_size=False)
    dev = next(model.parameters()).device

    def prep(t: torch.Tensor) -> torch.Tensor:
        t = F.interpolate(t.float(), size=(DREAMSIM_IMG_SIZE, DREAMSIM_IMG_SIZE), mode="bicubic",
                          align_corners=False, antialias=True)
        return t.clamp(0.0, 1.0).to(dev)

    with torch.no_grad():
        return model(prep(x), prep(y)).float().cpu().reshape(-1)


_MODELS: dict[tuple, Any] = {}


def _compute(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
    kind = weights.get("dreamsim_type", DREAMSIM_TYPE)
    key = (str(weights.get("dreamsim")), kind)
    if key not in _MODELS:
        _MODELS[key] = load_dreamsim(weights.get("dreamsim"), kind)
    model = _MODELS[key]
    return dreamsim_distance(x, y, model), {"variant": kind, "weights_sha256": model.camo_weights_sha256}


def _from_path(path: str) -> dict[str, str]:
    p = Path(path).expanduser()
    if not p.is_dir():
        raise CamoError(f"dreamsim weights: folder not found: {p}")
    return {"dreamsim": str(p)}


def _unavailable(weights: Mapping[str, Any]) -> Optional[str]:
    return None if weights.get("dreamsim") else f"DreamSim needs {DREAMSIM_NEEDS}"


#: What a user needs for DreamSim (one line).
DREAMSIM_NEEDS = ("the optional 'dreamsim' package (pip install '.[dreamsim]') and a local weights folder "
                  "(--weights dreamsim=DIR); no registry package ships its weights")

#: The metric of this module (collected by :mod:`evaluation.metrics.registry`).
METRICS = (Metric("dreamsim", _compute, False, "1", "[0, 2]", "DreamSim (optional package, local weights folder)",
                  "DreamSim", needs_weights=True, order=6, table_order=2, variant=True, weights_key="dreamsim",
                  unavailable=_unavailable, needs=DREAMSIM_NEEDS, from_path=_from_path),)
