"""The planner's pilot: a few seconds of rendering that measure what each light-transport effect contributes.

:func:`run_pilot` renders a few views of the actual scene, object and stage at low resolution, with and without the
object, with the same random numbers, through :mod:`optimizer.rendering.tracer`'s recording path tracer (full
depth, Russian roulette from vertex 5: the "always full path tracing" setting). Per pixel it then knows the light
that needs each path depth, the per-sample variance and cost of stopping at each depth, the light that went through
or was reflected by the object onto its surroundings, the light seen through the object, and each emitter's
light. With ``geometry`` it also renders the object moved by a small step along x and along y (finite differences,
same random numbers) to see where the image responds to the pose: on the silhouette (Mitsuba's projective
silhouette term), inside the object (the continuous term), or around it (its shadow: indirect visibility).

:class:`Pilot` turns those per-pixel records into per-effect figures over the pixels that matter (the object's
region, or the whole frame), in sRGB units (the first-order effect of a linear change on the 8-bit encoding,
``d srgb / d linear`` at each pixel's luminance; 0 where the pixel clips). The planner
(:mod:`optimizer.rendering.planner`) decides from these figures; every figure it prints comes from here.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable, Sequence

import numpy as np

from optimizer.scenes.cameras import Camera

#: The full setting the pilot measures against: Mitsuba's ``path`` defaults kept by the bench's reference.
FULL_DEPTH = 12
RR_DEPTH = 5


@dataclasses.dataclass(frozen=True)
class PilotSettings:
    views: int = 4  # evenly spaced among the stage's views
    resolution: int = 48  # pixels on the shorter side
    spp: int = 32
    max_depth: int = FULL_DEPTH
    rr_depth: int = RR_DEPTH
    threshold: float = 0.5 / 255  # sRGB change that marks a pixel as changed by the object
    shift: float = 0.02  # finite-difference step of the pose sensitivity, a fraction of the object's size


@dataclasses.dataclass
class DepthFigures:
    """Per candidate ``max_depth`` M = 1..K over a pixel set (sRGB units, per sample where it says so)."""

    bias: np.ndarray  # (K,) RMS of the light that needs a depth > M (the bias of stopping at M)
    variance: np.ndarray  # (K,) mean per-sample variance of a render at depth M
    cost: np.ndarray  # (K,) mean vertices traced per sample at depth M
    bounce: np.ndarray  # (K,) RMS of the light that needs exactly depth M
    pixels: int


def srgb_slope(y: np.ndarray) -> np.ndarray:
    """``d srgb(x) / dx`` at linear ``y`` (IEC 61966-2-1); 0 at and above 1 (clipped pixels show no change)."""
    y = np.asarray(y, np.float64)
    lin = 12.92 * np.ones_like(y)
    pw = 1.055 / 2.4 * np.power(np.maximum(y, 0.0031308), 1.0 / 2.4 - 1.0)
    out = np.where(y <= 0.0031308, lin, pw)
    return np.where(y >= 1.0, 0.0, out)


class Pilot:
    """The pilot's renders of one scene, object and stage (module doc); :func:`run_pilot` makes one.

    Each render is two independent halves (samples ``0 .. spp/2 - 1`` and ``spp/2 .. spp - 1`` of the same
    streams): a squared mean is estimated without its noise as the product of the halves' means
    (``E[a b] = E[a] E[b]`` for independent halves), as :func:`optimizer.optimise.holdout.split_error` does."""

    def __init__(self, settings: PilotSettings, names: list[str], obj: np.ndarray, bg: np.ndarray,
                 coverage: np.ndarray, emitters: list[str], seconds: float, vertices: float,
                 sensitivity: dict | None = None, width: int = 0, height: int = 0):
        self.settings = settings
        self.names = names
        self.index = {n: i for i, n in enumerate(names)}
        self.halves = {"obj": obj, "bg": bg}  # (2, V, h, w, R) mean records of each half, with / without the object
        self.obj, self.bg = obj.mean(0), bg.mean(0)  # (V, h, w, R) over both halves
        self.coverage = coverage  # (V, h, w) object coverage at the pilot's resolution
        self.emitters = emitters
        self.seconds = seconds
        self.vertices = vertices  # path vertices traced by the pilot's renders (its cost, for the time model)
        self.sensitivity = sensitivity
        self.width, self.height = width, height
        self.changed = self._changed()

    # -- per pixel ---------------------------------------------------------------------------------------------
    def channel(self, rec: np.ndarray, name: str) -> np.ndarray:
        return rec[..., self.index[name]].astype(np.float64)

    @property
    def K(self) -> int:
        return self.settings.max_depth

    def luminance(self, rec: np.ndarray) -> np.ndarray:
        return sum(self.channel(rec, f"m{m}") for m in range(1, self.K + 1))

    def _changed(self) -> np.ndarray:
        from scipy.ndimage import uniform_filter

        from camo_base.imaging import linear_to_srgb

        d = np.abs(linear_to_srgb(np.clip(self.luminance(self.obj), 0, None)) -
                   linear_to_srgb(np.clip(self.luminance(self.bg), 0, None)))
        return np.stack([uniform_filter(x, 3) > self.settings.threshold for x in d]) | (self.coverage > 0)

    def region(self) -> np.ndarray:
        """``(V, h, w)`` bool: the pixels the object changes (its coverage and the measured change), dilated by one
        pixel."""
        from optimizer.rendering.region import dilate_px

        return np.stack([dilate_px(c, 1) for c in self.changed])

    def _tails(self, rec: np.ndarray, sel: np.ndarray) -> np.ndarray:
        """``(N, K)``: per selected pixel, the light that needs a depth above M = 1..K."""
        m = np.stack([self.channel(rec, f"m{i}")[sel] for i in range(1, self.K + 1)], -1)
        return m.sum(-1, keepdims=True) - np.cumsum(m, -1)

    # -- figures -----------------------------------------------------------------------------------------------
    def depth_figures(self, pixels: np.ndarray | None = None, with_object: bool = True,
                      difference: bool = False) -> DepthFigures:
        """:class:`DepthFigures` over ``pixels`` (``(V, h, w)`` bool; None: all) of the render with (or without)
        the object. ``difference``: the bias is that of the object's *effect* (the render with the object minus
        the one without, the same random numbers): what a loss or a metric comparing the two sees, since the light
        both lack cancels."""
        rec = self.obj if with_object else self.bg
        sel = np.ones(rec.shape[:3], bool) if pixels is None else np.asarray(pixels, bool)
        K = self.K
        y = self.luminance(rec)[sel]
        s2 = srgb_slope(y) ** 2
        m = np.stack([self.channel(rec, f"m{i}")[sel] for i in range(1, K + 1)], -1)
        q = np.stack([self.channel(rec, f"q{i}")[sel] for i in range(1, K + 1)], -1)
        n = np.stack([self.channel(rec, f"n{i}")[sel] for i in range(K)], -1)
        partial = np.cumsum(m, -1)
        var = np.maximum(q - partial ** 2, 0.0)
        key = "obj" if with_object else "bg"
        a, b = (self._tails(h, sel) for h in self.halves[key])
        if difference:
            a = a - self._tails(self.halves["bg"][0], sel)
            b = b - self._tails(self.halves["bg"][1], sel)
        cnt = max(int(sel.sum()), 1)
        bias2 = (s2[:, None] * a * b).sum(0) / cnt  # E[a b] = squared mean: the halves are independent
        ma, mb = (np.stack([self.channel(h, f"m{i}")[sel] for i in range(1, K + 1)], -1) for h in self.halves[key])
        return DepthFigures(
            bias=np.sqrt(np.maximum(bias2, 0.0)),
            variance=(s2[:, None] * var).sum(0) / cnt,
            cost=np.cumsum(n, -1).sum(0) / cnt,
            bounce=np.sqrt(np.maximum((s2[:, None] * ma * mb).sum(0) / cnt, 0.0)),
            pixels=int(sel.sum()),
        )

    def category(self, name: str, pixels: np.ndarray | None = None) -> tuple[float, float]:
        """``(rms, noise)`` of a recorded category (``via``, ``via_t``, ``seen_t`` or ``e{i}``) of the render with
        the object over ``pixels``: the RMS of its mean and, for ``via_t`` / ``seen_t``, the RMS of its per-sample
        standard deviation (sRGB)."""
        sel = np.ones(self.obj.shape[:3], bool) if pixels is None else np.asarray(pixels, bool)
        y = self.luminance(self.obj)[sel]
        s2 = srgb_slope(y) ** 2
        c = self.channel(self.obj, name)[sel]
        rms = float(np.sqrt(np.mean(s2 * c ** 2))) if c.size else 0.0
        noise = 0.0
        if name + "2" in self.index and c.size:
            sq = self.channel(self.obj, name + "2")[sel]
            noise = float(np.sqrt(np.mean(s2 * np.maximum(sq - c ** 2, 0.0))))
        return rms, noise

    def emitter_shares(self, pixels: np.ndarray | None = None) -> list[float]:
        """Each emitter's share of the light in ``pixels`` of the render with the object."""
        sel = np.ones(self.obj.shape[:3], bool) if pixels is None else np.asarray(pixels, bool)
        total = max(float(self.luminance(self.obj)[sel].sum()), 1e-12)
        return [float(self.channel(self.obj, f"e{i}")[sel].sum()) / total
                for i in range(min(len(self.emitters), sum(1 for n in self.names if n.startswith("e"))))]

    def cost_share(self, pixels: np.ndarray) -> float:
        """The share of a full render's cost (path vertices per sample, with the object) that ``pixels`` hold."""
        n = sum(self.channel(self.obj, f"n{k}") for k in range(self.K))
        return float(n[np.asarray(pixels, bool)].sum() / max(float(n.sum()), 1e-12))

    def seconds_per_vertex(self) -> float:
        return self.seconds / max(self.vertices, 1.0)

    def to_dict(self) -> dict:
        s = self.settings
        reg = self.region()
        return {"views": int(self.obj.shape[0]), "width": self.width, "height": self.height, "spp": s.spp,
                "max_depth": s.max_depth, "rr_depth": s.rr_depth, "seconds": round(self.seconds, 3),
                "region_share": round(float(reg.mean()), 4), "emitters": list(self.emitters),
                "sensitivity": self.sensitivity}


def pick_views(cams: Sequence[Camera], k: int) -> list[int]:
    from optimizer.scenes.cameras import evenly_spaced

    return evenly_spaced(len(cams), min(k, len(cams)))


def pilot_camera(cam: Camera, resolution: int) -> Camera:
    s = resolution / max(1, min(cam.width, cam.height))
    return dataclasses.replace(cam, width=max(4, round(cam.width * s)), height=max(4, round(cam.height * s)))


def shifted(mesh_fn: Callable[[], object], offset: Sequence[float]):
    """A fresh mesh from ``mesh_fn()`` moved by ``offset`` (world units)."""
    import mitsuba as mi

    mesh = mesh_fn()
    params = mi.traverse(mesh)
    v = np.asarray(params["vertex_positions"], np.float32).reshape(-1, 3) + np.asarray(offset, np.float32)
    params["vertex_positions"] = mi.Float(v.ravel())
    params.update()
    return mesh


def emitter_names(scene) -> list[str]:
    """``"id (Kind)"`` of each of ``scene``'s emitters (id: the scene element's key, empty for an area light)."""
    out = []
    for e in scene.emitters():
        kind = e.class_name() if hasattr(e, "class_name") else type(e).__name__
        out.append(f"{e.id() or '-'} ({kind})")
    return out


def run_pilot(elements_fn: Callable[[], dict], mesh_fn: Callable[[], object], cams: Sequence[Camera],
              settings: PilotSettings = PilotSettings(), seed: int = 0, geometry: bool = False,
              size: float = 1.0) -> Pilot:
    """The pilot (module doc) of the object ``mesh_fn()`` in the environment ``elements_fn()`` seen from ``cams``
    (``settings.views`` of them, evenly spaced, at ``settings.resolution``). ``geometry``: also measure where the
    image responds to the pose (four more renders); ``size``: the object's size (scale of that step)."""
    from optimizer.rendering import scene as scn
    from optimizer.rendering.render import coverage_and_depth_views
    from optimizer.rendering.tracer import record_names, render_views

    t0 = time.perf_counter()
    picked = [pilot_camera(cams[i], settings.resolution) for i in pick_views(cams, settings.views)]
    V, w, h = len(picked), picked[0].width, picked[0].height
    mesh = mesh_fn()
    sc_obj = scn.build_scene(elements_fn(), mesh, [scn.batch(picked, settings.spp)])
    sc_bg = scn.build_scene(elements_fn(), None, [scn.batch(picked, settings.spp)])
    names = record_names(settings.max_depth, len(sc_obj.emitters()))
    half = max(1, settings.spp // 2)

    def halves(sc):
        return np.stack([render_views(sc, V, w, h, half, seed, settings.max_depth, settings.rr_depth, record=True,
                                      first_sample=i * half)[1] for i in range(2)])

    obj, bg = halves(sc_obj), halves(sc_bg)
    sc_cov = scn.build_scene(elements_fn(), mesh)
    coverage = coverage_and_depth_views(sc_cov, picked, mesh, 2)[0]
    n_idx = [names.index(f"n{k}") for k in range(settings.max_depth)]
    vertices = float((obj[..., n_idx].sum() + bg[..., n_idx].sum()) * half)
    seconds = time.perf_counter() - t0
    sens = None
    if geometry:
        sens = pose_sensitivity(elements_fn, mesh_fn, picked, coverage, settings, seed, size)
    return Pilot(settings, names, obj, bg, coverage, emitter_names(sc_obj), seconds, vertices, sens, w, h)


def pose_sensitivity(elements_fn, mesh_fn, cams: Sequence[Camera], coverage: np.ndarray, settings: PilotSettings,
                     seed: int, size: float) -> dict:
    """Where the image responds to moving the object: finite differences (central, step ``settings.shift *
    size`` along x and y; renders sharing their random numbers) of the sRGB image, their energy split into the
    silhouette band (pixels partly covered, or within one pixel of the outline), the object's inside and its
    surroundings (shadow, reflections, light it blocks: what only indirect visibility sampling differentiates)."""
    from camo_base.imaging import linear_to_srgb
    from optimizer.rendering import scene as scn
    from optimizer.rendering.region import dilate_px
    from optimizer.rendering.tracer import render_views

    V, w, h = len(cams), cams[0].width, cams[0].height
    eps = settings.shift * size
    energy = np.zeros((V, h, w))
    for axis in range(2):
        imgs = []
        for sign in (1.0, -1.0):
            off = [0.0, 0.0, 0.0]
            off[axis] = sign * eps
            sc = scn.build_scene(elements_fn(), shifted(mesh_fn, off), [scn.batch(cams, settings.spp)])
            img = render_views(sc, V, w, h, settings.spp, seed, settings.max_depth, settings.rr_depth)
            imgs.append(linear_to_srgb(np.clip(img, 0, None)))
        d = (imgs[0] - imgs[1]) / (2 * eps)
        energy += (d ** 2).sum(-1)
    from scipy.ndimage import binary_erosion

    full = coverage >= 0.999
    band = np.stack([dilate_px(c > 0, 1) & ~binary_erosion(f, iterations=1) for c, f in zip(coverage, full)])
    inside = full & ~band
    total = max(float(energy.sum()), 1e-30)
    return {"silhouette": round(float(energy[band].sum()) / total, 4),
            "inside": round(float(energy[inside].sum()) / total, 4),
            "surroundings": round(float(energy[~band & ~inside].sum()) / total, 4),
            "step": eps}


@dataclasses.dataclass(frozen=True)
class CutTiming:
    """What a depth cut saves in seconds, timed (:func:`time_depth_cut`): the least of ``reps`` interleaved rounds
    at the cut's depth and at full depth, each a primal and adjoint render of every view of the stage at its spp over
    the stage's window."""

    depth: int  # the cut's max_depth
    full_depth: int
    rr_depth: int
    seconds_cut: float  # least of the reps (the clock's seconds: process CPU seconds by default)
    seconds_full: float
    views: int
    width: int  # the stage's film
    height: int
    window: tuple[int, int, int, int]  # (x0, y0, x1, y1), shared by the views
    spp: int
    reps: int
    warmup_seconds: float  # the untimed warm-up renders (kernel compilation), for the record
    clock: str = "process"

    @property
    def saving(self) -> float:
        """The share of the full render's seconds the cut saves (negative: the cut is slower)."""
        return 1.0 - self.seconds_cut / max(self.seconds_full, 1e-12)

    @property
    def window_share(self) -> float:
        x0, y0, x1, y1 = self.window
        return (x1 - x0) * (y1 - y0) / max(self.width * self.height, 1)

    def describe(self) -> str:
        return (f"timed {self.seconds_cut:.3f} against {self.seconds_full:.3f} {self.clock} s (least of {self.reps}, "
                f"interleaved; {self.views} views at {self.width}x{self.height}, window {self.window_share:.0%}, "
                f"{self.spp} spp)")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["window"] = list(self.window)
        d["saving"] = round(self.saving, 4)
        return d


def stage_window(region: np.ndarray, width: int, height: int) -> tuple[int, int, int, int]:
    """The window ``(x0, y0, x1, y1)`` of a ``width x height`` film that bounds ``region (V, h, w)`` (the pilot's
    object region at its own resolution) in every view, scaled outward to the film: the shared window Stage 1
    renders (:func:`optimizer.optimise.stage1.training_windows`), from the pilot's views. The whole film when
    the region is empty."""
    from optimizer.rendering.region import bbox

    reg = np.asarray(region, bool)
    b = bbox(reg.any(axis=0))
    if b is None:
        return 0, 0, int(width), int(height)
    h, w = reg.shape[1:]
    x0, y0, x1, y1 = b
    return (max(0, int(np.floor(x0 * width / w))), max(0, int(np.floor(y0 * height / h))),
            min(int(width), int(np.ceil(x1 * width / w))), min(int(height), int(np.ceil(y1 * height / h))))


def time_depth_cut(elements_fn: Callable[[], dict], mesh_fn: Callable[[], object], cams: Sequence[Camera],
                   region: np.ndarray, depth: int, spp: int, seed: int = 0, full_depth: int = FULL_DEPTH,
                   rr_depth: int = RR_DEPTH, reps: int = 3, clock: Callable[[], float] = time.process_time,
                   clock_name: str = "process", integrators: dict[int, tuple[dict, int]] | None = None,
                   geometry: bool = False) -> CutTiming:
    """Time a depth cut at the stage's size: every view of ``cams`` (the stage's cameras, at their resolution) over
    the stage's shared window (:func:`stage_window` of the pilot's ``region``), ``spp`` samples per pixel, a Stage 1
    step's rendering: the training integrator's primal render and its adjoint pass into the object's BSDF parameters
    (and, with ``geometry``, its vertex positions: the projective integrators' silhouette terms run as in training),
    at ``max_depth = depth`` and at ``full_depth``, each with Russian roulette from ``rr_depth`` as its plan has it (a
    cut at or below ``rr_depth`` stops its paths before the roulette starts). ``integrators``: per depth, the
    integrator dict and the ``spp`` argument of ``mi.render`` (the planner's
    :func:`~optimizer.rendering.planner.training_integrator`); default Mitsuba's ``prb`` at ``spp``.

    One untimed warm-up render of every view per depth first (Mitsuba compiles a kernel per depth: the compile is
    not the cut's price), then ``reps`` rounds, each timing the cut and full depth one after the other (interleaved,
    so a swing of the machine's load falls on both); the least of each's rounds is kept. ``clock``: seconds
    (process CPU seconds by default: the figure least moved by other jobs on a shared machine).

    Why timed and not counted: the pilot's path vertices are work, not seconds (a small step is mostly launch
    overhead and the adjoint pass is most of a step), and the premise the demo's size put in doubt (meadow's Stage 1
    took 232 s at depth 4 against 301 s at 12 where the vertices said 3.5 %) is settled by timing the step at that
    size (docs/results/planner.md). The adjoint pass is timed with the primal (~80 % of a Stage 1 step), and with the
    training integrator itself: in the room (4 views x 64 px, 4 spp, interleaved) a cut to 4 saves 28 % of a plain
    ``prb`` render + adjoint but 5 % of the projective one's with geometry gradients (1.84 against 1.93 process s):
    the silhouette terms, which do not shorten with the depth, are most of a projective step."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.rendering import scene as scn

    cams = list(cams)
    if not cams:
        raise ValueError("time_depth_cut: no cameras")
    W, H = cams[0].width, cams[0].height
    window = stage_window(region, W, H)
    sc = scn.build_scene(elements_fn(), mesh_fn(), [scn.perspective(c, int(spp), crop=window) for c in cams])
    if integrators is None:
        integrators = {d: ({"type": "prb", "max_depth": int(d), "rr_depth": int(rr_depth)}, int(spp))
                       for d in (int(depth), int(full_depth))}
    if set(integrators) != {int(depth), int(full_depth)}:
        raise ValueError("time_depth_cut: integrators must be given for the cut's depth and for full depth")
    from optimizer.rendering import projective

    projective.register()  # the training plans' camo_* projective integrators
    loaded = {d: (mi.load_dict(dict(integ)), int(n)) for d, (integ, n) in integrators.items()}
    params = mi.traverse(sc)
    keys = [k for k in params.keys() if k.startswith(scn.OBJECT_ID + ".bsdf") and
            dr.is_diff_v(params[k]) and dr.is_float_v(params[k])]
    if geometry:
        keys.append(scn.OBJECT_ID + ".vertex_positions")  # the pose and displacement: the silhouette terms run
    if not keys:
        raise ValueError("time_depth_cut: the object's BSDF has no differentiable parameter")

    def step(d: int, s: int) -> None:
        # a Stage 1 step's rendering: the primal render of every view, then its adjoint (path replay) for the maps
        for i in range(len(cams)):
            for k in keys:
                dr.enable_grad(params[k])
            params.update()
            integ, n = loaded[d]
            img = mi.render(sc, params, sensor=i, integrator=integ, spp=n, seed=s + i)
            dr.backward(dr.mean(img, axis=None))
            for k in keys:
                dr.eval(dr.grad(params[k]))
                dr.disable_grad(params[k])
        dr.sync_thread()

    t0 = clock()
    for d in loaded:
        step(d, seed)
    warm = clock() - t0
    best = {d: math.inf for d in loaded}
    for r in range(int(reps)):
        for d in loaded:
            t = clock()
            step(d, seed + (r + 1) * 1000)
            best[d] = min(best[d], clock() - t)
    return CutTiming(int(depth), int(full_depth), int(rr_depth), float(best[int(depth)]), float(best[int(full_depth)]),
                     len(cams), int(W), int(H), tuple(int(v) for v in window), int(spp), int(reps), float(warm),
                     clock_name)
