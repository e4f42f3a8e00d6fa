"""How much of the ground's grain can the albedo carry at today's start? (issue 29, docs/results/giveaways.md, "A grain
layer projected from the ground").

Prepares Stage 1 as a run at the give-away settings does (4 training views at 64 px, map 128 texels, displacement 64,
3,000 vertices, targets at 64 spp, the turn search, the warm start; no roughness or start search and the static
planner's plan, not a run's measured one; the object from ``prepare_object(pack, target_vertices=3000)``, which on
meadow solves far more texels than a run's set-up: ``bench/warmstart_visibility.py``) and
renders the training views at 256 spp with four albedo maps that differ only on the texels the warm start solved:

* ``mean``: the warm start's multi-view least-squares albedo (what every run starts from);
* ``grain``: ``mean`` + the grain layer (``--grain 1``, :mod:`optimizer.optimise.grain`);
* ``best view, clipped``: each texel's best-view least-squares albedo clipped to [0, 1] (= ``grain`` up to rounding);
* ``best view, unclipped``: the same clipped to [0, 4] only (a non-physical albedo above 1: the bound of what any
  albedo texture could do if the material's range were not the limit).

Prints the detail ratio (``evaluation.metrics.detail_ratio``, sRGB luma, the coverage >= 0.5 mask) and the linear
squared error (x 1e4) inside the mask per training view, and what the warm start's observations say: the slope
``L1 - L0`` a texel's albedo has on its pixel, the share of texels seen in more than one view, and how often the
best-view solution needs an albedo above 1.

    python bench/grain_ceiling.py meadow
    python bench/grain_ceiling.py meadow --transmittance 0    # the same with an opaque start
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--spp", type=int, default=256, help="samples per pixel of the compared renders")
    ap.add_argument("--transmittance", type=float, help="set the start's transmittance map to this value before the "
                    "warm start (e.g. 0: an opaque body, whose pixel is one texel's albedo times its irradiance)")
    a = ap.parse_args(argv)

    from optimizer import backend

    backend.init()
    import optimizer.optimise.warmstart as ws
    from camo_base.imaging import linear_to_srgb
    from evaluation.metrics.detail_ratio import detail_ratio
    from optimizer.assets.result import Result, render_result
    from optimizer.optimise.grain import best_view_weights, fold
    from optimizer.optimise.stage1 import Stage1, Stage1Config
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.rendering.placement import prepare_object
    from optimizer.rendering.planner import plan
    from optimizer.scenes import builtin_scenes
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment

    seen_obs: dict = {}
    solve = ws.grain_residual

    def capture(B, L0, L1, w, **kw):  # the warm start's observations of the solved texels
        seen_obs.update(B=np.asarray(B, np.float64), L0=np.asarray(L0, np.float64), L1=np.asarray(L1, np.float64),
                        w=np.asarray(w, np.float64))
        return solve(B, L0, L1, w, **kw)

    ws.grain_residual = capture
    pack = builtin_scenes.get(a.scene)
    pack.cameras = dataclasses.replace(pack.cameras, views=4)
    pack.render = dataclasses.replace(pack.render, resolution=(64, 64))
    app = dataclasses.replace(AppearanceConfig(), map_resolution=128, displacement_resolution=64)
    env = get_environment(pack.environment)
    cfg = Stage1Config(spp=4, target_spp=64, seed=0, warm_start=True, grain=1.0)
    s1 = Stage1(pack, env, prepare_object(pack, target_vertices=3000), cameras(pack),
                plan(pack, env, app.planner_params()), cfg, app)
    s1.search_pose()
    s1.render_targets()
    if a.transmittance is not None:
        s1.values["transmittance"] = np.full_like(s1.values["transmittance"], a.transmittance)
    s1.warm_start()
    s1.build()
    ws.grain_residual = solve
    B, L0, L1, w = (seen_obs[k] for k in ("B", "L0", "L1", "w"))
    s = L1 - L0
    seen = w > 0
    wb = best_view_weights(w)
    best = (wb[..., None] * s * (B - L0)).sum(0) / np.maximum((wb[..., None] * s * s).sum(0), 1e-12)
    ok = wb.sum(0) > 0
    print(f"{a.scene}: {int(ok.sum())} texels solved, {float((seen.sum(0) > 1).mean()):.2f} of them seen in more "
          f"than one view; slope L1 - L0 (linear, per channel) {np.round([s[..., c][seen].mean() for c in range(3)], 3)}"
          f" against the background's {np.round([B[..., c][seen].mean() for c in range(3)], 3)}; best-view albedo "
          f"> 1 in some channel on {float((best[ok] > 1).any(-1).mean()):.2f} of the texels; grain layer rms "
          f"{s1.warm_start_info.grain_rms:.3f}")
    tv = next(iter(s1._warm_cache.values()))
    R = s1.values["albedo"].shape[0]

    def with_texels(col):
        m = s1.values["albedo"].reshape(-1, 3).copy()
        m[np.asarray(tv.surface.index)[tv.seen[ok]]] = col[ok]
        out = dict(s1.values)
        out["albedo"] = m.reshape(R, R, 3).astype(np.float32)
        return out

    from scipy.ndimage import gaussian_filter

    bg = s1.targets.background
    sharp = {}
    for alpha in (1.0, 2.0):  # unsharp mask of the targets (sigma 0.7 px), sampled at the same projections
        bs = np.stack([b + alpha * (b - gaussian_filter(b, (0.7, 0.7, 0))) for b in bg])
        Bs = tv.obs.sample(bs)
        sharp[alpha] = (wb[..., None] * s * (Bs - L0)).sum(0) / np.maximum((wb[..., None] * s * s).sum(0), 1e-12)
    cases = (("mean (warm start)", s1.values), ("grain (--grain 1)", fold(s1.values, s1.warm_start_info.grain, 1.0, 1e-3)),
             ("best view, clipped to [0, 1]", with_texels(np.clip(best, 1e-3, 1.0))),
             ("best view, unclipped (<= 4)", with_texels(np.clip(best, 1e-3, 4.0))),
             ("best view of the sharpened targets (1), clipped", with_texels(np.clip(sharp[1.0], 1e-3, 1.0))),
             ("best view of the sharpened targets (2), clipped", with_texels(np.clip(sharp[2.0], 1e-3, 1.0))),
             ("best view of the sharpened targets (2), unclipped", with_texels(np.clip(sharp[2.0], 1e-3, 4.0))))
    print("| albedo on the solved texels | detail ratio, views 1-4 | mean | squared error x 1e4, views 1-4 |")
    print("|---|---|---|---|")
    for label, vals in cases:
        res = Result(s1.pack, s1.env, s1.cams, s1.geometry, vals, s1.app, s1.shading_integrator(), a.spp, None)
        imgs = render_result(res, seed=7)
        dr_, se = [], []
        for v in range(len(s1.cams)):
            m = s1.targets.coverage[v] >= 0.5
            dr_.append(float(detail_ratio(linear_to_srgb(np.clip(imgs[v], 0, None)),
                                          linear_to_srgb(s1.targets.background[v]), m)))
            se.append(float(((imgs[v] - s1.targets.background[v])[m] ** 2).mean()) * 1e4)
        print(f"| {label} | {', '.join(f'{x:.2f}' for x in dr_)} | {np.mean(dr_):.2f} | "
              f"{', '.join(f'{x:.2f}' for x in se)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
