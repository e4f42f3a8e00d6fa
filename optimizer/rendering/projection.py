"""Texel projection shared by the image-projection baselines (Owens 2014, 2D diffusion, GANmouflage bake).

Steps, all in NumPy except the ray casts (Mitsuba):

1. :func:`rasterise_texels` -- every texel of the ``R x R`` atlas whose centre
   ``((col + 0.5) / R, (row + 0.5) / R)`` lies inside a UV triangle gets that
   triangle's 3D surface point (barycentric interpolation of the world
   positions), its face id and barycentrics, the geometric face normal and the
   interpolated vertex normal. Row 0 of the map is ``v = 0`` (Mitsuba's bitmap
   convention, see :mod:`optimizer.scenes.mesh`). Texels whose centre lies in no
   triangle are "off-chart"; :func:`bake` pads them afterwards.
2. :func:`project` -- world points to pixel coordinates of a :class:`Camera`
   exactly as Mitsuba's ``perspective`` sensor built by
   :func:`optimizer.rendering.scene.perspective` maps them (``look_at`` frame, x field of
   view; pixel ``(i, j)`` covers ``[j, j+1) x [i, i+1)``).
3. :func:`visible` -- a surface point is visible in a view when it projects
   inside the image, faces the camera (geometric normal, the side Mitsuba's
   winding gives, oriented like the vertex normals) and a ray from the camera
   centre towards it, cast into the *full* scene (environment, occluders and
   the object), first hits the object within ``eps`` of the point.
4. :func:`sample_bilinear` -- the colour of an image at the projection
   (bilinear between pixel centres, clamped at the border).
5. :func:`bake` -- per-texel colours into an ``(R, R, 3)`` map: surface texels
   that no view saw take the colour of the nearest (in 3D) texel that got one
   (e.g. the bottom resting on the ground); off-chart texels take the colour
   of the nearest on-chart texel in the atlas (dilation padding to the whole
   map, so bilinear lookups at chart borders never blend in a foreign colour).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from optimizer.scenes.cameras import Camera


@dataclasses.dataclass
class TexelSurface:
    """The on-chart texels of an ``R x R`` atlas and their surface points (world space)."""

    resolution: int
    index: np.ndarray  # (N,) flat texel index row * R + col
    face: np.ndarray  # (N,) face of the UV mesh holding the texel centre
    bary: np.ndarray  # (N, 3) float32 barycentrics in that face
    points: np.ndarray  # (N, 3) float32 world positions
    normals: np.ndarray  # (N, 3) float32 unit geometric (face) normals, outward
    shading_normals: np.ndarray  # (N, 3) float32 unit interpolated vertex normals

    @property
    def rows(self) -> np.ndarray:
        return self.index // self.resolution

    @property
    def cols(self) -> np.ndarray:
        return self.index % self.resolution

    def __len__(self) -> int:
        return int(len(self.index))


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.maximum(n, 1e-20)


def face_normals(positions: np.ndarray, faces: np.ndarray, vertex_normals: np.ndarray | None = None) -> np.ndarray:
    """Unit geometric normals ``(F, 3)`` (winding order); flipped where they disagree with ``vertex_normals``."""
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    n = _unit(np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]))
    if vertex_normals is not None:
        vn = np.asarray(vertex_normals, np.float64)[f].sum(1)
        n = np.where((np.einsum("ij,ij->i", n, vn) < 0)[:, None], -n, n)
    return n


def barycentric_points(positions: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """``sum_k bary[:, k] * positions[faces[face, k]]`` as float32 ``(N, 3)``."""
    tri = np.asarray(positions, np.float64)[np.asarray(faces)[face]]  # (N, 3, 3)
    return np.einsum("nk,nkc->nc", np.asarray(bary, np.float64), tri).astype(np.float32)


def rasterise_texels(positions: np.ndarray, faces: np.ndarray, uvs: np.ndarray, resolution: int,
                     vertex_normals: np.ndarray | None = None) -> TexelSurface:
    """Texels of an ``R x R`` atlas whose centres fall inside a UV triangle (see the module doc).

    ``positions (Nu, 3)`` world positions, ``faces (F, 3)`` and ``uvs (Nu, 2)``
    of the UV mesh; ``vertex_normals (Nu, 3)`` (default: area-weighted normals
    of ``positions``) orient the face normals and give the shading normals. A
    texel centre on an edge shared by two triangles goes to the lower face id.
    """
    R = int(resolution)
    pos = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    if vertex_normals is None:
        from optimizer.scenes.mesh import vertex_normals as _vn

        vertex_normals = _vn(pos, f)
    vn = _unit(np.asarray(vertex_normals, np.float64))
    # Texel-centre coordinates: texel (row, col) has its centre at x = col, y = row.
    uv = np.asarray(uvs, np.float64)[f] * R - 0.5  # (F, 3, 2)
    x0, y0 = uv[:, 0, 0], uv[:, 0, 1]
    e1 = uv[:, 1] - uv[:, 0]
    e2 = uv[:, 2] - uv[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-12
    xmin = np.clip(np.ceil(uv[..., 0].min(1) - 1e-9), 0, R - 1).astype(np.int64)
    xmax = np.clip(np.floor(uv[..., 0].max(1) + 1e-9), 0, R - 1).astype(np.int64)
    ymin = np.clip(np.ceil(uv[..., 1].min(1) - 1e-9), 0, R - 1).astype(np.int64)
    ymax = np.clip(np.floor(uv[..., 1].max(1) + 1e-9), 0, R - 1).astype(np.int64)
    nx = np.where(ok, xmax - xmin + 1, 0).clip(0)
    ny = np.where(ok, ymax - ymin + 1, 0).clip(0)
    count = nx * ny
    total = int(count.sum())
    fid = np.repeat(np.arange(len(f)), count)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    k = np.arange(total) - start[fid]
    cx = xmin[fid] + k % np.maximum(nx[fid], 1)
    cy = ymin[fid] + k // np.maximum(nx[fid], 1)
    dx, dy = cx - x0[fid], cy - y0[fid]
    inv = 1.0 / np.where(ok, det, 1.0)[fid]
    b1 = (dx * e2[fid, 1] - dy * e2[fid, 0]) * inv
    b2 = (e1[fid, 0] * dy - e1[fid, 1] * dx) * inv
    b0 = 1.0 - b1 - b2
    tol = -1e-7
    inside = (b0 >= tol) & (b1 >= tol) & (b2 >= tol)
    fid, cx, cy = fid[inside], cx[inside], cy[inside]
    bary = np.clip(np.stack([b0[inside], b1[inside], b2[inside]], 1), 0.0, 1.0)
    bary /= bary.sum(1, keepdims=True)
    index = cy * R + cx
    # One face per texel: the lowest face id (np.unique keeps the first occurrence of the sorted order).
    order = np.lexsort((fid, index))
    index, fid, bary = index[order], fid[order], bary[order]
    first = np.ones(len(index), bool)
    first[1:] = index[1:] != index[:-1]
    index, fid, bary = index[first], fid[first], bary[first]
    points = barycentric_points(pos, f, fid, bary)
    fn = face_normals(pos, f, vn)[fid].astype(np.float32)
    sn = _unit(np.einsum("nk,nkc->nc", bary, vn[f[fid]])).astype(np.float32)
    return TexelSurface(R, index.astype(np.int64), fid.astype(np.int64), bary.astype(np.float32), points, fn, sn)


# --- cameras -----------------------------------------------------------------


def camera_frame(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Mitsuba's ``look_at`` frame: origin, left (+x), up (+y), forward (+z), world space."""
    o = np.asarray(cam.origin, np.float64)
    d = _unit(np.asarray(cam.target, np.float64) - o)
    left = _unit(np.cross(np.asarray(cam.up, np.float64), d))
    up = np.cross(d, left)
    return o, left, up, d


def project(points: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates ``x, y`` (continuous; pixel ``(i, j)`` covers ``[j, j+1) x [i, i+1)``) and depth ``z``.

    ``z`` is the distance along the view axis (``<= 0`` behind the camera).
    Matches Mitsuba's perspective sensor with ``fov_axis = "x"``.
    """
    o, left, up, fwd = camera_frame(cam)
    q = np.asarray(points, np.float64) - o
    xc, yc, zc = q @ left, q @ up, q @ fwd
    t = math.tan(math.radians(cam.fov) / 2.0)
    zs = np.where(np.abs(zc) < 1e-12, 1e-12, zc)
    aspect = cam.width / cam.height
    x = cam.width * (0.5 - 0.5 * xc / (zs * t))
    y = cam.height * (0.5 - 0.5 * aspect * yc / (zs * t))
    return x, y, zc


def in_frame(x: np.ndarray, y: np.ndarray, z: np.ndarray, cam: Camera) -> np.ndarray:
    return (z > 0) & (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)


def to_camera(vectors: np.ndarray, cam: Camera) -> np.ndarray:
    """Directions ``(N, 3)`` in the camera frame with x right, y down, z forward (image axes)."""
    _, left, up, fwd = camera_frame(cam)
    v = np.asarray(vectors, np.float64)
    return np.stack([-(v @ left), -(v @ up), v @ fwd], -1).astype(np.float32)


# --- visibility --------------------------------------------------------------


def object_scene(env, positions: np.ndarray, faces: np.ndarray, uvs: np.ndarray):
    """The full scene (environment + the object) for visibility rays; returns ``(scene, object_shape)``."""
    from optimizer.rendering import scene as scn

    obj = scn.object_mesh(positions, faces, uvs, {"type": "diffuse"})
    return scn.build_scene(env.build(), obj), obj


def first_hits(scene, origin, points: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays from ``origin`` towards ``points``; returns (hit is ``shape``, hit distance; inf on a miss)."""
    import drjit as dr
    import mitsuba as mi

    p = np.asarray(points, np.float64)
    o = np.asarray(origin, np.float64)
    d = _unit(p - o).astype(np.float32)
    n = len(p)
    if n == 0:
        return np.zeros(0, bool), np.zeros(0, np.float32)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(n, o[k], np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(np.ascontiguousarray(d[:, k])) for k in range(3)]))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    on = valid & (si.shape == mi.ShapePtr(shape))
    t = dr.select(valid, si.t, dr.inf)
    return np.asarray(on, bool), np.asarray(t, np.float32)


def visible(scene, shape, cam: Camera, points: np.ndarray, normals: np.ndarray, eps: float) -> np.ndarray:
    """Bool ``(N,)``: in frame, front-facing and the first hit of the camera ray (occluders included)."""
    x, y, z = project(points, cam)
    ok = in_frame(x, y, z, cam)
    o = np.asarray(cam.origin, np.float64)
    to_cam = o - np.asarray(points, np.float64)
    ok &= np.einsum("ij,ij->i", np.asarray(normals, np.float64), to_cam) > 0
    idx = np.nonzero(ok)[0]
    if len(idx):
        on, t = first_hits(scene, o, points[idx], shape)
        dist = np.linalg.norm(to_cam[idx], axis=1)
        ok[idx] = on & (np.abs(t - dist) <= eps)
    return ok


def sample_bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``img (H, W, C)`` at continuous pixel coordinates (centres at ``j + 0.5``), clamped at the border."""
    h, w = img.shape[:2]
    fx = np.clip(np.asarray(x, np.float64) - 0.5, 0.0, w - 1.0)
    fy = np.clip(np.asarray(y, np.float64) - 0.5, 0.0, h - 1.0)
    x0 = np.floor(fx).astype(np.int64)
    y0 = np.floor(fy).astype(np.int64)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    ax = (fx - x0)[:, None]
    ay = (fy - y0)[:, None]
    top = img[y0, x0] * (1 - ax) + img[y0, x1] * ax
    bot = img[y1, x0] * (1 - ax) + img[y1, x1] * ax
    return (top * (1 - ay) + bot * ay).astype(np.float32)


@dataclasses.dataclass
class Observations:
    """What every training view shows at every texel."""

    visible: np.ndarray  # (V, N) bool
    x: np.ndarray  # (V, N) float32 pixel coordinates of the projection
    y: np.ndarray  # (V, N)
    cos: np.ndarray  # (V, N) float32 |cos| between the face normal and the direction to the camera

    def sample(self, images: np.ndarray | Sequence[np.ndarray], view: int | None = None) -> np.ndarray:
        """Colours ``(V, N, C)`` (or ``(N, C)`` for one ``view``) of per-view images at the projections."""
        if view is not None:
            return sample_bilinear(images[view], self.x[view], self.y[view])
        return np.stack([sample_bilinear(images[v], self.x[v], self.y[v]) for v in range(len(self.x))])


def observe(scene, shape, cams: Sequence[Camera], surface: TexelSurface, eps: float) -> Observations:
    """Visibility and projection of every texel in every view."""
    vis, xs, ys, cs = [], [], [], []
    for cam in cams:
        x, y, _ = project(surface.points, cam)
        vis.append(visible(scene, shape, cam, surface.points, surface.normals, eps))
        xs.append(x.astype(np.float32))
        ys.append(y.astype(np.float32))
        to_cam = _unit(np.asarray(cam.origin, np.float64) - surface.points)
        cs.append(np.abs(np.einsum("ij,ij->i", to_cam, surface.normals)).astype(np.float32))
    return Observations(np.stack(vis), np.stack(xs), np.stack(ys), np.stack(cs))


# --- baking ------------------------------------------------------------------


def bake(surface: TexelSurface, colours: np.ndarray, assigned: np.ndarray, fallback=(0.5, 0.5, 0.5)) -> np.ndarray:
    """An ``(R, R, 3)`` float32 map from per-texel ``colours (N, 3)`` where ``assigned (N,)`` (module doc, step 5)."""
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import cKDTree

    R = surface.resolution
    c = np.asarray(colours, np.float32).copy()
    a = np.asarray(assigned, bool)
    if not a.any():
        c[:] = np.asarray(fallback, np.float32)
    elif not a.all():
        _, j = cKDTree(surface.points[a]).query(surface.points[~a], k=1)
        c[~a] = c[a][j]
    out = np.zeros((R * R, 3), np.float32)
    out[surface.index] = c
    on = np.zeros(R * R, bool)
    on[surface.index] = True
    if len(surface) and not on.all():
        _, (iy, ix) = distance_transform_edt(~on.reshape(R, R), return_indices=True)
        out = out.reshape(R, R, 3)[iy, ix]
    return np.clip(out.reshape(R, R, 3), 0.0, 1.0)


