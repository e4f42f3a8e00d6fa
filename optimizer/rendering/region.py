"""The region of each view an object can change: its silhouette, its shadows, the light it casts or blocks.

A render with the object only needs these pixels: every other pixel equals the background render (the same
random numbers draw the same paths there, :mod:`optimizer.rendering.tracer`). A region is the union of

* the object's **coverage** (pixels it is seen in);
* a **geometric bound on hard shadows**: for every compact light (the sun, an area light, a sun-like spot of an
  envmap: the directions of the scene's emitter samples that carry most of the light, seen from the object) rays
  from points of the object's bounding box, cast away from the light, hit the receivers where the box's shadow
  falls; the convex hull of their projections and of the box's projection is filled. It holds however long the
  shadow (a low sun) and wherever it falls (ground, walls);
* the **measured change**: the object's effect ``|srgb(with) - srgb(without)|`` from a low-resolution pair of renders
  sharing their random numbers, box-filtered (3 x 3) and thresholded at ``threshold`` (sRGB, default half an 8-bit
  step): soft shadows under a sky, light the object reflects onto its surroundings, its colour on the ground;

dilated by ``margin`` (a fraction of the image's larger side). What the region leaves out is, by construction,
an effect below ``threshold`` (measured at the pilot's resolution: the margin covers what that resolution
blurs); tests/test_region.py checks a converged region render against the full frame and a sun 8 degrees
above the horizon.

Masks are ``(H, W)`` bool at the views' resolution.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from optimizer.scenes.cameras import Camera

#: An effect below this (sRGB, [0, 1]) is left to the background render: half an 8-bit step.
THRESHOLD = 0.5 / 255
#: Dilation of the region, as a fraction of the image's larger side.
MARGIN = 0.03
#: Emitter directions (seen from the object) with at least this share of the brightest one's radiance form the
#: bright set; it is a compact light (hard shadows, covered by the geometric bound) when its solid angle is below
#: ``COMPACT_SOLID_ANGLE`` sr (the sun: 7e-5 sr; the room's lamp seen from the object: ~0.3 sr; an overcast sky: ~3).
COMPACT_SHARE = 0.05
COMPACT_SOLID_ANGLE = 1.0


@dataclasses.dataclass(frozen=True)
class RegionSettings:
    resolution: float = 0.5  # the measured change is rendered at this fraction of the views' resolution
    min_size: int = 32  # ... and at least this many pixels on the shorter side
    spp: int = 8
    threshold: float = THRESHOLD
    margin: float = MARGIN
    light_samples: int = 1024  # emitter samples from the object's centre that find the compact lights


@dataclasses.dataclass
class Regions:
    masks: np.ndarray  # (V, H, W) bool
    coverage_share: list[float]  # per view: share of the frame the object covers
    bound_share: list[float]  # ... its geometric shadow bound covers
    measured_share: list[float]  # ... the measured change covers (before dilation)
    lights: list[list[float]]  # compact light directions used by the bound (towards the light)
    seconds: float = 0.0

    @property
    def share(self) -> list[float]:
        return [float(m.mean()) for m in self.masks]

    def boxes(self) -> list[tuple[int, int, int, int] | None]:
        return [bbox(m) for m in self.masks]

    def to_dict(self) -> dict:
        return {"share": [round(x, 4) for x in self.share], "coverage_share": [round(x, 4) for x in self.coverage_share],
                "bound_share": [round(x, 4) for x in self.bound_share],
                "measured_share": [round(x, 4) for x in self.measured_share],
                "lights": [[round(c, 4) for c in d] for d in self.lights], "seconds": round(self.seconds, 3)}


def bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(x0, y0, x1, y1)`` (end exclusive) of the set pixels of ``mask (H, W)``, or None when none is set."""
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def box_mask(box: tuple[int, int, int, int] | None, shape: tuple[int, int]) -> np.ndarray:
    out = np.zeros(shape, bool)
    if box is not None:
        x0, y0, x1, y1 = box
        out[y0:y1, x0:x1] = True
    return out


def dilate_px(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation of ``(H, W)`` by a disc of ``radius`` pixels."""
    if radius <= 0:
        return mask.copy()
    from scipy.ndimage import binary_dilation

    yy, xx = np.mgrid[-radius: radius + 1, -radius: radius + 1]
    return binary_dilation(mask, structure=(xx**2 + yy**2) <= radius**2)


def project(cam: Camera, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``(N, 2)`` (x right, y down; continuous, pixel centres at +0.5) of world ``points (N, 3)``
    seen by ``cam``; NaN for points behind it."""
    o = np.asarray(cam.origin, float)
    f = np.asarray(cam.target, float) - o
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(cam.up, float))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d = np.asarray(points, float) - o
    z = d @ f
    t = np.tan(np.radians(cam.fov) / 2.0)
    x = (d @ r) / np.where(z > 1e-6, z, np.nan) / t  # [-1, 1] across the width
    y = (d @ u) / np.where(z > 1e-6, z, np.nan) / t * cam.width / cam.height
    return np.stack([(x + 1.0) * 0.5 * cam.width, (1.0 - y) * 0.5 * cam.height], -1)


def fill_hull(points_px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pixels of ``shape`` inside the convex hull of pixel points ``(N, 2)`` (NaN rows ignored)."""
    from skimage.draw import polygon

    pts = points_px[np.all(np.isfinite(points_px), axis=1)]
    out = np.zeros(shape, bool)
    if len(pts) == 0:
        return out
    h, w = shape
    pts = np.clip(pts, -4.0 * max(h, w), 5.0 * max(h, w))
    try:
        from scipy.spatial import ConvexHull

        hull = pts[ConvexHull(pts).vertices]
    except Exception:  # fewer than 3 distinct points, or all on a line: their bounding box
        lo, hi = pts.min(0), pts.max(0)
        hull = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    rr, cc = polygon(hull[:, 1] - 0.5, hull[:, 0] - 0.5, shape)
    out[rr, cc] = True
    # the hull's own pixels (thin hulls rasterise to nothing)
    inside = pts[(pts[:, 0] >= 0) & (pts[:, 0] < w) & (pts[:, 1] >= 0) & (pts[:, 1] < h)].astype(int)
    out[inside[:, 1], inside[:, 0]] = True
    return out


def box_points(lo: np.ndarray, hi: np.ndarray, n: int = 4) -> np.ndarray:
    """An ``n x n x n`` grid of points spanning the box ``[lo, hi]`` (its corners included), ``(n^3, 3)``."""
    axes = [np.linspace(lo[i], hi[i], n) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def compact_lights(scene_bg, centre: np.ndarray, samples: int = 1024, share: float = COMPACT_SHARE,
                   max_solid_angle: float = COMPACT_SOLID_ANGLE, seed: int = 0) -> np.ndarray:
    """Unit directions ``(K, 3)`` from ``centre`` towards the scene's compact lights (hard shadows). Emitter samples
    (visibility ignored) whose radiance is at least ``share`` of the brightest form the bright set; it is a compact
    light when its solid angle (estimated as the sum of ``1 / (pdf N)`` over its samples) is below
    ``max_solid_angle`` sr. A sun gives one direction, an area light the spread of its own, a sky or an even
    envmap none (their shadows are soft: the measured change finds them). Near-identical directions (within ~1
    degree) are merged, at most 64 kept."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.rendering.tracer import pixel_rng

    rng = pixel_rng(dr.arange(mi.UInt32, samples), dr.zeros(mi.UInt32, samples), seed)
    it = dr.zeros(mi.Interaction3f, samples)
    it.p = mi.Point3f(*[float(c) for c in centre])
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    ds, w = scene_bg.sample_emitter_direction(it, u, False)
    pdf = np.asarray(ds.pdf)
    radiance = np.asarray(0.2126 * w[0] + 0.7152 * w[1] + 0.0722 * w[2]) * pdf
    d = np.stack([np.asarray(ds.d[i]) for i in range(3)], -1)
    ok = np.isfinite(radiance) & (radiance > 0) & (pdf > 0) & np.all(np.isfinite(d), 1)
    if not ok.any():
        return np.zeros((0, 3))
    radiance, d, pdf = radiance[ok], d[ok], pdf[ok]
    bright = radiance >= share * radiance.max()
    if float(np.sum(1.0 / (pdf[bright] * samples))) > max_solid_angle:
        return np.zeros((0, 3))
    out: list[np.ndarray] = []
    for v in d[bright][np.argsort(-radiance[bright])]:
        if all(float(v @ o) < 0.99985 for o in out):
            out.append(v)
        if len(out) >= 64:
            break
    return np.array(out)


def shadow_points(scene_bg, lo: np.ndarray, hi: np.ndarray, lights: np.ndarray, n: int = 4) -> np.ndarray:
    """Where the shadow of the box ``[lo, hi]`` falls for each light direction in ``lights``: the first hits
    ``(M, 3)`` of rays from the box's grid points cast away from the light (rays that escape give none)."""
    import mitsuba as mi

    pts = box_points(lo, hi, n)
    if len(lights) == 0:
        return np.zeros((0, 3))
    o = np.repeat(pts, len(lights), axis=0)
    d = -np.tile(lights, (len(pts), 1))
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, i].astype(np.float32)) for i in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, i].astype(np.float32)) for i in range(3)]))
    si = scene_bg.ray_intersect(ray)
    hit = np.asarray(si.is_valid())
    p = np.stack([np.asarray(si.p[i]) for i in range(3)], -1)
    return p[hit]


def geometric_bound(cam: Camera, lo: np.ndarray, hi: np.ndarray, shadow_hits: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: the convex hull of the box ``[lo, hi]``'s corners and ``shadow_hits`` seen by ``cam``."""
    pts = np.concatenate([box_points(lo, hi, 2), shadow_hits]) if len(shadow_hits) else box_points(lo, hi, 2)
    return fill_hull(project(cam, pts), (cam.height, cam.width))


def mesh_bounds(mesh) -> tuple[np.ndarray, np.ndarray]:
    """World bounding box ``(lo, hi)`` of an ``mi.Mesh``."""
    import mitsuba as mi

    v = np.asarray(mi.traverse(mesh)["vertex_positions"], dtype=np.float64).reshape(-1, 3)
    return v.min(0), v.max(0)


def measured_change(elements_fn, mesh, cams: Sequence[Camera], settings: RegionSettings, seed: int,
                    max_depth: int, rr_depth: int = 5, sure: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """``(V, h, w)`` bool at the region pass's resolution: pixels whose box-filtered (3 x 3) sRGB change with the
    object exceeds ``settings.threshold``, from renders with and without ``mesh`` that share their random numbers.

    Two passes: all pixels at ``settings.spp``, then the candidates (a filtered change above half the threshold,
    outside ``sure``, the pixels already in the region, ``(V, h, w)``) again at 8 x the spp. A sparse few paths
    that meet the object (a ground pixel's bounce) make single-pass estimates noisy far from it; the second pass
    keeps only what holds up at 8 x the samples."""
    from scipy.ndimage import uniform_filter

    from camo_base.imaging import linear_to_srgb
    from optimizer.rendering import scene as scn
    from optimizer.rendering.tracer import render_views

    low = [low_res(c, settings) for c in cams]
    V, h, w = len(low), low[0].height, low[0].width
    sc_obj = scn.build_scene(elements_fn(), mesh, [scn.batch(low, settings.spp)])
    sc_bg = scn.build_scene(elements_fn(), None, [scn.batch(low, settings.spp)])

    def change(spp, masks=None, fill=None):
        a = render_views(sc_obj, V, w, h, spp, seed, max_depth, rr_depth, masks, None if fill is None else fill[0])
        b = render_views(sc_bg, V, w, h, spp, seed, max_depth, rr_depth, masks, None if fill is None else fill[1])
        return a, b

    def filtered(a, b):
        d = np.abs(linear_to_srgb(np.clip(a, 0, None)) - linear_to_srgb(np.clip(b, 0, None))).max(-1)
        return np.stack([uniform_filter(x, 3) for x in d])

    a, b = change(settings.spp)
    d = filtered(a, b)
    sure_low = np.zeros_like(d, bool) if sure is None else np.asarray(sure, bool)
    candidates = (d > settings.threshold / 2) & ~sure_low
    if candidates.any():
        redo = np.stack([dilate_px(c, 1) for c in candidates])
        a, b = change(settings.spp * 8, redo, (a, b))
        d = filtered(a, b)
    return d > settings.threshold


def low_res(cam: Camera, settings: RegionSettings) -> Camera:
    s = max(settings.resolution, settings.min_size / max(1, min(cam.width, cam.height)))
    s = min(s, 1.0)
    return dataclasses.replace(cam, width=max(1, round(cam.width * s)), height=max(1, round(cam.height * s)))


def resize_any(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resize a bool mask to ``shape``: a target pixel is set when any source pixel it overlaps is set."""
    h, w = mask.shape
    H, W = shape
    ys = np.arange(H)
    xs = np.arange(W)
    y0 = np.floor(ys * h / H).astype(int)
    y1 = np.minimum(np.ceil((ys + 1) * h / H).astype(int), h)
    x0 = np.floor(xs * w / W).astype(int)
    x1 = np.minimum(np.ceil((xs + 1) * w / W).astype(int), w)
    # integral image for "any set pixel in the source rectangle"
    ii = np.pad(mask.astype(np.int32).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    s = ii[y1][:, x1] - ii[y0][:, x1] - ii[y1][:, x0] + ii[y0][:, x0]
    return s > 0


def resize_all(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resize a bool mask to ``shape``: a target pixel is set when every source pixel it overlaps is set."""
    return ~resize_any(~mask, shape)


def regions(elements_fn, mesh, cams: Sequence[Camera], coverage: np.ndarray | None = None,
            settings: RegionSettings = RegionSettings(), seed: int = 0, max_depth: int = 12,
            rr_depth: int = 5) -> Regions:
    """The region of every view in which ``mesh`` (an ``mi.Mesh`` placed in the scene of ``elements_fn()``) can
    change the image (module doc). ``coverage (V, H, W)``: the object's coverage when already known (else it is
    ray cast)."""
    import time

    from optimizer.rendering import scene as scn
    from optimizer.rendering.render import coverage_and_depth

    t0 = time.perf_counter()
    sc_bg = scn.build_scene(elements_fn())
    lo, hi = mesh_bounds(mesh)
    lights = compact_lights(sc_bg, (lo + hi) / 2.0, settings.light_samples, seed=seed)
    hits = shadow_points(sc_bg, lo, hi, lights)
    if coverage is None:
        sc_obj = scn.build_scene(elements_fn(), mesh)
        coverage = np.stack([coverage_and_depth(sc_obj, c, mesh)[0] for c in cams])
    bounds = [geometric_bound(c, lo, hi, hits) for c in cams]
    low = [low_res(c, settings) for c in cams]
    sure = [resize_all((coverage[v] > 0) | bounds[v], (low[v].height, low[v].width)) for v in range(len(cams))]
    measured = measured_change(elements_fn, mesh, cams, settings, seed, max_depth, rr_depth, sure)
    masks, cov_s, bound_s, meas_s = [], [], [], []
    for v, c in enumerate(cams):
        shape = (c.height, c.width)
        cov = coverage[v] > 0
        bound = bounds[v]
        meas = resize_any(measured[v], shape)
        px = max(1, round(settings.margin * max(shape)))
        masks.append(dilate_px(cov | bound | meas, px))
        cov_s.append(float(cov.mean()))
        bound_s.append(float(bound.mean()))
        meas_s.append(float(meas.mean()))
    return Regions(np.stack(masks), cov_s, bound_s, meas_s, [list(map(float, d)) for d in lights],
                   time.perf_counter() - t0)
