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

This is the "local" albedo of the projection baselines (:mod:`optimizer.optimise.baselines.common`) generalised from a
white Lambertian copy to the run's own initial material, so it also holds for a transmissive, glossy start.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Sequence

import numpy as np

from optimizer.scenes.cameras import Camera


@dataclasses.dataclass
class WarmStartInfo:
    """What the warm start did (written to ``summary.json``)."""

    texels: int  # on-chart texels of the albedo atlas
    texels_seen: int  # of those, seen in at least one view with full coverage
    clipped_high: float  # fraction of seen texels whose least-squares albedo was > 1 (too dark to match)
    clipped_low: float  # fraction < 0 (too bright to match)
    mean_albedo: list[float]  # mean over seen texels, linear
    seconds: float
    # ``grain=True``: the grain layer's map (R, R, 3) (optimizer/optimise/grain.py; not written to summary.json) and
    # its rms over the texels that got grain
    grain: np.ndarray | None = dataclasses.field(default=None, repr=False)
    grain_rms: float | None = None

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
                      grain_sharpen: float = 0.0) -> tuple[dict[str, np.ndarray], WarmStartInfo]:
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
    renders = []
    for grey in (0.0, 1.0):
        v = dict(values)
        v["albedo"] = np.full_like(values["albedo"], grey)
        mesh = scn.object_mesh(positions, geometry.faces, geometry.uvs, object_bsdf(v, app))
        renders.append(render_shaded(env.build(), mesh, cams, integrator, spp, seed, masks,
                                     None if masks is None else background))
    black, white = renders
    n = len(tv.surface)
    albedo = np.zeros((n, 3), np.float32)
    raw = np.zeros((n, 3), np.float32)
    assigned = np.zeros(n, bool)
    albedo[tv.seen], assigned[tv.seen], raw[tv.seen] = least_squares_albedo(
        tv.background, tv.obs.sample(black), tv.obs.sample(white), tv.weight)
    init_mean = values["albedo"].reshape(-1, 3).mean(0)
    new = dict(values)
    new["albedo"] = projection.bake(tv.surface, albedo, assigned, fallback=tuple(float(x) for x in init_mean))
    seen = int(assigned.sum())
    info = WarmStartInfo(
        texels=n, texels_seen=seen,
        clipped_high=float((raw[assigned] > 1.0).any(-1).mean()) if seen else 0.0,
        clipped_low=float((raw[assigned] < 0.0).any(-1).mean()) if seen else 0.0,
        mean_albedo=[float(x) for x in (albedo[assigned].mean(0) if seen else init_mean)],
        seconds=0.0)
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
