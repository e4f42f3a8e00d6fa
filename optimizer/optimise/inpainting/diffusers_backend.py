"""Stage-2 backend ``"diffusers"``: SDXL inpainting + depth ControlNet (paper Eq. 12-13, Fig. 8).

``StableDiffusionXLControlNetInpaintPipeline`` from :mod:`diffusers`, loaded
only from local files:

* ``sdxl_path`` (``--sdxl-path``): a diffusers-format SDXL *inpainting*
  pipeline folder (``model_index.json``, ``unet/``, ``vae/``, ``text_encoder``,
  ``text_encoder_2``, ``tokenizer``, ``tokenizer_2``, ``scheduler/``), e.g. a
  local copy of ``diffusers/stable-diffusion-xl-1.0-inpainting-0.1``;
* ``controlnet_path`` (``--controlnet-path``): a diffusers ``ControlNetModel``
  folder (``config.json`` + weights) of an SDXL *depth* ControlNet, e.g.
  ``diffusers/controlnet-depth-sdxl-1.0``.

Left out (``None``), the repos above are looked up in the local Hugging Face
cache only (``HF_HUB_OFFLINE=1``, ``local_files_only=True``). A path that does
not exist but looks like ``owner/name`` is also looked up in that cache.
Nothing is ever downloaded. Missing or broken weights raise a one-line
:class:`CamoError`, at construction time.

One call (:meth:`DiffusersInpainter._inpaint`):

* ``image`` is the Stage-1 render already sRGB-encoded by the caller, which is
  the gamma encoding of Eq. 12 (diffusion models are trained on sRGB images);
* ``strength`` is passed as the pipeline's ``strength`` (= ``t_start`` as a
  fraction of the schedule: the image is noised to ``t_start`` and denoised
  from there, Eq. 13). The number of steps is raised to ``ceil(1/strength)`` if
  needed so that at least one denoising step runs;
* the depth conditioning is the *normalised inverse depth* of the background
  (near = bright = 1, farthest hit = 0, sky = 0), replicated to 3 channels, as
  depth ControlNets (trained on MiDaS/DPT disparity) expect;
* image, mask and control image are resized to the pipeline resolution (long
  side ``resolution``, both sides multiples of 8; the mask conservatively, any
  covered pixel counts), and the result is resized back; the base class then
  pastes only the masked pixels into the input, so everything outside the mask
  is returned bit-exact (the VAE round trip never touches it);
* the prompt defaults to ``"background"`` (the paper: no prompt engineering).
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import math
import os
from pathlib import Path

import numpy as np

from camo_base.documents import read_json
from camo_base.errors import CamoError
from optimizer.optimise.inpainting.base import Inpainter

DEFAULT_SDXL_REPO = "diffusers/stable-diffusion-xl-1.0-inpainting-0.1"
DEFAULT_CONTROLNET_REPO = "diffusers/controlnet-depth-sdxl-1.0"
PIPELINE_CLASS = "StableDiffusionXLControlNetInpaintPipeline"
_WEIGHT_SUFFIXES = (".safetensors", ".bin")
_PIPE_PARTS = ("unet", "vae", "text_encoder", "text_encoder_2")


def _one_line(exc: BaseException, limit: int = 300) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _looks_like_repo_id(s: str) -> bool:
    parts = s.split("/")
    return len(parts) == 2 and all(parts) and not s.startswith((".", "~")) and "\\" not in s


def _from_hf_cache(repo_id: str, what: str, flag: str) -> Path:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    try:
        import huggingface_hub

        return Path(huggingface_hub.snapshot_download(repo_id, local_files_only=True))
    except Exception as exc:  # noqa: BLE001 - any failure means "not available offline"
        raise CamoError(
            f"{what} {repo_id!r} is not in the offline Hugging Face cache ({_one_line(exc, 120)}); pass {flag} DIR"
        ) from None


def resolve_folder(path, default_repo: str, what: str, flag: str) -> Path:
    """A local folder for ``path`` (or the offline HF cache copy of a repo id / ``default_repo``)."""
    if path is None or str(path).strip() == "":
        return _from_hf_cache(default_repo, what, flag)
    p = Path(os.path.expanduser(str(path)))
    if p.is_dir():
        return p
    if p.exists():
        raise CamoError(f"{what} path {str(path)!r} is not a folder")
    if _looks_like_repo_id(str(path)):
        return _from_hf_cache(str(path), what, flag)
    raise CamoError(f"{what} folder not found: {path}")


def _has_weights(folder: Path) -> bool:
    return folder.is_dir() and any(f.name.endswith(_WEIGHT_SUFFIXES) for f in folder.iterdir())


def check_sdxl_folder(folder: Path) -> dict:
    """Check the layout of a diffusers SDXL inpainting folder; return its ``model_index.json``."""
    index = folder / "model_index.json"
    if not index.is_file():
        raise CamoError(f"SDXL inpainting folder {folder} has no model_index.json (not a diffusers pipeline folder)")
    meta = read_json(index, "SDXL inpainting model_index.json", dict)
    for part in _PIPE_PARTS:
        if not (folder / part / "config.json").is_file() or not _has_weights(folder / part):
            raise CamoError(f"SDXL inpainting folder {folder}: {part}/ is missing its config.json or weights")
    for part in ("tokenizer", "tokenizer_2", "scheduler"):
        if not (folder / part).is_dir():
            raise CamoError(f"SDXL inpainting folder {folder}: {part}/ is missing")
    return meta


def check_controlnet_folder(folder: Path) -> None:
    if not (folder / "config.json").is_file() or not _has_weights(folder):
        raise CamoError(f"ControlNet folder {folder} has no config.json or no weights (*.safetensors / *.bin)")


def _pipeline_has_controlnet(meta: dict) -> bool:
    entry = meta.get("controlnet")
    return isinstance(entry, list) and len(entry) == 2 and entry[0] is not None


def pipeline_size(h: int, w: int, resolution: int) -> tuple[int, int]:
    """(height, width) with the long side ~``resolution``, both multiples of 8 (at least 8)."""
    scale = float(resolution) / float(max(h, w))
    return max(8, int(round(h * scale / 8.0)) * 8), max(8, int(round(w * scale / 8.0)) * 8)


def depth_control_image(depth: np.ndarray) -> np.ndarray:
    """Normalised inverse depth, ``(H, W, 3)`` float32 in [0, 1]: nearest = 1, farthest hit = 0, sky = 0."""
    d = np.asarray(depth, dtype=np.float32)
    hit = np.isfinite(d) & (d > 0)
    out = np.zeros(d.shape, np.float32)
    if hit.any():
        inv = 1.0 / d[hit]
        lo, hi = float(inv.min()), float(inv.max())
        out[hit] = (inv - lo) / (hi - lo) if hi - lo > 1e-12 * max(hi, 1e-30) else 1.0
    return np.repeat(out[..., None], 3, axis=2)


def _resize(x: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    import cv2

    h, w = size_hw
    if x.shape[:2] == (h, w):
        return x.astype(np.float32, copy=True)
    shrink = h < x.shape[0] or w < x.shape[1]
    interp = cv2.INTER_AREA if shrink else cv2.INTER_CUBIC
    return cv2.resize(np.ascontiguousarray(x, dtype=np.float32), (w, h), interpolation=interp)


@contextlib.contextmanager
def _quiet():
    """Silence diffusers/transformers warnings and progress bars for the duration; restore them after."""
    loggers = [logging.getLogger(n) for n in ("diffusers", "transformers")]
    levels = [lg.level for lg in loggers]
    bars = []
    for mod in ("diffusers.utils.logging", "transformers.utils.logging"):
        try:
            m = importlib.import_module(mod)
            bars.append((m, m.is_progress_bar_enabled()))
            m.disable_progress_bar()
        except Exception:  # noqa: BLE001 - best effort
            pass
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for lg, lv in zip(loggers, levels):
            lg.setLevel(lv)
        for m, on in bars:
            if on:
                m.enable_progress_bar()


def _dtype_kwarg(diffusers_module) -> str:
    """``dtype`` on diffusers versions that deprecate ``torch_dtype``, else ``torch_dtype``."""
    dep = getattr(getattr(diffusers_module, "utils", None), "deprecation_utils", None)
    if dep is None:
        with contextlib.suppress(Exception):
            dep = importlib.import_module("diffusers.utils.deprecation_utils")
    return "dtype" if hasattr(dep, "_TORCH_DTYPE_DEPRECATION_MESSAGE") else "torch_dtype"


def _resize_mask(mask: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """Conservative mask resize: a pipeline pixel is masked if it overlaps any object pixel."""
    import cv2

    h, w = size_hw
    if mask.shape == (h, w):
        return mask.copy()
    m = mask.astype(np.float32)
    shrink = h < mask.shape[0] or w < mask.shape[1]
    r = cv2.resize(m, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return r > 1e-3


def _to_pil(x: np.ndarray):
    from PIL import Image

    return Image.fromarray(np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8))


class DiffusersInpainter(Inpainter):
    """SDXL inpainting + depth ControlNet from local weights (see the module docstring)."""

    name = "diffusers"

    def __init__(
        self,
        sdxl_path: str | os.PathLike | None = None,
        controlnet_path: str | os.PathLike | None = None,
        *,
        prompt: str = "background",
        negative_prompt: str | None = None,
        num_inference_steps: int = 30,
        guidance_scale: float = 5.0,
        controlnet_conditioning_scale: float = 0.5,
        resolution: int = 1024,
        device: str | None = None,
        dtype: str | None = None,
        variant: str | None = None,
    ):
        if int(num_inference_steps) < 1:
            raise CamoError(f"diffusers inpainter: num_inference_steps must be >= 1, got {num_inference_steps}")
        if int(resolution) < 8:
            raise CamoError(f"diffusers inpainter: resolution must be >= 8, got {resolution}")
        self.prompt = str(prompt)
        self.negative_prompt = negative_prompt
        self.num_inference_steps = int(num_inference_steps)
        self.guidance_scale = float(guidance_scale)
        self.controlnet_conditioning_scale = float(controlnet_conditioning_scale)
        self.resolution = int(resolution)
        self.pipe, self.sdxl_dir, self.controlnet_dir = load_pipeline(sdxl_path, controlnet_path, device=device, dtype=dtype, variant=variant)

    @property
    def device(self) -> str:
        return str(self.pipe.device)

    def _inpaint(self, image, mask, background, depth, strength, seed):
        import torch

        h, w = mask.shape
        ph, pw = pipeline_size(h, w, self.resolution)
        img_p = _to_pil(_resize(image, (ph, pw)))
        mask_p = _resize_mask(mask, (ph, pw))
        mask_p = _to_pil(mask_p.astype(np.float32)).convert("L")
        ctrl_p = _to_pil(_resize(depth_control_image(depth), (ph, pw)))
        steps = max(self.num_inference_steps, math.ceil(1.0 / strength - 1e-9))
        generator = torch.Generator(device="cpu").manual_seed(int(seed))
        try:
            with torch.inference_mode(), _quiet():
                result = self.pipe(
                    prompt=self.prompt,
                    negative_prompt=self.negative_prompt,
                    image=img_p,
                    mask_image=mask_p,
                    control_image=ctrl_p,
                    height=ph,
                    width=pw,
                    strength=float(strength),
                    num_inference_steps=steps,
                    guidance_scale=self.guidance_scale,
                    controlnet_conditioning_scale=self.controlnet_conditioning_scale,
                    generator=generator,
                    output_type="np",
                )
        except torch.cuda.OutOfMemoryError:  # pragma: no cover - needs a GPU
            raise CamoError(f"diffusers inpainter: out of GPU memory at {pw}x{ph}; lower the resolution") from None
        except (RuntimeError, ValueError) as exc:
            raise CamoError(
                "diffusers inpainter: the pipeline failed "
                f"(are {self.sdxl_dir} and {self.controlnet_dir} an SDXL inpainting model and an SDXL depth ControlNet?): "
                f"{_one_line(exc, 200)}"
            ) from None
        out = np.asarray(result.images[0], dtype=np.float32)
        if not np.isfinite(out).all():
            raise CamoError("diffusers inpainter: the pipeline produced non-finite pixels (fp16 overflow? try dtype='float32')")
        return _resize(out, (h, w))


def _dtype(torch, name: str | None, device: str):
    if name is None:
        return torch.float16 if device.startswith("cuda") else torch.float32
    table = {"float16": torch.float16, "fp16": torch.float16, "bfloat16": torch.bfloat16, "bf16": torch.bfloat16,
             "float32": torch.float32, "fp32": torch.float32}
    if str(name).lower() not in table:
        raise CamoError(f"diffusers inpainter: unknown dtype {name!r}; use float16, bfloat16 or float32")
    return table[str(name).lower()]


def resolve_folders(sdxl_path=None, controlnet_path=None) -> tuple[Path, Path | None]:
    """The checked local SDXL folder and, unless the pipeline already bundles one, the ControlNet folder."""
    sdxl_dir = resolve_folder(sdxl_path, DEFAULT_SDXL_REPO, "SDXL inpainting model", "--sdxl-path")
    meta = check_sdxl_folder(sdxl_dir)
    controlnet_dir = None
    if controlnet_path is not None or not _pipeline_has_controlnet(meta):
        controlnet_dir = resolve_folder(controlnet_path, DEFAULT_CONTROLNET_REPO, "depth ControlNet", "--controlnet-path")
        check_controlnet_folder(controlnet_dir)
    return sdxl_dir, controlnet_dir


def load_pipeline(sdxl_path=None, controlnet_path=None, *, device=None, dtype=None, variant=None):
    """Load ``(pipeline, sdxl_dir, controlnet_dir)`` from local folders only (CamoError on any failure)."""
    if importlib.util.find_spec("diffusers") is None or importlib.util.find_spec("transformers") is None:
        raise CamoError("the diffusers backend needs diffusers and transformers: pip install 'camo-toolkit[diffusion]'")
    sdxl_dir, controlnet_dir = resolve_folders(sdxl_path, controlnet_path)

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    import torch

    try:
        import diffusers
    except Exception as exc:  # noqa: BLE001 - a broken install is a user-environment problem
        raise CamoError(f"cannot import diffusers ({_one_line(exc, 200)})") from None
    pipe_cls = getattr(diffusers, PIPELINE_CLASS, None)
    if pipe_cls is None:
        raise CamoError(f"diffusers {diffusers.__version__} has no {PIPELINE_CLASS}; upgrade diffusers (>= 0.27)")
    dev = device or ("cuda" if torch.cuda.is_available() else "cpu")
    tdtype = _dtype(torch, dtype, dev)
    kw = {_dtype_kwarg(diffusers): tdtype}
    if variant:
        kw["variant"] = variant
    try:
        with _quiet():
            extra = {}
            if controlnet_dir is not None:
                extra["controlnet"] = diffusers.ControlNetModel.from_pretrained(str(controlnet_dir), local_files_only=True, **kw)
            pipe = pipe_cls.from_pretrained(str(sdxl_dir), local_files_only=True, **extra, **kw)
    except CamoError:
        raise
    except Exception as exc:  # noqa: BLE001 - corrupt/mismatched weights surface as many exception types
        where = f"{sdxl_dir}" + (f" + {controlnet_dir}" if controlnet_dir else "")
        raise CamoError(f"cannot load the SDXL ControlNet inpainting pipeline from {where}: {_one_line(exc)}") from None
    try:
        with _quiet():
            pipe = pipe.to(dev)
    except Exception as exc:  # noqa: BLE001
        raise CamoError(f"cannot move the diffusers pipeline to {dev}: {_one_line(exc)}") from None
    pipe.set_progress_bar_config(disable=True)
    return pipe, sdxl_dir, controlnet_dir


def diffusers_status(sdxl_path=None, controlnet_path=None, *, load: bool = False) -> str:
    """One line for ``camo doctor``: whether the ``diffusers`` backend can load.

    Checks (without importing torch) that diffusers/transformers are installed,
    that the pipeline class exists, and that the folders (or offline-cache
    copies) have the expected files. ``load=True`` also loads the weights.
    Never raises for a user problem; the line starts with ``ok`` or ``unavailable``.
    """
    for mod in ("diffusers", "transformers", "safetensors"):
        if importlib.util.find_spec(mod) is None:
            return f"unavailable: {mod} is not installed (pip install 'camo-toolkit[diffusion]')"
    try:
        from importlib.metadata import version

        ver = version("diffusers")
        sdxl_dir, cn_dir = resolve_folders(sdxl_path, controlnet_path)
        device = ""
        if load:
            pipe, _, _ = load_pipeline(sdxl_dir, cn_dir)
            device = f", loaded on {pipe.device}"
            del pipe
        elif not _has_pipeline_class():
            return f"unavailable: diffusers {ver} has no {PIPELINE_CLASS}; upgrade diffusers (>= 0.27)"
    except CamoError as exc:
        return f"unavailable: {exc}"
    cn = str(cn_dir) if cn_dir else "(inside the pipeline folder)"
    how = "loaded" if load else "files found, weights not loaded"
    return f"ok ({how}): diffusers {ver}, SDXL inpainting {sdxl_dir}, depth ControlNet {cn}{device}"


def _has_pipeline_class() -> bool:
    """Whether the installed diffusers exports the pipeline class (source scan; no torch import)."""
    spec = importlib.util.find_spec("diffusers")
    if spec is None or not spec.submodule_search_locations:
        return False
    init = Path(list(spec.submodule_search_locations)[0]) / "__init__.py"
    try:
        return PIPELINE_CLASS in init.read_text(encoding="utf-8")
    except OSError:
        return False
