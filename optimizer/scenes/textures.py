"""Offline ground and wall textures built from scikit-image's shipped images.

Every texture is linear RGB float32 ``(H, W, 3)`` in [0, 1] (an albedo), made
by colouring one of scikit-image's grey photographs (``grass``, ``gravel``,
``brick``) with a two-colour ramp. Nothing is downloaded.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np

from camo_base.errors import CamoError
from camo_base.imaging import srgb_to_linear


def _grey(name: str) -> np.ndarray:
    import skimage.data

    img = np.asarray(getattr(skimage.data, name)(), dtype=np.float32) / 255.0
    if img.ndim == 3:
        img = img[..., :3].mean(axis=-1)
    lo, hi = np.percentile(img, [1, 99])
    return np.clip((img - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


def _ramp(grey: np.ndarray, dark_srgb: tuple[float, float, float], light_srgb: tuple[float, float, float]) -> np.ndarray:
    """Colour a grey image with a ramp between two sRGB colours; returns linear albedo."""
    dark = srgb_to_linear(np.array(dark_srgb, np.float32))
    light = srgb_to_linear(np.array(light_srgb, np.float32))
    t = grey[..., None]
    return (dark * (1.0 - t) + light * t).astype(np.float32)


def grass() -> np.ndarray:
    return _ramp(_grey("grass"), (0.10, 0.20, 0.05), (0.55, 0.70, 0.25))


def gravel() -> np.ndarray:
    return _ramp(_grey("gravel"), (0.25, 0.22, 0.19), (0.78, 0.74, 0.68))


def brick() -> np.ndarray:
    return _ramp(_grey("brick"), (0.30, 0.10, 0.07), (0.80, 0.50, 0.40))


def marble() -> np.ndarray:
    """Bright, low-contrast stone (the paper's white marble side)."""
    g = _grey("gravel")
    return _ramp(0.35 + 0.65 * g, (0.70, 0.70, 0.68), (0.95, 0.94, 0.92))


def asphalt() -> np.ndarray:
    """Dark, fine-grained ground (the paper's asphalt side)."""
    return _ramp(_grey("gravel"), (0.10, 0.10, 0.11), (0.32, 0.32, 0.33))


def planks() -> np.ndarray:
    """Wooden floor boards: grass grain stretched along the boards, with dark seams."""
    g = _grey("grass")
    grain = np.repeat(g[:, ::8], 8, axis=1)[:, : g.shape[1]]
    grain = 0.6 * grain + 0.4 * g
    rows = np.arange(g.shape[0])
    seam = ((rows % 64) < 2)[:, None]
    img = _ramp(grain, (0.35, 0.20, 0.10), (0.70, 0.48, 0.28))
    return np.where(seam[..., None], img * 0.35, img).astype(np.float32)


TEXTURES: dict[str, Callable[[], np.ndarray]] = {
    "grass": grass,
    "gravel": gravel,
    "brick": brick,
    "marble": marble,
    "asphalt": asphalt,
    "planks": planks,
}


@lru_cache(maxsize=None)
def _cached(name: str) -> np.ndarray:
    return TEXTURES[name]()


def texture(name: str) -> np.ndarray:
    """A built-in texture by name (cached; returns a copy)."""
    if name not in TEXTURES:
        raise CamoError(f"unknown texture {name!r}; choose one of: {', '.join(sorted(TEXTURES))}")
    return _cached(name).copy()
