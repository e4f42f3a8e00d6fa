"""Object pose: the paper's model matrix (Eq. 2-3).

``T_orig = T_t R S`` places the normalised mesh (largest side 1, base centred
at the origin on z = 0) in the scene; optimisation adds a translation offset
``dt`` and a rotation ``theta_z`` about the up axis:
``T_new = T_dt T_t R_z(theta_z) R S``. ``dt`` is clipped to a fraction (5 %) of
the object's size; ``dz = 0`` unless vertical motion is enabled.
All matrices are 4x4 float64 NumPy arrays; angles in radians unless named ``_deg``.
"""

from __future__ import annotations

import math

import numpy as np


def translation(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def scaling(s: float) -> np.ndarray:
    return np.diag([s, s, s, 1.0])


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def euler_xyz_deg(r) -> np.ndarray:
    """Rotation R from XYZ Euler angles in degrees (x applied first)."""
    return rot_z(math.radians(r[2])) @ rot_y(math.radians(r[1])) @ rot_x(math.radians(r[0]))


def model_matrix(size: float, rotation_deg, translation_xyz, dt=(0.0, 0.0, 0.0), theta_z: float = 0.0) -> np.ndarray:
    """``T_dt T_t R_z(theta_z) R S`` (Eq. 3); with ``dt = 0, theta_z = 0`` it is ``T_orig`` (Eq. 2)."""
    return translation(dt) @ translation(translation_xyz) @ rot_z(theta_z) @ euler_xyz_deg(rotation_deg) @ scaling(size)


def clip_offset(dt, size: float, fraction: float = 0.05, allow_z: bool = False) -> np.ndarray:
    """Clip each component of ``dt`` to ``+-fraction * size``; ``dz`` forced to 0 unless ``allow_z``."""
    lim = fraction * size
    out = np.clip(np.asarray(dt, dtype=np.float64), -lim, lim)
    if not allow_z:
        out[2] = 0.0
    return out


def transform_points(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a 4x4 matrix to points ``(N, 3)``."""
    return (p @ m[:3, :3].T + m[:3, 3]).astype(p.dtype)
