"""Image encodings and image files.

Linear radiance <-> sRGB (IEC 61966-2-1 piecewise curve), 8-bit previews,
and float images as EXR/NPY. Shapes: ``(H, W, 3)`` or ``(..., 3)`` float32;
masks ``(H, W)`` bool.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np

from camo_base.atomic import atomic_path
from camo_base.errors import CamoError

REC709_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Encode linear values to sRGB. Input is clipped to [0, 1] first (HDR is tone-clipped)."""
    x = np.clip(np.nan_to_num(np.asarray(x, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Decode sRGB values in [0, 1] to linear."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def luminance(x: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of ``(..., 3)`` linear RGB."""
    return np.asarray(x, dtype=np.float32) @ REC709_LUMA


def to_uint8(x_srgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x_srgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def save_png(path: str | os.PathLike, img: np.ndarray) -> None:
    """Save a PNG. Float input is taken as already sRGB-encoded in [0, 1]; bool as a mask (0/255)."""
    from PIL import Image

    arr = np.asarray(img)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8) * 255
    elif arr.dtype != np.uint8:
        arr = to_uint8(arr)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")


def load_png(path: str | os.PathLike) -> np.ndarray:
    """Load a PNG as float32 in [0, 1] (sRGB values as stored), ``(H, W, 3)`` or ``(H, W)``."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            arr = np.asarray(im.convert("RGB") if im.mode not in ("L", "1") else im.convert("L"))
    except (OSError, UnidentifiedImageError) as exc:
        raise CamoError(f"cannot read image {path}: {exc}") from None
    return arr.astype(np.float32) / 255.0


def save_exr(path: str | os.PathLike, img: np.ndarray) -> None:
    """Save a float image (``(H, W)`` or ``(H, W, 3)``) as a 32-bit float EXR."""
    import OpenEXR

    arr = np.ascontiguousarray(np.asarray(img, dtype=np.float32))
    channels = {"Y": arr} if arr.ndim == 2 else {"RGB": arr[..., :3]}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))


@contextlib.contextmanager
def quiet_stderr() -> Iterator[list[str]]:
    """Silence C libraries (OpenEXR, OpenCV) that print to file descriptor 2 while reading a bad file.

    Yields a list that receives what they printed, so the caller can fold it into one error line.
    """
    captured: list[str] = []
    try:
        saved = os.dup(2)
    except OSError:  # no real stderr (embedded interpreter): nothing to silence
        yield captured
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield captured
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            captured.extend(tmp.read().decode("utf-8", "replace").splitlines())


def load_exr(path: str | os.PathLike) -> np.ndarray:
    """Load an EXR as float32 ``(H, W, 3)`` (or ``(H, W)`` for one channel)."""
    import OpenEXR

    if not Path(path).is_file():
        raise CamoError(f"EXR file not found: {path}")
    try:
        with quiet_stderr():
            with OpenEXR.File(str(path)) as f:
                ch = f.channels()
                if "RGB" in ch:
                    arr = ch["RGB"].pixels
                elif "RGBA" in ch:
                    arr = ch["RGBA"].pixels[..., :3]
                elif all(k in ch for k in "RGB"):
                    arr = np.stack([ch[k].pixels for k in "RGB"], axis=-1)
                else:
                    arr = next(iter(ch.values())).pixels
                arr = np.array(arr, dtype=np.float32)
    except Exception as exc:  # OpenEXR raises a bare RuntimeError on corrupt files
        raise CamoError(f"cannot read EXR {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    arr = np.asarray(arr, dtype=np.float32)
    if not np.isfinite(arr).all():
        raise CamoError(f"EXR {path} contains NaN or infinite pixels")
    return arr


def load_hdr_image(path: str | os.PathLike) -> np.ndarray:
    """Load an HDR panorama (``.exr`` or Radiance ``.hdr``) as linear float32 ``(H, W, 3)``."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        return load_exr(path)
    if path.suffix.lower() == ".hdr":
        if not path.is_file():
            raise CamoError(f"HDR image not found: {path}")
        os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
        import cv2

        # OpenCV directly, unchanged depth: imageio's opencv plugin reads with IMREAD_COLOR, which tone-maps a
        # Radiance file to 8 bit (values 0-255, not radiance).
        try:
            with quiet_stderr():
                raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        except Exception:
            raw = None
        if raw is None or raw.dtype != np.float32:
            raise CamoError(f"cannot read HDR image {path}: not a valid Radiance .hdr file")
        if raw.ndim != 3 or raw.shape[2] < 3:
            raise CamoError(f"cannot read HDR image {path}: not an RGB image")
        arr = np.ascontiguousarray(raw[..., 2::-1])  # BGR -> RGB
        if not np.isfinite(arr).all():
            raise CamoError(f"HDR image {path} contains NaN or infinite pixels")
        return arr[..., :3]
    raise CamoError(f"unsupported panorama format {path.suffix!r} (use .exr or .hdr)")
