"""Local network weights for the learned metrics: where they are looked up, how they are read, their SHA-256.

Nothing is ever downloaded. Lookup order (first hit wins):

* **trunk** state dicts (torchvision format, keys like ``features.0.weight``): the path the user gives, else
  ``$TORCH_HOME/hub/checkpoints/`` (``torch.hub.get_dir()``: ``$TORCH_HOME`` or ``$XDG_CACHE_HOME/torch`` or
  ``~/.cache/torch``) with the file names torchvision/pytorch-fid use: ``alexnet-owt-*.pth``, ``vgg16-*.pth``,
  ``inception_v3_google-*.pth``, ``pt_inception-2015-12-05-*.pth``.
* **LPIPS v0.1 linear layers** (``alex.pth`` / ``vgg.pth``, keys ``lin0.model.1.weight`` ...): the path the user
  gives, else the copy shipped inside an installed ``lpips`` wheel (``lpips/weights/v0.1/``), else inside an
  installed ``torchmetrics`` wheel (``torchmetrics/functional/image/lpips_models/``). The packages are located
  with ``importlib.util.find_spec`` and never imported.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path
from typing import Callable, Mapping, Optional, TypeVar, Union

import torch

from camo_base.errors import CamoError

PathLike = Union[str, os.PathLike]

#: File-name patterns searched in ``$TORCH_HOME/hub/checkpoints`` for each trunk, in order of preference.
TRUNK_FILE_PATTERNS: dict[str, tuple[str, ...]] = {
    "alex": ("alexnet-owt-7be5be79.pth", "alexnet-owt-*.pth", "alexnet-*.pth"),
    "vgg": ("vgg16-397923af.pth", "vgg16-*.pth"),
    # SinGAN's SIFID used torchvision's ImageNet Inception v3; pytorch-fid's FID port has the same stem keys.
    "inception": ("inception_v3_google-0cc3c7bd.pth", "inception_v3_google-*.pth", "pt_inception-2015-12-05-*.pth"),
}

#: SHA-256 of the official LPIPS v0.1 linear-layer files (identical in the lpips 0.1.4 and torchmetrics wheels).
LPIPS_LIN_V01_SHA256 = {
    "alex": "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0",
    "vgg": "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868",
}

_SHA_CACHE: dict[tuple[str, int, int], str] = {}
_MODELS: dict[tuple, torch.nn.Module] = {}
M = TypeVar("M", bound=torch.nn.Module)


def file_key(path: PathLike) -> tuple[str, int, int]:
    """``(resolved path, size, mtime)`` of a file: what a cache of anything read from it is keyed by, so that an
    edited or replaced file is read again."""
    p = Path(path).expanduser()
    st = p.stat()
    return (str(p.resolve()), st.st_size, st.st_mtime_ns)


def cached_model(key: tuple, build: Callable[[], M]) -> M:
    """The network ``build()`` returns, frozen (eval mode, no gradients) and built once per ``key`` (name the
    weight files in it with :func:`file_key`)."""
    if key not in _MODELS:
        _MODELS[key] = build().eval().requires_grad_(False)
    return _MODELS[key]


def torch_checkpoints_dir() -> Path:
    """``torch.hub.get_dir()/checkpoints`` (honours ``$TORCH_HOME``); only a path, nothing is created."""
    return Path(torch.hub.get_dir()) / "checkpoints"


def find_trunk_weights(kind: str, path: Optional[PathLike] = None) -> Path:
    """Resolve the trunk weight file for ``kind`` in ``("alex", "vgg", "inception")``; CamoError if none."""
    if kind not in TRUNK_FILE_PATTERNS:
        raise CamoError(f"unknown network {kind!r}; expected one of {sorted(TRUNK_FILE_PATTERNS)}")
    if path is not None:
        p = Path(path).expanduser()
        if not p.is_file():
            raise CamoError(f"{kind} weights not found: {p}")
        return p
    ckpt = torch_checkpoints_dir()
    for pattern in TRUNK_FILE_PATTERNS[kind]:
        hits = sorted(ckpt.glob(pattern)) if ckpt.is_dir() else []
        if hits:
            return hits[0]
    names = ", ".join(TRUNK_FILE_PATTERNS[kind])
    raise CamoError(
        f"no local {kind} weights: give a path, or put one of [{names}] into {ckpt} (weights are never downloaded)"
    )


def _package_dir(name: str) -> Optional[Path]:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def lpips_lin_candidates(net: str) -> list[Path]:
    """Places where an installed wheel ships the LPIPS v0.1 linear layers of ``net`` (existing or not)."""
    out = []
    d = _package_dir("lpips")
    if d is not None:
        out.append(d / "weights" / "v0.1" / f"{net}.pth")
    d = _package_dir("torchmetrics")
    if d is not None:
        out.append(d / "functional" / "image" / "lpips_models" / f"{net}.pth")
    return out


def find_lpips_lin_weights(net: str, path: Optional[PathLike] = None) -> Path:
    """Resolve the LPIPS v0.1 linear-layer file for ``net`` (``"alex"`` or ``"vgg"``); CamoError if none."""
    if path is not None:
        p = Path(path).expanduser()
        if not p.is_file():
            raise CamoError(f"LPIPS linear-layer weights not found: {p}")
        return p
    for p in lpips_lin_candidates(net):
        if p.is_file():
            return p
    raise CamoError(
        f"no LPIPS v0.1 linear-layer weights for {net!r}: give a path to {net}.pth, or install the 'lpips' or "
        "'torchmetrics' wheel, which ship them (weights are never downloaded)"
    )


def weights_sha256(path: PathLike) -> str:
    """Hex SHA-256 of a weight file; of a folder, the SHA-256 of its sorted ``relative/path\\0<file sha>\\n``
    lines (so a score row can record exactly which weights produced it). Cached by path, size and mtime."""
    p = Path(path).expanduser()
    if p.is_dir():
        h = hashlib.sha256()
        for f in sorted(q for q in p.rglob("*") if q.is_file()):
            h.update(f"{f.relative_to(p).as_posix()}\0{weights_sha256(f)}\n".encode())
        return h.hexdigest()
    if not p.is_file():
        raise CamoError(f"weights not found: {p}")
    key = file_key(p)
    if key not in _SHA_CACHE:
        h = hashlib.sha256()
        with open(p, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        _SHA_CACHE[key] = h.hexdigest()
    return _SHA_CACHE[key]


def load_state_dict(path: PathLike, what: str) -> dict[str, torch.Tensor]:
    """Read a ``torch.save``d state dict on the CPU with ``weights_only=True`` (no pickled code runs).

    Accepted wrappings: a plain ``{name: tensor}`` dict, or one nested under ``"state_dict"`` / ``"model"``; a
    ``"module."`` prefix (DataParallel) is removed. CamoError on anything else.
    """
    p = Path(path)
    try:
        obj = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a corrupt or non-torch file
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CamoError(f"cannot read {what} weights {p}: {msg}") from None
    if isinstance(obj, Mapping):
        for key in ("state_dict", "model"):
            inner = obj.get(key)
            if isinstance(inner, Mapping):
                obj = inner
                break
    if not isinstance(obj, Mapping) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise CamoError(f"{what} weights {p} are not a state dict of tensors")
    return {(k[7:] if k.startswith("module.") else k): v for k, v in obj.items()}


def take(sd: Mapping[str, torch.Tensor], key: str, shape: tuple[int, ...], what: str, path: PathLike) -> torch.Tensor:
    """``sd[key]`` as float32 after checking its shape; CamoError naming the file, key and shapes otherwise."""
    if key not in sd:
        some = ", ".join(sorted(sd)[:6])
        raise CamoError(f"{what} weights {path} lack key {key!r} (file has: {some}, ...)")
    t = sd[key]
    if tuple(t.shape) != tuple(shape):
        raise CamoError(f"{what} weights {path}: {key!r} has shape {tuple(t.shape)}, expected {tuple(shape)}")
    return t.float()
