"""Equirect HDR panoramas: capture one from a scene, and project one onto a ground plane.

Convention (matches Mitsuba's ``envmap`` with ``to_world = R_z(rot) R_x(90deg)``
that turns its Y-up frame Z-up): pixel ``(row, col)`` of an ``(H, 2H, 3)``
panorama has ``u = (col + 0.5) / W``, ``v = (row + 0.5) / H``,
``theta = pi v`` (from the zenith), ``phi = 2 pi u`` and looks along the world
direction ``R_z(rot) (sin theta sin phi, sin theta cos phi, cos theta)``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def equirect_directions(width: int, height: int) -> np.ndarray:
    """World directions ``(H, W, 3)`` of an equirect panorama's pixel centres (rotation 0)."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    theta = np.pi * v[:, None]
    phi = 2.0 * np.pi * u[None, :]
    st = np.sin(theta)
    return np.stack(np.broadcast_arrays(st * np.sin(phi), st * np.cos(phi), np.cos(theta)), axis=-1).astype(np.float32)


def render_equirect(elements: dict[str, Any], origin, width: int = 512, spp: int = 32, seed: int = 0,
                    max_depth: int = 8) -> np.ndarray:
    """Path-trace an equirect panorama ``(width/2, width, 3)`` of a scene seen from ``origin``.

    ``elements`` are scene-element dicts (see :mod:`optimizer.scenes.environments`).
    Returns linear radiance, float32.
    """
    import drjit as dr
    import mitsuba as mi

    height = width // 2
    scene = mi.load_dict({"type": "scene", **elements})
    integrator = mi.load_dict({"type": "path", "max_depth": max_depth})
    n = width * height
    acc = np.zeros((n, 3), np.float64)
    sampler = mi.load_dict({"type": "independent"})
    for s in range(spp):
        sampler.seed(seed * 100003 + s, n)
        idx = dr.arange(mi.UInt32, n)
        col = mi.Float(idx % width) + sampler.next_1d()
        row = mi.Float(idx // width) + sampler.next_1d()
        theta = dr.pi * row / height
        phi = 2.0 * dr.pi * col / width
        st = dr.sin(theta)
        d = mi.Vector3f(st * dr.sin(phi), st * dr.cos(phi), dr.cos(theta))
        ray = mi.RayDifferential3f(o=mi.Point3f(*origin), d=d)
        L, _, _ = integrator.sample(scene, sampler, ray)
        acc += np.stack([np.asarray(L[0]), np.asarray(L[1]), np.asarray(L[2])], axis=-1)
    return (acc / spp).reshape(height, width, 3).astype(np.float32)


def sample_equirect(pano: np.ndarray, dirs: np.ndarray, rotation_deg: float = 0.0) -> np.ndarray:
    """Bilinear lookup of ``pano`` ``(H, W, 3)`` along world directions ``(..., 3)``."""
    h, w = pano.shape[:2]
    d = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    if rotation_deg:
        c, s = math.cos(math.radians(-rotation_deg)), math.sin(math.radians(-rotation_deg))
        d = np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1], d[..., 2]], axis=-1)
    u = (np.arctan2(d[..., 0], d[..., 1]) / (2 * np.pi)) % 1.0
    v = np.arccos(np.clip(d[..., 2], -1.0, 1.0)) / np.pi
    x = u * w - 0.5
    y = np.clip(v * h - 0.5, 0.0, h - 1.0)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x1 = (x0 + 1) % w
    x0 = x0 % w
    y1 = np.minimum(y0 + 1, h - 1)
    top = pano[y0, x0] * (1 - fx) + pano[y0, x1] * fx
    bot = pano[y1, x0] * (1 - fx) + pano[y1, x1] * fx
    return (top * (1 - fy) + bot * fy).astype(np.float32)


def sky_irradiance(pano: np.ndarray) -> np.ndarray:
    """Irradiance ``(3,)`` on an unoccluded upward-facing surface from the panorama's upper hemisphere."""
    h, w = pano.shape[:2]
    theta = np.pi * (np.arange(h) + 0.5) / h
    weight = np.where(theta < np.pi / 2, np.cos(theta) * np.sin(theta), 0.0) * (np.pi / h) * (2 * np.pi / w)
    return np.einsum("h,hwc->c", weight, pano.astype(np.float64)).astype(np.float32)


def project_to_ground(pano: np.ndarray, capture_height: float, extent: float, resolution: int = 1024,
                      rotation_deg: float = 0.0) -> np.ndarray:
    """Albedo texture ``(N, N, 3)`` for a ground rectangle ``[-extent, extent]^2`` at z = 0.

    Each texel takes the panorama's radiance along the direction from the
    capture point ``(0, 0, capture_height)`` to the texel, divided by the
    diffuse response to the panorama's sky (``E / pi``), so that the ground
    lit by the panorama renders with the radiance the panorama recorded, and an
    object placed on it casts a shadow. Row 0 is ``uv.y = 0`` (Mitsuba's
    ``rectangle`` maps local ``y = -1`` to ``v = 0``).
    """
    n = resolution
    t = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    X, Y = np.meshgrid(t * extent, t * extent)  # rows follow y
    dirs = np.stack([X, Y, np.full_like(X, -capture_height)], axis=-1)
    radiance = sample_equirect(pano, dirs, rotation_deg)
    E = np.maximum(sky_irradiance(pano), 1e-6)
    return np.clip(radiance * np.pi / E, 0.0, 1.0).astype(np.float32)


def solid_angles(height: int, width: int) -> np.ndarray:
    """Solid angle ``(H, 1)`` of one pixel per row of an equirect panorama (steradians; they sum to 4 pi)."""
    theta = np.pi * (np.arange(height) + 0.5) / height
    return (np.sin(theta) * (np.pi / height) * (2 * np.pi / width))[:, None]


def _box_sum(x: np.ndarray, r: int) -> np.ndarray:
    """Sum over a (2r+1)^2 window per pixel of an (H, W) image: wraps in longitude, clamps at the poles."""
    p = np.pad(x, ((r, r), (0, 0)), mode="constant")
    p = np.concatenate([p[:, -r:], p, p[:, :r]], axis=1) if r else p
    c = np.cumsum(np.cumsum(np.pad(p, ((1, 0), (1, 0))), axis=0), axis=1)
    k = 2 * r + 1
    return c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]


def _finite_rgb(pano: np.ndarray) -> np.ndarray:
    """The first three channels of a panorama as float32 ``(H, W, 3)``; CamoError for another shape, NaN or inf."""
    from camo_base.errors import CamoError

    a = np.asarray(pano, dtype=np.float32)
    if a.ndim != 3 or a.shape[2] < 3:
        raise CamoError(f"panorama must be (H, W, 3), got shape {a.shape}")
    a = a[..., :3]
    if not np.isfinite(a).all():
        raise CamoError("panorama contains NaN or infinite values; refusing to repair it")
    return a


def repair_negative_radiance(pano: np.ndarray, radius: int = 2) -> tuple[np.ndarray, dict[str, float]]:
    """Remove the negative lobes of a linear panorama ``(H, W, 3)`` without adding energy.

    Resampling an HDR image with a sharpening filter (Lanczos; the ``@pmndrs/assets`` HDRIs were resized by
    ImageMagick and stored as lossy DWAB EXRs) rings around a bright sun: pixels next to it go negative
    (e.g. -3894 beside a 2.99e4 sun) and the ones beside those overshoot by about as much. Setting the
    negative values to 0 alone would keep the overshoot and make the sun up to 13 % brighter (``sky``).
    Here each negative value is set to 0 and its (negative) energy is taken, per channel, from the positive
    pixels in the ``(2 radius + 1)^2`` window around it, in proportion to their energy (value x solid angle): the positive
    overshoot absorbs the negative lobe, as the filter's lobes cancel in the original. A pixel never goes
    below 0; energy it cannot give is reported as ``residual_fraction`` (then the repair added that much).

    Returns the repaired panorama (every pixel away from a negative lobe is bit-exact) and figures, all
    solid-angle weighted Rec. 709 luminance: ``pixels`` with a negative channel and ``pixel_fraction``,
    ``min_value``, ``negative_energy_fraction`` (the negative energy, of the panorama's power: what clamping
    at 0 would have added), ``power_change_fraction`` (after / before - 1) and ``residual_fraction``.
    NaN or infinite values are refused with a :class:`~camo_base.errors.CamoError`, never repaired.
    """
    from camo_base.imaging import REC709_LUMA

    a = _finite_rgb(pano)
    x = a.astype(np.float64)
    w = solid_angles(a.shape[0], a.shape[1])
    e = x * w[..., None]  # energy per pixel: the redistribution conserves this, not the pixel sum
    out = np.empty_like(x)
    for ch in range(3):
        v = e[..., ch]
        pos = np.maximum(v, 0.0)
        debt = np.maximum(-v, 0.0)
        if not debt.any():
            out[..., ch] = pos
            continue
        s_pos = _box_sum(pos, radius)
        share = np.where(debt > 0, debt / np.maximum(s_pos, 1e-30), 0.0)
        take = _box_sum(share, radius)
        out[..., ch] = np.maximum(pos * (1.0 - take), 0.0)
    out /= w[..., None]
    luma = np.asarray(REC709_LUMA, np.float64)
    before = float(np.sum((x @ luma) * w))
    negative = float(-np.sum((np.minimum(x, 0.0) @ luma) * w))
    after = float(np.sum((out @ luma) * w))
    pixels = int((a < 0).any(axis=-1).sum())
    fixed = out.astype(np.float32)
    keep = ~(_box_sum((a < 0).any(axis=-1).astype(np.float64), radius) > 0)
    fixed[keep] = a[keep]  # bit-exact away from the lobes
    return fixed, {
        "pixels": pixels,
        "pixel_fraction": pixels / float(a.shape[0] * a.shape[1]),
        "min_value": float(a.min()),
        "negative_energy_fraction": negative / before if before > 0 else 0.0,
        "power_change_fraction": after / before - 1.0 if before > 0 else 0.0,
        "residual_fraction": max(0.0, after - before) / before if before > 0 else 0.0,
    }


