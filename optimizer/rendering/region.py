"""Render only what an object can change: its silhouette, its shadows, the light it casts or blocks.

A render with the object needs only the pixels the object changes: every other pixel equals the background
render of the same seed (the same random numbers draw the same paths there, :mod:`optimizer.rendering.tracer`).
:func:`render_region` renders, at full resolution and the stage's spp,

1. a **start**: the object's coverage and a **geometric bound on its hard shadows** -- for every compact light
   (the sun, an area light, a sun-like spot of an envmap, a directional light: the emitter samples seen from the
   object that carry most of the light in a small solid angle, :func:`compact_lights`) rays from points of the
   object's bounding box cast away from the light hit the receivers where the box's shadow falls, and the convex
   hull of their projections and of the box's projection is filled. It holds however long the shadow (a low sun)
   and wherever it falls (ground, walls) -- dilated by ``margin`` (a fraction of the image's larger side);
2. then **grows** it: wherever the rendered set's outer border shows a change ``srgb(with) - srgb(without)``
   (signed, box-filtered over the rendered pixels, 3 x 3, then its magnitude: :func:`change`) above ``threshold`` (default half an 8-bit step), a ring around
   those border pixels is rendered too (``ring`` of the image's larger side, doubling at every step; once the region
   holds 3/4 of the frames, the rest), until the border is quiet: soft shadows under a sky, light the object
   reflects onto its surroundings, its colour on the ground.

Every rendered pixel is exact; what is left out changes the image by less than ``threshold`` at the border it was
grown to (a change that is not connected to the object's region -- its reflection in a distant mirror -- is not
searched for). tests/test_region.py checks a converged region render against the full frame under a sun 8 degrees
above the horizon. Masks are ``(H, W)`` bool at the views' resolution.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from optimizer.scenes.cameras import Camera

#: An effect below this (sRGB, [0, 1]) is left to the background render: half an 8-bit step.
THRESHOLD = 0.5 / 255
#: Dilation of the region's start, as a fraction of the image's larger side.
MARGIN = 0.03
#: What the first growth step adds around a border pixel that still changes, same units; each further step
#: doubles it.
RING = 0.06
#: Once the region holds this share of the frames and still grows, the rest is rendered in one step.
FULL_SHARE = 0.75
#: Emitter directions (seen from the object) with at least this share of the brightest one's radiance form the
#: bright set; it is a compact light (hard shadows, covered by the geometric bound) when its solid angle is below
#: ``COMPACT_SOLID_ANGLE`` sr (the sun: 7e-5 sr; the room's lamp seen from the object: ~0.3 sr; an overcast sky: ~3).
COMPACT_SHARE = 0.05
COMPACT_SOLID_ANGLE = 1.0


@dataclasses.dataclass(frozen=True)
class RegionSettings:
    threshold: float = THRESHOLD  # sRGB change that keeps a region growing
    margin: float = MARGIN  # dilation of the start, a fraction of the image's larger side
    ring: float = RING  # what one growth step adds around a changing border pixel, same units
    max_steps: int = 8
    light_samples: int = 1024  # emitter samples from the object's centre that find the compact lights


@dataclasses.dataclass
class Regions:
    masks: np.ndarray  # (V, H, W) bool: the pixels rendered
    coverage_share: list[float]  # per view: share of the frame the object covers
    bound_share: list[float]  # ... its geometric shadow bound covers
    steps: int  # growth steps taken
    lights: list[list[float]]  # compact light directions used by the bound (towards the light)
    seconds: float = 0.0

    @property
    def share(self) -> list[float]:
        return [float(m.mean()) for m in self.masks]

    def to_dict(self) -> dict:
        return {"share": [round(x, 4) for x in self.share], "coverage_share": [round(x, 4) for x in self.coverage_share],
                "bound_share": [round(x, 4) for x in self.bound_share], "steps": self.steps,
                "lights": [[round(c, 4) for c in d] for d in self.lights], "seconds": round(self.seconds, 3)}


def bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(x0, y0, x1, y1)`` (end exclusive) of the set pixels of ``mask (H, W)``, or None when none is set."""
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def dilate_px(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation of ``(H, W)`` by a disc of ``radius`` pixels (a pixel is set when a set pixel lies within
    ``radius`` of it, centre to centre).

    Through the exact Euclidean distance transform (scipy), O(pixels) whatever the radius: a binary dilation by a
    disc structure costs pixels x disc area, which at the region's doubling rings (radius up to ~50 px at 96 px)
    cost seconds per render -- more than the pixels it saved (measured on the panorama: 4 of 5.5 CPU s)."""
    mask = np.asarray(mask, bool)
    if radius <= 0 or not mask.any():
        return mask.copy()
    from scipy.ndimage import distance_transform_edt

    d2 = distance_transform_edt(~mask, return_distances=True) ** 2
    return d2 <= radius * radius + 1e-6


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
    ``max_solid_angle`` sr. Delta lights (directional, point) are compact. A sun gives one direction, an area light the spread of its own, a sky or an even
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
    delta = np.asarray(ds.delta)[ok]
    radiance, d, pdf = radiance[ok], d[ok], pdf[ok]
    # a delta light (directional, point) is compact whatever the rest; the others by their bright set's solid angle
    keep = delta.copy()
    area = ~delta
    if area.any():
        bright = area & (radiance >= share * radiance[area].max())
        if float(np.sum(1.0 / (pdf[bright] * samples))) <= max_solid_angle:
            keep |= bright
    out: list[np.ndarray] = []
    for v in d[keep][np.argsort(-radiance[keep])]:
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


def start_masks(scene_bg, mesh, cams: Sequence[Camera], coverage: np.ndarray, settings: RegionSettings,
                seed: int = 0, cache: dict | None = None) -> tuple[np.ndarray, list[float], list, np.ndarray]:
    """``(start, bound_share, lights, bounds)``: per view the object's coverage and its hard-shadow bound, dilated by
    ``settings.margin`` (``(V, H, W)`` bool). ``cache``: a dict kept across objects of one scene (the compact
    lights are found once)."""
    lo, hi = mesh_bounds(mesh)
    lights = cache.get("lights") if cache is not None else None
    if lights is None:
        lights = compact_lights(scene_bg, (lo + hi) / 2.0, settings.light_samples, seed=seed)
        if cache is not None:
            cache["lights"] = lights
    hits = shadow_points(scene_bg, lo, hi, lights)
    bounds = np.stack([geometric_bound(c, lo, hi, hits) for c in cams])
    px = max(1, round(settings.margin * max(cams[0].width, cams[0].height)))
    start = np.stack([dilate_px((coverage[v] > 0) | bounds[v], px) for v in range(len(cams))])
    return start, [float(b.mean()) for b in bounds], lights, bounds


def border(rendered: np.ndarray, width: int = 2) -> np.ndarray:
    """The outer ``width``-pixel band of a set of pixels ``(H, W)`` (the frame's edge is not a border)."""
    from scipy.ndimage import binary_erosion

    return rendered & ~binary_erosion(rendered, iterations=width, border_value=1)


def change(image: np.ndarray, background: np.ndarray, rendered: np.ndarray) -> np.ndarray:
    """``(H, W)``: the sRGB change ``max_c |box(srgb(image) - srgb(background))|``: each channel's signed change
    box-filtered (3 x 3) over the rendered pixels only (pixels not rendered neither count nor dilute), then its
    magnitude. Signed before the magnitude: where a few paths of a pixel meet the object, their noise averages out
    instead of adding up (the mean of ``|noise|`` is positive), so the region grows where the object's *mean* effect
    is above the threshold (a shadow, a reflection: one sign over neighbouring pixels), not where its noise is."""
    from scipy.ndimage import uniform_filter

    from camo_base.imaging import linear_to_srgb

    d = linear_to_srgb(np.clip(image, 0, None)).astype(np.float64) - linear_to_srgb(np.clip(background, 0, None))
    w = rendered.astype(np.float64)
    den = uniform_filter(w, 3)
    num = np.stack([uniform_filter(d[..., c] * w, 3) for c in range(d.shape[-1])], -1)
    return np.where(den > 0, np.abs(num).max(-1) / np.maximum(den, 1e-12), 0.0)


def render_region(render, background: np.ndarray, scene_bg, mesh, cams: Sequence[Camera], coverage: np.ndarray,
                  settings: RegionSettings = RegionSettings(), seed: int = 0,
                  cache: dict | None = None) -> tuple[np.ndarray, Regions]:
    """The render with the object ``mesh`` over the region it can change (module doc), the rest the
    ``background (V, H, W, 3)`` (the same spp and seed); returns ``(image, regions)``.

    ``render(masks, fill)`` renders the pixels ``masks (V, H, W)`` with the object (same spp and seed as the
    background), copying ``fill`` elsewhere; ``scene_bg``: the scene without the object (its emitters and
    receivers); ``coverage (V, H, W)``: the object's pixel coverage."""
    import time

    t0 = time.perf_counter()
    V = len(cams)
    todo, bound_share, lights, _ = start_masks(scene_bg, mesh, cams, coverage, settings, seed, cache)
    ring = max(1, round(settings.ring * max(cams[0].width, cams[0].height)))
    rendered = np.zeros_like(todo)
    image = np.array(background, np.float32, copy=True)
    steps = 0
    while todo.any() and steps < settings.max_steps:
        image = render(todo, image)
        rendered |= todo
        steps += 1
        hot = np.zeros_like(todo)
        for v in range(V):
            edge = border(rendered[v])
            if edge.any():
                hot[v] = edge & (change(image[v], background[v], rendered[v]) > settings.threshold)
        if not hot.any():
            break
        if rendered.mean() > FULL_SHARE or steps == settings.max_steps - 1:
            todo = ~rendered  # nearly everything changes: the rest in one go
        else:
            todo = np.stack([dilate_px(h, ring << (steps - 1)) for h in hot]) & ~rendered  # rings double
    return image, Regions(rendered, [float((c > 0).mean()) for c in coverage], bound_share, steps,
                          [list(map(float, d)) for d in lights], time.perf_counter() - t0)


def box_pixels(obj, cams: Sequence) -> list[np.ndarray | None]:
    """Per view, the pixels (flat row-major indices, ascending) whose rays can meet ``obj``'s bounding box: the
    bounding rectangle of its 8 projected corners (it holds the box's projection when every corner is in front of
    the camera; else None: every pixel), grown by a pixel against rounding."""
    from optimizer.rendering.projection import project

    lo, hi = mesh_bounds(obj)
    pad = 1e-3 * float(np.max(hi - lo))
    corners = box_points(lo - pad, hi + pad, 2)
    out: list[np.ndarray | None] = []
    for cam in cams:
        x, y, z = project(corners, cam)
        if (z <= 0.02).any():  # a corner behind the camera (or before its near clip): no bound
            out.append(None)
            continue
        x0, x1 = max(int(np.floor(x.min())) - 1, 0), min(int(np.ceil(x.max())) + 1, cam.width)
        y0, y1 = max(int(np.floor(y.min())) - 1, 0), min(int(np.ceil(y.max())) + 1, cam.height)
        m = np.zeros((cam.height, cam.width), bool)
        if x0 < x1 and y0 < y1:
            m[y0:y1, x0:x1] = True
        out.append(np.flatnonzero(m))
    return out
