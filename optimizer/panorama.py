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

    ``elements`` are scene-element dicts (see :mod:`optimizer.environments`).
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
