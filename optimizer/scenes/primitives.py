"""Built-in objects of everyday shape, built procedurally with trimesh.

Every builder returns a fresh :class:`trimesh.Trimesh` in the toolkit's frame:
**Z is up**, the object stands on the ground plane ``z = 0`` (its lowest point
is exactly at 0), it is centred at ``x = y = 0`` (bounding-box centre) and its
largest bounding-box side is exactly ``1.0`` scene unit. Faces are wound
counter-clockwise seen from outside (outward normals).

=============  ===========================================================  ==========
name           what                                                         watertight
=============  ===========================================================  ==========
utility_box    street utility cabinet: rounded box with an overhanging roof  yes
backpack       rounded body, front pocket, top flap and a carry handle       yes
chair          seat, four legs, two back posts, backrest (intersecting        per part
               rounded-box parts, concatenated, not booleaned)
vase           lathe profile with a belly, neck and flared lip; open mouth,  yes
               closed bottom, walls with thickness
teapot         lathe body with lid knob, spout and handle                    yes
torus          ring lying flat on the ground                                 yes
bollard        street bollard: cylinder, ring band, domed cap                yes
duck           rubber-duck-like blob with a flat bottom                      yes
=============  ===========================================================  ==========

"yes" means one closed 2-manifold surface (``mesh.is_watertight`` and a
positive volume). The chair is a concatenation of closed parts that intersect
each other: every edge still has exactly two faces (so ``is_watertight`` is
True), but the surface self-intersects; :data:`SINGLE_VOLUME` lists the ones
that are a clean single volume. The multi-part objects are merged with
``manifold3d`` booleans when it is installed; without it they fall back to a
concatenation of closed parts (still ``is_watertight``, but intersecting).

Use :func:`make_primitive` (raises :class:`~camo_base.errors.CamoError` for
an unknown name) or the :data:`PRIMITIVES` registry.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import trimesh

from camo_base.errors import CamoError

__all__ = [
    "PRIMITIVES",
    "SINGLE_VOLUME",
    "backpack",
    "bollard",
    "chair",
    "duck",
    "make_primitive",
    "primitive_names",
    "teapot",
    "torus",
    "utility_box",
    "vase",
]


# --------------------------------------------------------------------------- helpers


def _place(mesh: trimesh.Trimesh, size: float = 1.0) -> trimesh.Trimesh:
    """Scale so the largest bounding-box side is ``size``; centre x/y at 0; lowest point on z = 0."""
    mesh = mesh.copy()
    lo, hi = mesh.bounds
    scale = size / float(np.max(hi - lo))
    centre = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    mesh.vertices = (mesh.vertices - centre) * scale
    # exact zero for the lowest point despite rounding
    mesh.vertices[:, 2] -= mesh.vertices[:, 2].min()
    return mesh


def _finish(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Drop degenerate faces, orient outward, place on the ground.

    Vertices are not merged: the parts are welded already, and merging
    coincident vertices of two different (concatenated) parts would create
    non-manifold edges.
    """
    mesh = trimesh.Trimesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), process=False)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if mesh.is_watertight:
        trimesh.repair.fix_normals(mesh, multibody=True)
    return _place(mesh)


def _union(parts: Sequence[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Boolean union with manifold3d; concatenation of the (closed) parts when it is unavailable."""
    try:
        out = trimesh.boolean.union(list(parts), engine="manifold")
        if isinstance(out, trimesh.Trimesh) and len(out.faces) and out.is_watertight:
            return out
    except Exception:  # manifold3d missing or failed: keep the parts
        pass
    return trimesh.util.concatenate(list(parts))


def _difference(a: trimesh.Trimesh, b: trimesh.Trimesh) -> trimesh.Trimesh:
    try:
        out = trimesh.boolean.difference([a, b], engine="manifold")
        if isinstance(out, trimesh.Trimesh) and len(out.faces) and out.is_watertight:
            return out
    except Exception:
        pass
    return a


def _axis_coords(half: float, radius: float, seg: float) -> np.ndarray:
    """1-D grid for one axis of a rounded box: steps of about ``seg`` on the flat part, and steps of
    about ``seg`` of arc in the rounding bands (``inner + r tan(theta)``, theta uniform in [0, pi/4])."""
    inner = half - radius
    n_flat = max(1, int(np.ceil(2 * inner / seg)))
    n_round = max(1, int(np.ceil(np.pi / 4 * radius / seg)))
    flat = np.linspace(-inner, inner, n_flat + 1)
    band = inner + radius * np.tan(np.linspace(0.0, np.pi / 4, n_round + 1))[1:]
    return np.concatenate([-band[::-1], flat, band])


def _grid_face(c1: np.ndarray, c2: np.ndarray, axis: int, sign: float, const: float):
    a1, a2 = (axis + 1) % 3, (axis + 2) % 3
    u, v = np.meshgrid(c1, c2, indexing="ij")
    pts = np.zeros((u.size, 3))
    pts[:, a1] = u.ravel()
    pts[:, a2] = v.ravel()
    pts[:, axis] = sign * const
    n1, n2 = len(c1), len(c2)
    i, j = np.meshgrid(np.arange(n1 - 1), np.arange(n2 - 1), indexing="ij")
    k = (i * n2 + j).ravel()
    # (i,j) -> (i+1,j) -> (i+1,j+1) -> (i,j+1) is counter-clockwise in the (a1, a2) plane,
    # whose normal a1 x a2 is +axis
    quads = np.stack([k, k + n2, k + n2 + 1, k + 1], axis=1)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    if sign < 0:
        tris = tris[:, ::-1]
    return pts, tris


def rounded_box(extents: Sequence[float], radius: float, seg: float = 0.02) -> trimesh.Trimesh:
    """Closed box of the given full ``extents`` whose edges and corners are rounded with ``radius``.

    Built by projecting a tensor-product grid on the box surface onto the
    offset surface of the inner box (``p = c + r (q - c) / |q - c|``,
    ``c = clip(q)``), so it is watertight, centred at the origin; grid steps
    are about ``seg`` long on the flat parts and along the rounded ones.
    """
    half = np.asarray(extents, dtype=np.float64) / 2.0
    radius = float(min(radius, 0.999 * half.min()))
    coords = [_axis_coords(h, radius, seg) for h in half]
    verts, faces, offset = [], [], 0
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1.0, -1.0):
            p, t = _grid_face(coords[a1], coords[a2], axis, sign, half[axis])
            verts.append(p)
            faces.append(t + offset)
            offset += len(p)
    q = np.concatenate(verts)
    f = np.concatenate(faces)
    # weld the shared face borders (identical coordinates by construction)
    key = np.round(q / (half.max() * 1e-9)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    q = q[first]
    f = inverse.reshape(-1)[f]
    inner = half - radius
    c = np.clip(q, -inner, inner)
    d = q - c
    n = np.linalg.norm(d, axis=1, keepdims=True)
    p = c + radius * d / np.maximum(n, 1e-300)
    mesh = trimesh.Trimesh(p, f, process=False)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    return mesh


def _ellipsoid(radii: Sequence[float], centre: Sequence[float], subdivisions: int = 3) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    m.vertices = m.vertices * np.asarray(radii, dtype=np.float64) + np.asarray(centre, dtype=np.float64)
    return m


def _resample_polyline(points: np.ndarray, seg: float) -> np.ndarray:
    """Insert points so that no segment of the polyline is longer than ``seg``."""
    out = [points[:1]]
    for p, q in zip(points[:-1], points[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / seg)))
        t = np.linspace(0.0, 1.0, n + 1)[1:, None]
        out.append(p + t * (q - p))
    return np.concatenate(out)


def _lathe(profile: np.ndarray, sections: int | None = None, seg: float = 0.02) -> trimesh.Trimesh:
    """Revolve an (r, z) profile about the Z axis; a profile running axis -> outside -> axis is closed.

    The profile is resampled to steps of at most ``seg``; by default the
    number of sections gives steps of about ``seg`` around the widest circle,
    so the triangles are not long slivers.
    """
    prof = _resample_polyline(np.asarray(profile, dtype=np.float64), seg)
    if sections is None:
        sections = max(32, int(np.ceil(2 * np.pi * prof[:, 0].max() / seg)))
    m = trimesh.creation.revolve(prof, sections=sections)
    if m.volume < 0:
        m.invert()
    return m


def _smooth_profile(knots_z: Sequence[float], knots_r: Sequence[float], n: int) -> np.ndarray:
    """Radius as a smooth (monotone cubic) function of height, sampled at ``n`` heights."""
    from scipy.interpolate import PchipInterpolator

    z = np.linspace(knots_z[0], knots_z[-1], n)
    r = PchipInterpolator(knots_z, knots_r)(z)
    return np.column_stack([r, z])


# --------------------------------------------------------------------------- objects


def utility_box() -> trimesh.Trimesh:
    """Street utility cabinet: a tall rounded box (0.7 x 0.4 x 1.0) with a slightly overhanging roof."""
    body = rounded_box((0.70, 0.40, 0.94), radius=0.03)
    body.apply_translation((0, 0, 0.47))
    roof = rounded_box((0.76, 0.46, 0.06), radius=0.02)
    roof.apply_translation((0, 0, 0.97))
    plinth = rounded_box((0.66, 0.36, 0.06), radius=0.01)
    plinth.apply_translation((0, 0, 0.03))
    return _finish(_union([body, roof, plinth]))


def backpack() -> trimesh.Trimesh:
    """Backpack: soft rounded body, a front pocket, a top flap and a carry handle, merged into one mesh.

    The front of the pack faces -y.
    """
    body = rounded_box((0.62, 0.32, 0.92), radius=0.14)
    body.apply_translation((0, 0, 0.46))
    pocket = rounded_box((0.46, 0.14, 0.32), radius=0.06)
    pocket.apply_translation((0, -0.17, 0.26))
    flap = rounded_box((0.58, 0.14, 0.26), radius=0.06)
    flap.apply_transform(trimesh.transformations.rotation_matrix(np.radians(-12), (1, 0, 0)))
    flap.apply_translation((0, -0.11, 0.78))
    handle = trimesh.creation.torus(major_radius=0.07, minor_radius=0.018, major_sections=32, minor_sections=12)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    handle.apply_translation((0, 0.02, 0.93))
    return _finish(_union([body, pocket, flap, handle]))


def chair() -> trimesh.Trimesh:
    """Chair made of closed parts (seat, four square legs, two back posts, backrest), concatenated.

    Every part is a slightly rounded box; parts intersect where they meet.
    The backrest is on the +y side.
    """
    def part(extents, centre, radius=0.006):
        p = rounded_box(extents, radius=radius, seg=0.02)
        p.apply_translation(centre)
        return p

    parts = [part((0.46, 0.46, 0.05), (0, 0, 0.445), radius=0.01)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(part((0.04, 0.04, 0.44), (sx * 0.195, sy * 0.195, 0.22)))
    for sx in (-1, 1):
        parts.append(part((0.04, 0.04, 0.56), (sx * 0.195, 0.205, 0.72)))
    parts.append(part((0.44, 0.03, 0.26), (0, 0.205, 0.86)))
    return _finish(trimesh.util.concatenate(parts))


def vase(sections: int | None = None) -> trimesh.Trimesh:
    """Vase from a lathe profile: foot, belly, neck, flared lip; open mouth, closed bottom, 2 % walls."""
    outer = _smooth_profile([0.0, 0.08, 0.35, 0.65, 0.85, 1.0], [0.16, 0.22, 0.30, 0.17, 0.12, 0.17], 40)
    wall = 0.02
    inner = outer[::-1].copy()
    inner[:, 0] = np.maximum(inner[:, 0] - wall, 0.01)
    inner = inner[inner[:, 1] >= 0.04]
    profile = np.concatenate([[[0.0, 0.0]], outer, inner, [[0.0, inner[-1, 1]]]])
    return _finish(_lathe(profile, sections, seg=0.03))


def teapot(sections: int | None = None) -> trimesh.Trimesh:
    """Teapot-like object: lathe body with lid and knob, a tapered spout (-x) and a handle (+x)."""
    body_prof = _smooth_profile([0.0, 0.05, 0.25, 0.45, 0.55], [0.20, 0.27, 0.33, 0.24, 0.16], 30)
    lid = np.array([[0.16, 0.57], [0.12, 0.61], [0.05, 0.63], [0.035, 0.66], [0.05, 0.70], [0.0, 0.72]])
    body = _lathe(np.concatenate([[[0.0, 0.0]], body_prof, lid]), sections)
    spout = trimesh.creation.cone(radius=0.07, height=0.42, sections=24)
    # truncate the cone tip so the spout has an opening rim, not a needle
    spout = _difference(spout, trimesh.creation.box((1, 1, 1), trimesh.transformations.translation_matrix((0, 0, 0.8))))
    spout.apply_transform(trimesh.transformations.rotation_matrix(np.radians(-50), (0, 1, 0)))
    spout.apply_translation((-0.20, 0, 0.18))
    handle = trimesh.creation.torus(major_radius=0.13, minor_radius=0.025, major_sections=40, minor_sections=12)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    handle.apply_translation((0.30, 0, 0.30))
    return _finish(_union([body, spout, handle]))


def torus(major_radius: float = 0.35, minor_radius: float = 0.15) -> trimesh.Trimesh:
    """Ring lying flat on the ground (axis = Z)."""
    m = trimesh.creation.torus(
        major_radius=major_radius, minor_radius=minor_radius, major_sections=64, minor_sections=32
    )
    return _finish(m)


def bollard(sections: int | None = None) -> trimesh.Trimesh:
    """Street bollard: cylinder with a raised ring band and a domed cap."""
    r = 0.12
    prof = [[0.0, 0.0], [r, 0.0], [r, 0.66], [r + 0.015, 0.68], [r + 0.015, 0.74], [r, 0.76], [r, 0.84]]
    theta = np.linspace(0.0, np.pi / 2, 12)[1:]
    cap = np.column_stack([r * np.cos(theta), 0.84 + 0.6 * r * np.sin(theta)])
    cap[-1, 0] = 0.0
    return _finish(_lathe(np.concatenate([prof, cap]), sections))


def duck() -> trimesh.Trimesh:
    """Rubber-duck-like blob: ellipsoid body, head, beak and tail, flat bottom; beak points to +x."""
    body = _ellipsoid((0.42, 0.30, 0.24), (0.0, 0.0, 0.24))
    head = _ellipsoid((0.17, 0.17, 0.17), (0.26, 0.0, 0.55))
    beak = _ellipsoid((0.10, 0.07, 0.035), (0.43, 0.0, 0.53), subdivisions=2)
    tail = _ellipsoid((0.17, 0.09, 0.07), (0.0, 0.0, 0.0), subdivisions=2)
    tail.apply_transform(trimesh.transformations.rotation_matrix(np.radians(40), (0, 1, 0)))
    tail.apply_translation((-0.36, 0.0, 0.36))
    blob = _union([body, head, beak, tail])
    floor = trimesh.creation.box((2, 2, 1), trimesh.transformations.translation_matrix((0, 0, 0.04 - 0.5)))
    return _finish(_difference(blob, floor))


# --------------------------------------------------------------------------- registry

#: name -> builder; every builder takes no argument and returns a new mesh
PRIMITIVES: dict[str, Callable[[], trimesh.Trimesh]] = {
    "utility_box": utility_box,
    "backpack": backpack,
    "chair": chair,
    "vase": vase,
    "teapot": teapot,
    "torus": torus,
    "bollard": bollard,
    "duck": duck,
}

#: primitives that are one closed, non-self-intersecting volume (when manifold3d is installed)
SINGLE_VOLUME: frozenset[str] = frozenset(
    {"utility_box", "backpack", "vase", "teapot", "torus", "bollard", "duck"}
)


def primitive_names() -> list[str]:
    return sorted(PRIMITIVES)


def make_primitive(name: str) -> trimesh.Trimesh:
    """Build the built-in object ``name``; :class:`CamoError` for an unknown name."""
    try:
        builder = PRIMITIVES[name]
    except (KeyError, TypeError):
        raise CamoError(
            f"unknown built-in object {name!r}; choose one of: {', '.join(primitive_names())}"
        ) from None
    return builder()
