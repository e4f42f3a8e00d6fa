"""``camo doctor``: can the toolkit run here, and which optional local weights are found.

Weights are never downloaded; they are looked up in ``$TORCH_HOME/hub/checkpoints``
(default ``~/.cache/torch/hub/checkpoints``), in ``$CAMO_WEIGHTS`` and in folders given
with ``--weights-dir``. Exit 0 when the renderer works (weights are optional).
"""

from __future__ import annotations

import glob
import os
import platform
from pathlib import Path
from typing import Sequence

from .errors import CamoError

#: Optional weights: name -> (file glob patterns, what uses them).
WEIGHT_PATTERNS: dict[str, tuple[tuple[str, ...], str]] = {
    "lpips-alex": (("alexnet-owt-*.pth", "alexnet*.pth"), "LPIPS (AlexNet trunk)"),
    "lpips-vgg": (("vgg16-*.pth", "vgg16*.pth"), "LPIPS (VGG16 trunk)"),
    "inception": (("pt_inception-2015-12-05-*.pth", "inception_v3_google-*.pth"), "SIFID (Inception v3)"),
}


def weight_dirs(extra: Sequence[str] = ()) -> list[Path]:
    torch_home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))
    dirs = [torch_home / "hub" / "checkpoints"]
    if os.environ.get("CAMO_WEIGHTS"):
        dirs.append(Path(os.environ["CAMO_WEIGHTS"]))
    dirs += [Path(d) for d in extra]
    return dirs


def find_weight(name: str, extra: Sequence[str] = ()) -> Path | None:
    patterns, _ = WEIGHT_PATTERNS[name]
    for d in weight_dirs(extra):
        for pat in patterns:
            hits = sorted(glob.glob(str(d / pat)))
            if hits:
                return Path(hits[0])
    return None


def _line(label: str, value: str) -> None:
    print(f"{label:<22} {value}")


def run_doctor(extra_dirs: Sequence[str] = ()) -> int:
    from . import backend

    ok = True
    try:
        info = backend.init()
        import drjit as dr
        import mitsuba as mi

        _line("mitsuba", f"{mi.__version__} (variant {info.variant})")
        _line("drjit", dr.__version__)
        _line("libLLVM", f"{info.llvm.path} (LLVM {info.llvm.version})" if info.llvm else "not used (CUDA)")
        _line("threads", str(info.threads))
        _line("gpu", info.gpu or "none (CPU rendering)")
        sc = mi.load_dict({"type": "scene", "s": {"type": "sphere"}, "e": {"type": "constant"}})
        img = mi.render(sc, sensor=mi.load_dict({"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}}), spp=1)
        _line("test render", "ok" if dr.all(dr.isfinite(img.array)) else "NON-FINITE")
    except CamoError as exc:
        ok = False
        _line("renderer", f"NOT AVAILABLE: {exc}")
    except Exception as exc:  # report, do not crash the doctor
        ok = False
        _line("renderer", f"NOT AVAILABLE: {type(exc).__name__}: {exc}")
    try:
        import torch

        _line("torch", f"{torch.__version__} (cuda: {'yes' if torch.cuda.is_available() else 'no'})")
    except Exception as exc:
        ok = False
        _line("torch", f"NOT AVAILABLE: {exc}")
    _line("python", f"{platform.python_version()} on {platform.machine()}")
    print("optional local weights (never downloaded):")
    for name, (_, what) in WEIGHT_PATTERNS.items():
        hit = find_weight(name, extra_dirs)
        _line(f"  {name}", f"{hit}  [{what}]" if hit else f"not found  [{what}; metric falls back to its weight-free proxy]")
    for label, status in _extra_statuses():
        _line(f"  {label}", status)
    print("status:", "ok" if ok else "the renderer cannot run; see above")
    return 0 if ok else 1


def _extra_statuses() -> list[tuple[str, str]]:
    """Status lines contributed by optional parts (LPIPS lin layers, DreamSim, SDXL)."""
    out: list[tuple[str, str]] = []
    try:
        from evaluation.metrics import weights_status  # type: ignore[attr-defined]

        out += list(weights_status())
    except (ImportError, AttributeError):
        pass
    try:
        from .inpaint import diffusers_status  # type: ignore[attr-defined]

        out.append(("sdxl+controlnet", diffusers_status(os.environ.get("CAMO_SDXL_PATH"), os.environ.get("CAMO_CONTROLNET_PATH"))))
    except (ImportError, AttributeError):
        pass
    return out
