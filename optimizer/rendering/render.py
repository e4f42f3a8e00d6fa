"""Rendering core: per view, the background without the object, the scene with it,
the object's visible-pixel mask (occlusion aware) and the background depth.

Radiance is linear float32 ``(V, H, W, 3)``; masks ``(V, H, W)`` bool with the
float coverage beside them; depth ``(V, H, W)`` float32 distance along the
camera ray in scene units (0 where nothing is hit).

Shaded passes use one ``batch`` sensor for all views when the integrator
allows it (the projective integrators crash on it: one perspective sensor per
render there). Masks and depth come from a ray-cast AOV pass with no shading
(``ss x ss`` stratified rays per pixel), which is exact and occlusion aware.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from optimizer.rendering import scene as scn
from optimizer.scenes.cameras import Camera

PROJECTIVE = ("prb_projective", "direct_projective", "camo_prb_projective", "camo_direct_projective")


@dataclasses.dataclass
class ViewRenders:
    background: np.ndarray  # (V, H, W, 3) linear radiance, object removed
    with_object: np.ndarray  # (V, H, W, 3) linear radiance
    mask: np.ndarray  # (V, H, W) bool, coverage >= 0.5
    coverage: np.ndarray  # (V, H, W) float32 in [0, 1]
    depth: np.ndarray  # (V, H, W) float32, background depth (scene units, 0 = miss)


def uses_batch(integrator: dict[str, Any]) -> bool:
    return integrator.get("type") not in PROJECTIVE


class PathRenderer:
    """One scene (environment ``elements`` and an optional object ``obj``) seen from ``cams`` through a ``batch``
    sensor, rendered any number of times by :mod:`optimizer.rendering.tracer` (Mitsuba's ``path`` estimator with
    per-pixel random streams; ``integrator``: a ``path`` dict, its ``max_depth`` and ``rr_depth``). Renders with
    and without the object at one seed share their random numbers, and a render of some pixels equals those
    pixels of the full frame."""

    def __init__(self, elements: dict, obj, cams: Sequence[Camera], integrator: dict, spp: int, seed: int = 0):
        if integrator.get("type") != "path":
            raise ValueError(f"PathRenderer renders the path integrator, not {integrator.get('type')!r}")
        self.cams, self.spp, self.seed = list(cams), int(spp), int(seed)
        self.max_depth = int(integrator.get("max_depth", 12))
        self.rr_depth = int(integrator.get("rr_depth", 5))
        #: ``integrator["sampler"]`` (tracer.SAMPLERS; default ``independent``): how a pixel's samples are drawn
        self.sampler = str(integrator.get("sampler", "independent"))
        self.scene = scn.build_scene(elements, obj, [scn.batch(self.cams, self.spp)])

    def __call__(self, masks: np.ndarray | None = None, fill: np.ndarray | None = None, spp: int | None = None,
                 first_sample: int = 0, moments: bool = False, groups: int = 1, counts: np.ndarray | None = None):
        """``(V, H, W, 3)`` linear radiance: the pixels where ``masks (V, H, W)`` is set (None: all), the others
        copied from ``fill`` (zeros when None); samples ``first_sample`` on, ``spp`` of them (default the
        renderer's). ``moments``: also the mean squared luminance per sample ``(V, H, W)``; ``groups`` > 1: also the
        means of that many consecutive groups of samples ``(G, V, H, W, 3)`` (a tuple after the image). ``counts
        (V, H, W)`` int, instead of ``masks``: ``counts`` x ``spp`` samples per pixel from ``first_sample`` on, every
        pixel in one launch (:func:`optimizer.rendering.tracer.render_views`)."""
        from optimizer.rendering.tracer import render_views

        c = self.cams[0]
        return render_views(self.scene, len(self.cams), c.width, c.height, self.spp if spp is None else int(spp),
                            self.seed, self.max_depth, self.rr_depth, masks, fill, moments=moments,
                            first_sample=first_sample, groups=groups, counts=counts, sampler=self.sampler)


def render_shaded(elements: dict, obj, cams: Sequence[Camera], integrator: dict, spp: int, seed: int = 0,
                  masks: np.ndarray | None = None, fill: np.ndarray | None = None) -> np.ndarray:
    """Render every view; returns ``(V, H, W, 3)`` linear radiance.

    A ``path`` integrator renders through :class:`PathRenderer` (only the pixels where ``masks (V, H, W)`` is set,
    the others copied from ``fill (V, H, W, 3)``: typically the background render of the same seed). Other
    integrators render through ``mi.render`` (``masks`` must be None)."""
    import mitsuba as mi

    if integrator.get("type") == "path":
        return PathRenderer(elements, obj, cams, integrator, spp, seed)(masks, fill)
    if masks is not None:
        raise ValueError(f"a masked render needs the path integrator, not {integrator.get('type')!r}")
    if uses_batch(integrator):
        sc = scn.build_scene(elements, obj, [scn.batch(cams, spp)], integrator)
        img = np.asarray(mi.render(sc, spp=spp, seed=seed), dtype=np.float32)
        return split_batch(img, len(cams))
    sc = scn.build_scene(elements, obj, [scn.perspective(c, spp) for c in cams], integrator)
    return np.stack(
        [np.asarray(mi.render(sc, sensor=i, spp=spp, seed=seed * 1009 + i), dtype=np.float32) for i in range(len(cams))]
    )


def render_with_region(elements_fn, mesh, cams: Sequence[Camera], integrator: dict, spp: int, seed: int,
                       background: np.ndarray, coverage: np.ndarray, threshold: float | None = None,
                       groups: int = 1, cache: dict | None = None, renderer: "PathRenderer | None" = None):
    """The render with the object ``mesh`` over the region it can change
    (:func:`optimizer.rendering.region.render_region`), the rest from ``background`` (same spp and seed); returns
    ``(image, regions)`` or, with ``groups`` > 1, ``(image, regions, group_means)`` (``(G, V, H, W, 3)``, zeros
    outside the region). ``elements_fn()``: fresh environment elements; ``cache``: a dict kept across objects of
    one scene; ``renderer``: the :class:`PathRenderer` of this scene, spp and seed when the caller has one (a scene
    is built once)."""
    from optimizer.rendering.region import THRESHOLD, RegionSettings, render_region

    r = renderer if renderer is not None else PathRenderer(elements_fn(), mesh, cams, integrator, spp, seed)
    grouped = np.zeros((groups, *np.asarray(background).shape), np.float32) if groups > 1 else None

    def render(masks, fill):
        if grouped is None:
            return r(masks, fill)
        img, g = r(masks, fill, groups=groups)
        grouped[:, masks] = g[:, masks]
        return img

    sc_bg = cache.get("scene") if cache is not None else None
    if sc_bg is None:
        sc_bg = scn.build_scene(elements_fn())
        if cache is not None:
            cache["scene"] = sc_bg
    settings = RegionSettings(threshold=max(THRESHOLD, float(threshold or 0.0)))
    img, reg = render_region(render, background, sc_bg, mesh, cams, coverage, settings, seed, cache)
    return (img, reg, grouped) if grouped is not None else (img, reg)


def split_batch(img: np.ndarray, views: int) -> np.ndarray:
    """``(H, V * W, C)`` batch film -> ``(V, H, W, C)``."""
    h, vw, c = img.shape
    return img.reshape(h, views, vw // views, c).transpose(1, 0, 2, 3).copy()


def camera_rays(cam: Camera, ss: int = 4, gen: np.random.Generator | None = None, pixels: np.ndarray | None = None):
    """Stratified camera rays, ``ss x ss`` per pixel, ordered (pixel row, pixel col, sub-row, sub-col): at the
    strata's centres or, with ``gen``, uniformly jittered within them. ``pixels``: only the rays of these pixels
    (flat row-major indices, ascending), each as in the full set (``gen`` draws the full frame's jitter)."""
    import drjit as dr
    import mitsuba as mi

    sensor = mi.load_dict(scn.perspective(cam, spp=1))
    w, h = cam.width, cam.height
    n = w * h * ss * ss
    jit = None if gen is None else gen.random((2, n), np.float32)
    if pixels is None:
        idx = dr.arange(mi.UInt32, n)
    else:
        lanes = (np.asarray(pixels, np.int64)[:, None] * (ss * ss) + np.arange(ss * ss)).ravel()
        idx = mi.UInt32(lanes.astype(np.uint32))
        jit = None if jit is None else jit[:, lanes]
    sub = idx % (ss * ss)
    pix = idx // (ss * ss)
    jx, jy = (mi.Float(0.5), mi.Float(0.5)) if jit is None else (mi.Float(j) for j in jit)
    px = mi.Float(pix % w) + (mi.Float(sub % ss) + jx) / ss
    py = mi.Float(pix // w) + (mi.Float(sub // ss) + jy) / ss
    pos = mi.Point2f(px / w, py / h)
    rays, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    return rays


def stack_rays(rays: Sequence) -> Any:
    """One ``mi.Ray3f`` wavefront of several ray sets (e.g. :func:`camera_rays` of every view), in order: one
    launch traces them all."""
    import mitsuba as mi

    o = np.concatenate([np.asarray(r.o, dtype=np.float32).reshape(3, -1) for r in rays], 1)
    d = np.concatenate([np.asarray(r.d, dtype=np.float32).reshape(3, -1) for r in rays], 1)
    return mi.Ray3f(mi.Point3f(o), mi.Vector3f(d))


def coverage_and_depth(sc, cam: Camera, target_shape=None, ss: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Fraction of each pixel covered by ``target_shape`` (visible, i.e. first hit) and mean hit distance.

    Returns ``coverage (H, W)`` (zeros when ``target_shape`` is None) and
    ``depth (H, W)``: the mean distance from the camera centre of the rays that hit
    anything (0 when none do).
    """
    cov, depth = coverage_and_depth_views(sc, [cam], target_shape, ss)
    return cov[0], depth[0]


def coverage_and_depth_views(sc, cams: Sequence[Camera], target_shape=None,
                             ss: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """:func:`coverage_and_depth` of every view, ``(coverage (V, H, W), depth (V, H, W))``, all views' rays in one
    launch (the per-view calls cost ~30 ms each at 96 px, most of it the launch; ``tests/test_render.py``: equal
    to them)."""
    import drjit as dr
    import mitsuba as mi

    sizes = [c.width * c.height * ss * ss for c in cams]
    si = sc.ray_intersect(stack_rays([camera_rays(c, ss) for c in cams]))
    hit = si.is_valid()
    centre = mi.Point3f(np.concatenate([np.repeat(np.asarray(c.origin, np.float32)[:, None], n, 1)
                                        for c, n in zip(cams, sizes)], 1))
    t = dr.select(hit, dr.norm(si.p - centre), 0.0)
    on = hit & (si.shape == mi.ShapePtr(target_shape)) if target_shape is not None else None
    dr.eval(t, hit, on) if on is not None else dr.eval(t, hit)
    t_np, hit_np = np.asarray(t, dtype=np.float32), np.asarray(hit, dtype=bool)
    on_np = np.asarray(on, dtype=bool) if on is not None else None
    covs, depths, start = [], [], 0
    for c, n in zip(cams, sizes):
        shape = (c.height, c.width, ss * ss)
        tv, hv = t_np[start:start + n].reshape(shape), hit_np[start:start + n].reshape(shape)
        nhit = hv.sum(-1)
        depths.append(np.where(nhit > 0, tv.sum(-1) / np.maximum(nhit, 1), 0.0).astype(np.float32))
        covs.append(np.zeros(shape[:2], np.float32) if on_np is None
                    else on_np[start:start + n].reshape(shape).mean(-1).astype(np.float32))
        start += n
    return np.stack(covs), np.stack(depths)


def surface_normals_views(sc, cams: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """World-space shading normals and hit distances of the first surface seen through each pixel's centre, every
    view's rays in one launch (the geometry of :func:`coverage_and_depth_views`, one ray a pixel). Returns
    ``normals (V, H, W, 3)`` float32, unit length and turned towards the camera (a two-sided plane seen from its
    back reads as seen from its front), zeros where the ray meets nothing, and ``depth (V, H, W)`` float32 (0 where
    nothing is hit). What the simulated observer's surfaces are read from (:func:`evaluation.observer.
    surface_labels`): a floor and a wall of one colour are two surfaces by their normals."""
    import drjit as dr
    import mitsuba as mi

    rays = stack_rays([camera_rays(c, 1) for c in cams])
    si = sc.ray_intersect(rays)
    hit = si.is_valid()
    n = si.sh_frame.n
    centre = mi.Point3f(np.concatenate([np.repeat(np.asarray(c.origin, np.float32)[:, None], c.width * c.height, 1)
                                        for c in cams], 1))  # (the rays start on the near plane)
    t = dr.select(hit, dr.norm(si.p - centre), 0.0)  # from the camera centre, as coverage_and_depth_views'
    dr.eval(n, hit, t)
    n_np = np.asarray(n, dtype=np.float32).reshape(3, -1).T
    t_np = np.asarray(t, dtype=np.float32).ravel()
    hit_np = np.asarray(hit, dtype=bool).ravel()
    d_np = np.asarray(rays.d, dtype=np.float32).reshape(3, -1).T
    flip = np.where((n_np * d_np).sum(1) > 0, -1.0, 1.0).astype(np.float32)  # towards the camera
    n_np = n_np * flip[:, None]
    n_np /= np.maximum(np.linalg.norm(n_np, axis=1, keepdims=True), 1e-12)
    n_np[~hit_np] = 0.0
    t_np = np.where(hit_np, t_np, 0.0)
    normals, depths, start = [], [], 0
    for c in cams:
        k = c.width * c.height
        normals.append(n_np[start:start + k].reshape(c.height, c.width, 3))
        depths.append(t_np[start:start + k].reshape(c.height, c.width))
        start += k
    return np.stack(normals).astype(np.float32), np.stack(depths).astype(np.float32)


def object_coverage_views(sc, cams: Sequence[Camera], target_shape, ss: int = 4) -> np.ndarray:
    """The coverage of :func:`coverage_and_depth_views` ``(V, H, W)`` float32, exactly, tracing only the pixels whose
    rays can meet ``target_shape``'s bounding box (:func:`optimizer.rendering.region.box_pixels`; a ray that misses
    the box cannot hit the object, so the other pixels' coverage is 0) and no depth: at 96 px the full pass was 0.10
    of the ~1.6-1.9 CPU seconds of a with-object evaluation render at 4 spp (room, 4 views; measured)."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.rendering.region import box_pixels

    pix = box_pixels(target_shape, cams)
    pix = [np.arange(c.width * c.height) if p is None else p for c, p in zip(cams, pix)]
    out = [np.zeros((c.height, c.width), np.float32) for c in cams]
    if sum(p.size for p in pix) == 0:
        return np.stack(out)
    si = sc.ray_intersect(stack_rays([camera_rays(c, ss, None, p) for c, p in zip(cams, pix) if p.size]))
    on = si.is_valid() & (si.shape == mi.ShapePtr(target_shape))
    dr.eval(on)
    on_np = np.asarray(on, dtype=bool)
    start = 0
    for o, p in zip(out, pix):
        n = p.size * ss * ss
        if n:
            o.reshape(-1)[p] = on_np[start:start + n].reshape(p.size, ss * ss).mean(-1)
            start += n
    return np.stack(out)


def render_views(elements_fn, obj_fn, cams: Sequence[Camera], integrator: dict, spp: int, seed: int = 0,
                 ss: int = 4) -> ViewRenders:
    """All per-view products for one scene.

    ``elements_fn()`` returns fresh environment elements; ``obj_fn()`` a fresh
    object mesh (called once per scene that needs it).
    """
    bg = render_shaded(elements_fn(), None, cams, integrator, spp, seed)
    obj = obj_fn()
    fg = render_shaded(elements_fn(), obj, cams, integrator, spp, seed)
    sc_obj = scn.build_scene(elements_fn(), obj)
    sc_bg = scn.build_scene(elements_fn())
    cov, depth = [], []
    for c in cams:
        cv, _ = coverage_and_depth(sc_obj, c, obj, ss)
        _, d = coverage_and_depth(sc_bg, c, None, ss)
        cov.append(cv)
        depth.append(d)
    coverage = np.stack(cov)
    return ViewRenders(bg, fg, coverage >= 0.5, coverage, np.stack(depth))


def render_allocated(elements_fn, mesh, cams: Sequence[Camera], integrator: dict, spp: int, seed: int,
                     background: np.ndarray, background_groups: np.ndarray, coverage: np.ndarray,
                     threshold: float | None = None, region: bool = True, noise_floor: bool = True,
                     cache: dict | None = None, estimator: str = "sturdy", object_floor: bool = True):
    """The render with the object ``mesh`` at the error of a uniform ``spp``, its samples allocated per pixel with
    the background as a control variate (:mod:`optimizer.rendering.allocation`): a base pass of ``spp / 4``
    samples (over the region the object can change when ``region``, :func:`optimizer.rendering.region.
    render_region`, the background's pixels elsewhere; else every pixel), then extra samples where they lower the
    error most per CPU second (with ``noise_floor``, also wherever the render would be noisier than the
    background's). ``background (V, H, W, 3)``: the background at ``spp``, same seed; ``background_groups``: its
    ``allocation.background_groups(spp)`` consecutive group means ``(G, V, H, W, 3)``. ``cache``: a dict kept across
    objects of one scene (the compact lights, the costs per sample); ``estimator``: the per-pixel variance estimate
    (:data:`optimizer.rendering.allocation.ESTIMATORS`); ``object_floor``: the object's own pixels never below
    ``spp`` samples (:func:`optimizer.rendering.allocation.allocate`). Returns ``(image, regions or None,
    allocation)``."""
    import time

    from optimizer.rendering import allocation as A

    A.check_spp(spp)
    bg_groups = np.asarray(background_groups)
    G = A.background_groups(spp)
    if bg_groups.shape != (G, *np.shape(background)):
        raise ValueError(f"background_groups must be {(G, *np.shape(background))} for spp {spp}, got {bg_groups.shape}")
    base = spp // A.BASE_SHARE
    size = spp // G  # samples per group, the base pass's and the background's
    bg_base = bg_groups[:A.OBJECT_GROUPS].mean(0)  # the background over the base pass's samples
    cache = {} if cache is None else cache
    reg = None
    if region:
        img, reg, groups = render_with_region(elements_fn, mesh, cams, integrator, base, seed, bg_base, coverage,
                                              threshold, groups=A.OBJECT_GROUPS, cache=cache)
        rendered = reg.masks
    else:
        img, groups = PathRenderer(elements_fn(), mesh, cams, integrator, base, seed)(groups=A.OBJECT_GROUPS)
        rendered = np.ones(img.shape[:3], bool)
    t0 = time.perf_counter()
    more = PathRenderer(elements_fn(), mesh, cams, integrator, spp, seed)
    if "costs" not in cache:  # once per scene: a transmissive body's samples against the ground's
        t = time.process_time()
        cache["costs"] = A.measure_costs(more, coverage, rendered, base)
        cache["costs_seconds"] = time.process_time() - t
    c_obj, c_rest = cache["costs"]
    cost = np.where(np.asarray(coverage) > 0, c_obj, c_rest)
    # the sRGB slope at the base pass's pooled image (with the object: a body over a bright background is darker)
    samples, control, floor_share = A.allocate(groups, bg_groups[:A.OBJECT_GROUPS], size, img, cost,
                                               rendered, spp, noise_floor, kind=np.asarray(coverage) > 0,
                                               estimator=estimator, object_floor=object_floor)
    x_mean = A.extra_passes(more, img, samples, spp)
    out = A.combine(x_mean, samples, control, bg_groups, background, spp)
    return out, reg, A.Allocation(samples, control, spp, (c_obj, c_rest), floor_share, time.perf_counter() - t0)
