"""The Stage-2 inpainting interface (paper Sec. III-C, Eq. 13).

An :class:`Inpainter` re-synthesises the object pixels of a Stage-1 render so
that they look like the surrounding background; Stage 2 then uses the result
only as a pseudo ground truth for the photometric loss (Eq. 14). All backends
share :meth:`Inpainter.inpaint`, which validates the inputs, calls the backend
and composites: pixels outside the mask are returned unchanged, bit for bit.

Inputs (all NumPy, one view):

``image_srgb``       ``(H, W, 3)`` float32 in [0, 1], the Stage-1 render,
                     already sRGB/gamma-encoded (Eq. 12: the caller applies
                     ``camo_base.imaging.linear_to_srgb`` to the linear render).
``mask``             ``(H, W)`` bool, True = object pixels to re-synthesise
                     (``M_i`` of the paper).
``background_srgb``  ``(H, W, 3)`` the background rendered without the object
                     (``I_bg``), sRGB-encoded. Backends only ever use it
                     outside ``mask``: what lies behind the object is unknown to
                     an inpainter.
``depth``            ``(H, W)`` float32 background depth in scene units,
                     ``0`` (or non-finite) where no surface is hit (sky)
                     (``D(I_bg)``; known inside the mask too).
``strength``         float in (0, 1]: ``t_start`` as a fraction of the
                     diffusion schedule. 1 re-synthesises from scratch, small
                     values stay close to ``image_srgb`` inside the mask.
``seed``             int; equal inputs and seed give an identical result.
"""

from __future__ import annotations

import numpy as np

from camo_base.errors import CamoError


def _as_image(name: str, x, shape: tuple[int, int] | None) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise CamoError(f"inpaint: {name} is not a numeric array ({exc})") from None
    if a.ndim != 3 or a.shape[2] != 3:
        raise CamoError(f"inpaint: {name} must have shape (H, W, 3), got {a.shape}")
    if shape is not None and a.shape[:2] != shape:
        raise CamoError(f"inpaint: {name} has size {a.shape[:2]}, expected {shape}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise CamoError(f"inpaint: {name} is empty")
    return a


def validate_inputs(image_srgb, mask, background_srgb, depth, strength, seed):
    """Check and normalise the arguments of :meth:`Inpainter.inpaint` (CamoError on bad input)."""
    image = _as_image("image_srgb", image_srgb, None)
    shape = image.shape[:2]
    bg = _as_image("background_srgb", background_srgb, shape)
    m = np.asarray(mask)
    if m.shape != shape:
        raise CamoError(f"inpaint: mask has shape {m.shape}, expected {shape}")
    if m.dtype != bool:
        if not np.issubdtype(m.dtype, np.number):
            raise CamoError(f"inpaint: mask must be bool, got {m.dtype}")
        m = m != 0
    try:
        d = np.asarray(depth, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise CamoError(f"inpaint: depth is not a numeric array ({exc})") from None
    if d.shape != shape:
        raise CamoError(f"inpaint: depth has shape {d.shape}, expected {shape}")
    d = np.where(np.isfinite(d) & (d > 0), d, np.float32(0.0)).astype(np.float32)
    try:
        s = float(strength)
    except (TypeError, ValueError):
        raise CamoError(f"inpaint: strength must be a number in (0, 1], got {strength!r}") from None
    if not (0.0 < s <= 1.0):
        raise CamoError(f"inpaint: strength must be in (0, 1], got {s}")
    try:
        seed_i = int(seed)
    except (TypeError, ValueError):
        raise CamoError(f"inpaint: seed must be an integer, got {seed!r}") from None
    if seed_i < 0:
        raise CamoError(f"inpaint: seed must be >= 0, got {seed_i}")
    return image, m, bg, d, s, seed_i


def clean_srgb(x: np.ndarray) -> np.ndarray:
    """NaN/inf -> 0/1 and clip to [0, 1] (float32)."""
    return np.clip(np.nan_to_num(np.asarray(x, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)


class Inpainter:
    """Base class: subclasses implement :meth:`_inpaint` and set :attr:`name`."""

    name = "base"

    def inpaint(
        self,
        image_srgb: np.ndarray,
        mask: np.ndarray,
        background_srgb: np.ndarray,
        depth: np.ndarray,
        strength: float = 1.0,
        seed: int = 0,
    ) -> np.ndarray:
        """Re-synthesise the masked pixels; returns ``(H, W, 3)`` float32 in [0, 1].

        Pixels outside ``mask`` are ``image_srgb`` (as float32) unchanged, bit
        for bit. An empty mask returns a copy of ``image_srgb``. A mask that
        covers the whole image leaves nothing to copy from: CamoError.
        """
        image, m, bg, d, s, seed_i = validate_inputs(image_srgb, mask, background_srgb, depth, strength, seed)
        out = image.copy()
        if not m.any():
            return out
        if m.all():
            raise CamoError("inpaint: the mask covers the whole image; there is no background to inpaint from")
        fill = self._inpaint(clean_srgb(image), m, clean_srgb(bg), d, s, seed_i)
        fill = np.asarray(fill, dtype=np.float32)
        if fill.shape != image.shape:  # pragma: no cover - backend bug
            raise RuntimeError(f"{self.name} inpainter returned shape {fill.shape}, expected {image.shape}")
        out[m] = clean_srgb(fill[m])
        return out

    def _inpaint(
        self, image: np.ndarray, mask: np.ndarray, background: np.ndarray, depth: np.ndarray, strength: float, seed: int
    ) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"
