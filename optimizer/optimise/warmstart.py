"""Warm start of the albedo map from the background it has to match (a choice beyond the paper).

The paper starts every run from a grey albedo of 0.5 (Sec. IV-A); at Adam's rates a map value then moves about
one learning rate per step, so the first tens of iterations only carry the albedo towards the background's
colours. Before Stage 1 we instead solve for that albedo directly, per texel, by linear least squares.

The model. With geometry, pose, metallic, roughness and transmittance held at their initial values, the
radiance a camera pixel sees on the object is (to first order) affine in the albedo ``a`` of the surface point
it hits, per colour channel::

    L(a) = L0 + a * (L1 - L0)

``L0`` is the render with a black albedo, ``L1`` with a white one (same material otherwise, same sampler
seed: common random numbers). It is exact for paths that bounce once on the object (direct diffuse and the
base-coloured transmission lobe); light bounced twice on the object itself is neglected. Camouflage asks
``L(a) = B``, the background radiance the object occludes at that pixel. A texel seen in views ``v`` at
projected pixels ``x_v`` gets the least-squares solution over those views::

    a = sum_v w_v s_v (B_v - L0_v) / sum_v w_v s_v^2,    s_v = L1_v - L0_v

with ``w_v`` = the |cosine| between the surface normal and the view direction (grazing views see a texel
blurred over many pixels) times 1 where the object fully covers the pixel (silhouette pixels mix in the
background). ``a`` is clipped to [0, 1]; where the object is too dark even at ``a = 1`` (``s`` tiny) or a
texel is seen by no view, the texel takes the colour of the nearest seen texel
(:func:`optimizer.rendering.projection.bake`), or the initial albedo if nothing is seen at all.

Inputs with non-finite values (a NaN in a render or a target) never reach the map: such observations get
weight 0. The whole step costs two renders of the training views at the target spp and one visibility ray per
texel and view (about a second at the demo sizes on 2 cores).

**Light through the body where the albedo clips** (``transmittance_max`` > the start's transmittance; a choice
beyond the paper, issue 29). Where the body is too dark to match even at ``a = 1`` (meadow: 57 % of the solved
texels at the start's transmittance 0.75, gravel 67 %) the least-squares albedo saturates and the texel stays darker
and smoother than the ground. The transmittance ``t`` of the principled BSDF then also varies per texel: ``L0`` and
``L1`` are rendered at three transmittance levels ``t0`` (the start), ``(t0 + t1) / 2`` and ``t1 = transmittance_max``
(six renders instead of two) and interpolated quadratically in ``t`` per observation (light through the body crosses
two interfaces, each weighted by ``t``: second order). Each texel takes, from ``K`` transmittance values evenly spaced in
``[t0, t1]``, the one whose clipped least-squares albedo leaves the smallest weighted squared error plus a small ridge
``lam * (t - t0) * sum w B^2`` towards the start, so a texel the start already matches keeps it. The maps are
then the joint solution (:func:`joint_albedo_transmittance`).

**Lowered only where the sun's light does not go on into the cast shadow** (``sun``, issue 29). Lowered to 0
everywhere, the body turns opaque and casts a full dark shadow (meadow: the error inside the mask halves, outside it
nearly doubles). With the sun's direction ``s`` (towards the sun), a texel whose outward normal faces it (``n . s > 0``)
is where the sunlight enters the body on its way to the shadow: with ``mode = "facing"`` its transmittance may only
rise (floor = the start); the texels facing away (``n . s <= 0``) may go down to ``transmittance_min``. But the light
that reaches the shadow crosses the body twice, in through a sun-facing face and out through one facing away, so
lowering either darkens the shadow. ``mode = "shadow"`` instead follows each texel's sun line: the texel's shadow
point ``q = p - s p_z / s_z`` on the ground plane ``z = 0``; a texel may be lowered only when no training view sees
``q`` (in frame and the first hit of the camera ray, not the object), i.e. its shadow is hidden behind or under the
body.

This is the "local" albedo of the projection baselines (:mod:`optimizer.optimise.baselines.common`) generalised from a
white Lambertian copy to the run's own initial material, so it also holds for a transmissive, glossy start.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Sequence

import numpy as np

from optimizer.scenes.cameras import Camera

#: where the joint solve may lower the transmittance, by the sun (module doc, "Lowered only where ..."): everywhere,
#: only on the texels facing away from it, only on the texels whose cast shadow no training view sees
SUN_MODES = ("off", "facing", "shadow")


@dataclasses.dataclass
class WarmStartInfo:
    """What the warm start did (written to ``summary.json``)."""

    texels: int  # on-chart texels of the albedo atlas
    texels_seen: int  # of those, seen in at least one view with full coverage
    clipped_high: float  # fraction of seen texels whose least-squares albedo was > 1 (too dark to match)
    clipped_low: float  # fraction < 0 (too bright to match)
    mean_albedo: list[float]  # mean over seen texels, linear
    seconds: float
    # with ``transmittance_max``: the transmittance's mean over the seen texels after the joint solve, the fraction of
    # them raised above / lowered below the start, and the fraction still needing an albedo > 1 at their chosen
    # transmittance
    mean_transmittance: float | None = None
    raised: float | None = None
    lowered: float | None = None
    clipped_high_after: float | None = None
    # ``grain=True``: the grain layer's map (R, R, 3) (optimizer/optimise/grain.py; not written to summary.json) and
    # its rms over the texels that got grain
    grain: np.ndarray | None = dataclasses.field(default=None, repr=False)
    grain_rms: float | None = None
    # with ``sun``: the fraction of the seen texels the sun rule keeps at or above the start (not lowered)
    sun_kept: float | None = None

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("grain")
        return d


def least_squares_albedo(background: np.ndarray, black: np.ndarray, white: np.ndarray,
                         weight: np.ndarray, min_slope: float = 1e-4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-texel least-squares albedo from per-view observations (module doc).

    ``background, black, white``: ``(V, N, 3)`` linear radiance of the background, the black-albedo and the
    white-albedo object at each texel's projection in each view; ``weight``: ``(V, N)`` >= 0 (0 = not seen).
    Returns ``(albedo (N, 3) float32 in [0, 1], assigned (N,) bool, raw (N, 3) unclipped)``. Non-finite
    observations get weight 0; a texel is assigned when its total weighted slope ``sum w s^2`` exceeds
    ``min_slope^2`` times its total weight in every channel.
    """
    B = np.asarray(background, np.float64)
    L0 = np.asarray(black, np.float64)
    L1 = np.asarray(white, np.float64)
    w = np.asarray(weight, np.float64)[..., None] * np.ones(3)
    finite = np.isfinite(B) & np.isfinite(L0) & np.isfinite(L1) & np.isfinite(w)
    w = np.where(finite, np.maximum(w, 0.0), 0.0)
    B, L0, L1 = (np.where(finite, x, 0.0) for x in (B, L0, L1))
    s = L1 - L0
    num = (w * s * (B - L0)).sum(0)
    den = (w * s * s).sum(0)
    wsum = w.sum(0)
    ok = (den > (min_slope ** 2) * np.maximum(wsum, 1e-30)) & (wsum > 0)
    raw = np.where(ok, num / np.where(ok, den, 1.0), 0.0)
    assigned = ok.all(-1)
    return np.clip(raw, 0.0, 1.0).astype(np.float32), assigned, raw.astype(np.float32)


def _quadratic(levels: Sequence[float], values: Sequence[np.ndarray], t: float) -> np.ndarray:
    """The quadratic (Lagrange) through ``(levels[i], values[i])``, i = 0..2, at ``t``; linear with two levels."""
    x = [float(v) for v in levels]
    out = np.zeros_like(np.asarray(values[0], np.float64))
    for i, (xi, yi) in enumerate(zip(x, values)):
        w = 1.0
        for j, xj in enumerate(x):
            if j != i:
                w *= (t - xj) / (xi - xj)
        out = out + w * np.asarray(yi, np.float64)
    return out


def joint_albedo_transmittance(background: np.ndarray, black: Sequence[np.ndarray], white: Sequence[np.ndarray],
                               levels: Sequence[float], weight: np.ndarray, start: float | None = None,
                               steps: int = 9, ridge: float = 1e-3, floor: np.ndarray | None = None,
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-texel albedo and transmittance (module doc, "Light through the body where the albedo clips").

    ``background``: ``(V, N, 3)`` linear radiance the texel must match; ``black[i], white[i]``: ``(V, N, 3)`` the
    black- and white-albedo object's radiance at each texel's projection rendered at transmittance ``levels[i]``
    (2 or 3 levels, ascending); ``weight (V, N)`` as :func:`least_squares_albedo`'s; ``start`` the start's
    transmittance, in the levels' range (default ``levels[0]``). ``steps`` transmittance values evenly spaced in
    ``[levels[0], levels[-1]]`` (and the start) are tried per texel; each costs its clipped least-squares albedo's
    weighted squared error plus ``ridge * |t - start| / (levels[-1] - levels[0]) * sum w B^2`` (a texel the start
    matches keeps the start). ``floor (N,)``: per texel, no transmittance below it is tried (the start always is;
module doc, "Lowered only where ..."). Returns ``(albedo (N, 3) float32 in [0, 1],
    transmittance (N,) float32, assigned (N,) bool, raw (N, 3) the unclipped albedo at the chosen transmittance)``.
    """
    B = np.asarray(background, np.float64)
    w = np.asarray(weight, np.float64)
    finite = np.isfinite(B).all(-1) & np.isfinite(w)
    for arr in (*black, *white):
        finite &= np.isfinite(np.asarray(arr)).all(-1)
    w = np.where(finite, np.maximum(w, 0.0), 0.0)
    B = np.where(finite[..., None], B, 0.0)
    lo, hi = float(levels[0]), float(levels[-1])
    t0 = lo if start is None else float(start)
    ts = np.unique(np.r_[np.linspace(lo, hi, max(int(steps), 2)), t0]) if hi > lo else np.array([lo])
    ts = np.r_[t0, ts[ts != t0]]  # the start first: a tie keeps it
    energy = (w[..., None] * B * B).sum((0, 2))  # (N,)
    n = B.shape[1]
    best_cost = np.full(n, np.inf)
    albedo = np.zeros((n, 3), np.float32)
    raw = np.zeros((n, 3), np.float32)
    trans = np.full(n, t0, np.float32)
    assigned = np.zeros(n, bool)
    for t in ts:
        L0 = np.where(finite[..., None], _quadratic(levels, black, t), 0.0)
        L1 = np.where(finite[..., None], _quadratic(levels, white, t), 0.0)
        a, ok, r = least_squares_albedo(B, L0, L1, w)
        pred = L0 + a.astype(np.float64)[None] * (L1 - L0)
        cost = (w[..., None] * (pred - B) ** 2).sum((0, 2))
        cost = cost + ridge * (abs(t - t0) / (hi - lo) if hi > lo else 0.0) * energy
        allowed = ok if floor is None else ok & ((t >= np.asarray(floor) - 1e-9) | (t == t0))
        better = allowed & (cost < best_cost)
        best_cost = np.where(better, cost, best_cost)
        albedo[better], raw[better], trans[better] = a[better], r[better], t
        assigned |= ok
    return albedo, trans, assigned, raw


def sun_facing(normals: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the texels whose outward unit ``normals (N, 3)`` face the world unit vector ``sun`` (towards the
    sun), ``n . s > 0``: where the sunlight enters the body (module doc, "Lowered only where ...")."""
    return np.asarray(normals, np.float64) @ np.asarray(sun, np.float64).reshape(3) > 0.0


def shadow_points(points: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """``(N, 3)``: where the sun line through each of ``points (N, 3)`` (world) meets the ground plane ``z = 0``, away
    from the sun (``sun``: the unit vector towards it, ``s_z > 0``): ``p - s p_z / s_z``."""
    p = np.asarray(points, np.float64)
    s = np.asarray(sun, np.float64).reshape(3)
    if s[2] <= 1e-6:
        raise ValueError("the sun is at or below the horizon: no shadow on the ground")
    return p - s[None] * (p[:, 2:3] / s[2])


def shadow_seen(scene, shape, cams: Sequence[Camera], points: np.ndarray, sun: np.ndarray, eps: float) -> np.ndarray:
    """``(N,)`` bool: some view in ``cams`` sees the shadow point (:func:`shadow_points`) of each of ``points``: in
    frame, and the camera ray's first hit is there and is not ``shape`` (the object) in ``scene``."""
    from optimizer.rendering import projection

    q = shadow_points(points, sun)
    seen = np.zeros(len(q), bool)
    for cam in cams:
        x, y, z = projection.project(q, cam)
        ok = projection.in_frame(x, y, z, cam)
        idx = np.nonzero(ok & ~seen)[0]
        if len(idx):
            on, t = projection.first_hits(scene, cam.origin, q[idx], shape)
            dist = np.linalg.norm(q[idx] - np.asarray(cam.origin, np.float64), axis=1)
            seen[idx] = ~on & (np.abs(t - dist) <= eps)
    return seen


def grain_residual(background: np.ndarray, black: np.ndarray, white: np.ndarray, weight: np.ndarray,
                   best_background: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-texel grain of the grain layer: the best view's least-squares albedo minus the all-view one, both clipped to
    [0, 1] (:mod:`optimizer.optimise.grain`). Shapes as :func:`least_squares_albedo`'s (``(V, N, 3)`` linear radiance,
    ``weight (V, N)``). Returns ``(grain (N, 3) float32 in [-1, 1], assigned (N,) bool)``; unassigned texels (no
    usable view, or too dark to match in their best view) have grain 0. ``best_background``: the best view's solve
    reads these observations instead (the sharpened targets), the mean's still ``background``."""
    from optimizer.optimise.grain import best_view_weights

    mean, ok_mean, _ = least_squares_albedo(background, black, white, weight)
    best, ok_best, _ = least_squares_albedo(background if best_background is None else best_background, black, white,
                                            best_view_weights(weight))
    ok = ok_mean & ok_best
    grain = np.where(ok[:, None], best.astype(np.float64) - mean, 0.0)
    return grain.astype(np.float32), ok


@dataclasses.dataclass
class TexelViews:
    """What the warm start needs of the geometry alone (not of the material): the texel surface, and for the texels
    some training view sees with full coverage (``seen``, indices into the surface) their observations, weights
    ``(V, n)`` and background colours ``(V, n, 3)``. A start search warm-starts several materials on one geometry
    and computes this once (:func:`warm_start_albedo`'s ``cache``)."""

    surface: object
    seen: np.ndarray
    obs: object
    weight: np.ndarray
    background: np.ndarray


def texel_views(positions: np.ndarray, geometry, resolution: int, env, cams: Sequence[Camera],
                background: np.ndarray, coverage: np.ndarray, normals: np.ndarray | None = None) -> TexelViews:
    """:class:`TexelViews` of the object at world ``positions``. Only texels that some view sees are sampled and
    solved: the others have weight 0 in every view and stay unassigned. ``normals``: the vertex normals in the
    frame of ``positions`` (:func:`optimizer.rendering.appearance.world_normals`: turned with the object); they orient
    the faces, so normals of another frame make front faces look like back faces (default: ``geometry.normal``,
    right only for an unturned object)."""
    from optimizer.rendering import projection

    surface = projection.rasterise_texels(positions, geometry.faces, geometry.uvs, resolution,
                                          geometry.normal if normals is None else normals)
    sc, shape = projection.object_scene(env, positions, geometry.faces, geometry.uvs)
    obs = projection.observe(sc, shape, cams, surface, 0.01 * float(geometry.size))
    candidate = np.nonzero((obs.visible & (obs.cos > 0)).any(0))[0]
    sub = projection.Observations(obs.visible[:, candidate], obs.x[:, candidate], obs.y[:, candidate],
                                  obs.cos[:, candidate])
    full = np.stack([projection.sample_bilinear(coverage[k][..., None], sub.x[k], sub.y[k])[:, 0]
                     for k in range(len(cams))]) >= 0.999
    weight = sub.visible * full * sub.cos
    keep = (weight > 0).any(0)
    seen = candidate[keep]
    sub = projection.Observations(sub.visible[:, keep], sub.x[:, keep], sub.y[:, keep], sub.cos[:, keep])
    return TexelViews(surface, seen, sub, weight[:, keep], sub.sample(background))


def warm_start_albedo(values: dict[str, np.ndarray], geometry, app, env, cams: Sequence[Camera], integrator: dict,
                      background: np.ndarray, coverage: np.ndarray, spp: int, seed: int,
                      say=lambda s: None, cache: dict | None = None, region: bool = False, grain: bool = False,
                      grain_sharpen: float = 0.0, transmittance_max: float = 0.0,
                      transmittance_min: float | None = None, sun: tuple[np.ndarray, str] | None = None,
                      ) -> tuple[dict[str, np.ndarray], WarmStartInfo]:
    """Replace ``values["albedo"]`` by the least-squares albedo (module doc); returns ``(values, info)``.

    ``geometry``: :class:`optimizer.rendering.appearance.Geometry`; ``values``: the initial parameters (their displacement
    and pose place the surface); ``background (V, H, W, 3)`` linear targets and ``coverage (V, H, W)`` the
    object's pixel coverage in the training views ``cams``; ``integrator`` the shading path tracer of the
    targets. Other maps are unchanged. ``cache``: a dict kept across calls on the same geometry, views and targets
    (a start search): the :class:`TexelViews` are computed once per object placement and map resolution.
    ``region`` (a measured plan, a ``path`` integrator): the two renders cover only the object's pixels (its coverage
    dilated by 2 pixels: every bilinear tap of a texel with weight > 0), the only pixels the solve reads.
    ``grain``: also the grain layer's map from the same renders (:mod:`optimizer.optimise.grain`), in ``info.grain``;
    its best view reads the targets sharpened by ``grain_sharpen`` (:func:`optimizer.optimise.grain.sharpen`).
    ``transmittance_max`` above or ``transmittance_min`` below the start's (mean) transmittance: the transmittance
    map is solved with the albedo, per texel in ``[min(start, transmittance_min), max(start, transmittance_max)]``
    (module doc; six renders instead of two); ``transmittance_max`` 0 and ``transmittance_min`` None: the albedo
    alone. ``sun``: ``(the world unit vector towards the sun, mode)``, mode ``"facing"``: the texels whose outward
    normal faces it keep at least the start's transmittance, only the others go down to ``transmittance_min``;
    ``"shadow"``: only the texels whose shadow point no view sees go down (module doc).
    """
    import hashlib

    from optimizer.rendering import scene as scn
    from optimizer.rendering.appearance import object_bsdf, world_normals, world_positions
    from optimizer.rendering import projection
    from optimizer.rendering.render import render_shaded

    t0 = time.perf_counter()
    say("warm start: solving the albedo that matches the background (2 renders)")
    positions = world_positions(geometry, values, app)
    R = values["albedo"].shape[0]
    key = (hashlib.sha1(np.ascontiguousarray(positions, np.float64).tobytes()).hexdigest(), R)
    tv = cache.get(key) if cache is not None else None
    if tv is None:
        tv = texel_views(positions, geometry, R, env, cams, background, coverage, world_normals(geometry, values))
        if cache is not None:
            cache[key] = tv

    masks = None
    if region and integrator.get("type") == "path":
        from optimizer.rendering.region import dilate_px

        masks = np.stack([dilate_px(c > 0, 2) for c in coverage])
    t_start = float(np.mean(values["transmittance"])) if "transmittance" in values else 0.0
    t_hi = max(t_start, float(transmittance_max or 0.0))
    t_lo = t_start if transmittance_min is None else min(t_start, float(transmittance_min))
    joint = "transmittance" in values and t_hi - t_lo > 1e-6
    # three levels for the quadratic: the start and the range's ends, or the start, the midpoint and the other end
    levels = sorted({t_lo, t_start, t_hi}) if t_lo < t_start < t_hi else \
        sorted({t_lo, 0.5 * (t_lo + t_hi), t_hi})

    def render(grey: float, t: float | None):
        v = dict(values)
        v["albedo"] = np.full_like(values["albedo"], grey)
        if t is not None:
            v["transmittance"] = np.full_like(values["transmittance"], t)
        mesh = scn.object_mesh(positions, geometry.faces, geometry.uvs, object_bsdf(v, app))
        return render_shaded(env.build(), mesh, cams, integrator, spp, seed, masks,
                             None if masks is None else background)

    # level 0 is the start as given (its transmittance map untouched): the plain solve's two renders
    black, white = render(0.0, None), render(1.0, None)
    n = len(tv.surface)
    albedo = np.zeros((n, 3), np.float32)
    raw = np.zeros((n, 3), np.float32)
    assigned = np.zeros(n, bool)
    albedo[tv.seen], assigned[tv.seen], raw[tv.seen] = least_squares_albedo(
        tv.background, tv.obs.sample(black), tv.obs.sample(white), tv.weight)
    init_mean = values["albedo"].reshape(-1, 3).mean(0)
    new = dict(values)
    seen = int(assigned.sum())
    clipped_high = float((raw[assigned] > 1.0).any(-1).mean()) if seen else 0.0
    clipped_low = float((raw[assigned] < 0.0).any(-1).mean()) if seen else 0.0
    extra = {}
    if joint:
        say(f"warm start: solving the transmittance in [{t_lo:.2f}, {t_hi:.2f}] with the albedo (4 more renders)")
        blacks, whites = [], []
        for t in levels:  # the start's level reuses the plain solve's renders (the start's map as given)
            near = abs(t - t_start) < 1e-9
            blacks.append(tv.obs.sample(black if near else render(0.0, t)))
            whites.append(tv.obs.sample(white if near else render(1.0, t)))
        trans = np.full(n, t_start, np.float32)
        floor = None
        if sun is not None and sun[1] != "off":
            if sun[1] not in SUN_MODES:
                raise ValueError(f"sun mode must be one of {SUN_MODES}, got {sun[1]!r}")
            if sun[1] == "facing":
                keep = sun_facing(tv.surface.normals[tv.seen], sun[0])
            else:
                sc, shape = projection.object_scene(env, positions, geometry.faces, geometry.uvs)
                keep = shadow_seen(sc, shape, cams, tv.surface.points[tv.seen], sun[0],
                                   0.01 * float(geometry.size))
            floor = np.where(keep, t_start, t_lo)
            extra["sun_kept"] = float(keep.mean()) if keep.size else 0.0
        a2, t2, ok2, raw2 = joint_albedo_transmittance(tv.background, blacks, whites, levels, tv.weight,
                                                       start=t_start, floor=floor)
        albedo[tv.seen], trans[tv.seen], assigned[tv.seen], raw[tv.seen] = a2, t2, ok2, raw2
        seen = int(assigned.sum())
        new["transmittance"] = projection.bake(tv.surface, np.repeat(trans[:, None], 3, 1), assigned,
                                               fallback=(t_start,) * 3)[..., :1].astype(np.float32)
        extra.update(mean_transmittance=float(trans[assigned].mean()) if seen else t_start,
                     raised=float((trans[assigned] > t_start + 1e-6).mean()) if seen else 0.0,
                     lowered=float((trans[assigned] < t_start - 1e-6).mean()) if seen else 0.0,
                     clipped_high_after=float((raw[assigned] > 1.0).any(-1).mean()) if seen else 0.0)
        say(f"warm start: transmittance mean {extra['mean_transmittance']:.2f}, raised on "
            f"{100 * extra['raised']:.0f} % of the texels, lowered on {100 * extra['lowered']:.0f} %; albedo > 1 needed on {100 * clipped_high:.0f} % -> "
            f"{100 * extra['clipped_high_after']:.0f} %"
            + (f"; {100 * extra['sun_kept']:.0f} % of the solved texels kept at least the start by the sun ({sun[1]})"
               if "sun_kept" in extra else ""))
    new["albedo"] = projection.bake(tv.surface, albedo, assigned, fallback=tuple(float(x) for x in init_mean))
    info = WarmStartInfo(
        texels=n, texels_seen=seen, clipped_high=clipped_high, clipped_low=clipped_low,
        mean_albedo=[float(x) for x in (albedo[assigned].mean(0) if seen else init_mean)],
        seconds=0.0, **extra)
    if grain:
        from optimizer.optimise.grain import grain_map, sharpen

        g = np.zeros((n, 3), np.float32)
        got = np.zeros(n, bool)
        best_bg = tv.obs.sample(sharpen(background, grain_sharpen)) if grain_sharpen > 0 else None
        g[tv.seen], got[tv.seen] = grain_residual(tv.background, tv.obs.sample(black), tv.obs.sample(white), tv.weight,
                                                  best_background=best_bg)
        info.grain = grain_map(tv.surface, g, got)
        info.grain_rms = float(np.sqrt(np.mean(np.square(g[got])))) if got.any() else 0.0
        say(f"warm start: grain layer on {int(got.sum())} texels, rms {info.grain_rms:.3f} (albedo units)")
    info.seconds = time.perf_counter() - t0
    say(f"warm start: {seen}/{n} texels seen, mean albedo "
        f"({', '.join(f'{x:.2f}' for x in info.mean_albedo)}), {info.seconds:.1f} s")
    return new, info
