"""GANmouflage object crop: the square around the object that the metrics compare."""

from __future__ import annotations

import math
from typing import Union

import numpy as np
import torch

from camo_base.errors import CamoError

CROP_MULTIPLE = 32
CROP_MARGIN = 32


def crop_side(d: int) -> int:
    """``32 * ceil(d / 32) + 32``: the crop side for an object whose larger bounding-box side is ``d`` px."""
    if d < 1:
        raise CamoError(f"object size must be >= 1 px, got {d}")
    return CROP_MULTIPLE * math.ceil(d / CROP_MULTIPLE) + CROP_MARGIN


def object_crop_box(mask: Union[np.ndarray, torch.Tensor]) -> tuple[int, int, int]:
    """Square crop ``(y0, x0, side)`` around the object footprint (GANmouflage's evaluation crop).

    ``d`` is the larger side of the bounding box of the ``True`` pixels of ``mask`` ``(H, W)`` and
    ``side = 32 * ceil(d / 32) + 32`` px. The square is centred on the bounding box (``y0 = (y_min + y_max + 1 -
    side) // 2``: the floor division rounds the start *down*, so an odd leftover ``side - (y_max - y_min + 1)``
    puts the extra pixel **above / left** of the object, e.g. a 1-px object at row 100 gets the 64 rows 68-131: 32 above it, 31 below),
    then shifted to lie inside the image.
    If ``side`` exceeds the shorter image side it is **clamped** to ``min(H, W)``: the crop stays square and
    inside the image, no padded (synthetic) pixels ever enter a metric.

    Returns:
        ``(y0, x0, side)`` with ``0 <= y0 <= H - side``, ``0 <= x0 <= W - side``; crop ``img[y0:y0+side,
        x0:x0+side]`` (or use :func:`apply_crop`).

    Raises:
        CamoError: mask not 2-D or empty (no object pixel).
    """
    m = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    if m.ndim != 2:
        raise CamoError(f"mask must be (H, W), got shape {m.shape}")
    m = m.astype(bool)
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    if rows.size == 0:
        raise CamoError("mask is empty: the object is not visible in this view, nothing to crop")
    h, w = m.shape
    y_min, y_max, x_min, x_max = int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])
    d = max(y_max - y_min + 1, x_max - x_min + 1)
    side = min(crop_side(d), h, w)
    y0 = min(max((y_min + y_max + 1 - side) // 2, 0), h - side)
    x0 = min(max((x_min + x_max + 1 - side) // 2, 0), w - side)
    return y0, x0, side


def apply_crop(img: Union[np.ndarray, torch.Tensor], box: tuple[int, int, int]):
    """Crop ``(H, W, ...)`` NumPy images or ``(..., H, W)`` tensors to ``box = (y0, x0, side)``."""
    y0, x0, side = box
    if isinstance(img, torch.Tensor):
        return img[..., y0 : y0 + side, x0 : x0 + side]
    return np.asarray(img)[y0 : y0 + side, x0 : x0 + side]
