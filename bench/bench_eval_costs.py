"""Where a with-object evaluation render's seconds go, as ``camo evaluate`` makes it, per scene.

For the scene's object at its start from 4 jittered evaluation cameras (as ``bench_planner.py --only eval``), the
with-object render of :class:`evaluation.views.ViewRenderer` (noise matching on, the evaluation plan's region, the
denoiser ``--denoise``; the background, shared by every input of a scene, made beforehand and not counted), profiled
on the process's CPU clock: the whole render and its parts -- the region render with its search, noise matching's
further samples, the denoiser's features and the denoising, the coverage pass. Median of ``--reps`` renders after
one untimed warm-up (kernels compile). To compare two versions of the code, run it from each tree in turn
(``PYTHONPATH=TREE``), interleaved.

    python bench/bench_eval_costs.py --scenes meadow,split --spp 8 --denoise oidn-through [--reps 3]

``--region-vs-whole 8,16,32,64`` times instead, at each spp, the with-object render with the plan's region search
and over whole frames (no denoiser; order alternating, median of ``--reps``): where the search pays
(:data:`optimizer.rendering.planner.REGION_MIN_SPP`).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

import numpy as np

#: Parts of the render: the function whose cumulative seconds count as that part.
PARTS = {"region": ("render_with_region",), "noise matching": ("match",), "features": ("variant_features",),
         "denoising": ("denoise_variant",), "coverage": ("coverage_and_depth", "coverage_and_depth_views")}


def setup(name: str, views: int, resolution: int, vertices: int):
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_planner import load_pack

    from evaluation.views import evaluation_cameras, evaluation_plan
    from optimizer.rendering.placement import prepare_object, static_object_fn
    from optimizer.scenes.environments import get_environment

    pack = load_pack(name, views, resolution, vertices)
    env = get_environment(pack.environment)
    cams = evaluation_cameras(pack, views, seed=0).cams
    mesh = static_object_fn(pack, prepare_object(pack, target_vertices=vertices))()
    return pack, env, cams, mesh, evaluation_plan(pack, env, cams, 64, 0)


def renderer(spp: int, k: int, cache: dict):
    from bench_planner import _SharedCache

    from evaluation.views import ViewRenderer, render_seed

    r = ViewRenderer(spp, 0, noise_match=True, sampler_seed=render_seed(0) + k)
    r.region_cache = _SharedCache(cache)  # the scene's compact lights: found once
    return r


def parts(name: str, args) -> dict:
    pack, env, cams, mesh, plan = setup(name, args.views, args.resolution, args.target_vertices)
    cache: dict = {}
    rows = []
    for k in range(args.reps + 1):
        r = renderer(args.spp, k, cache)
        bg = r.background(pack, env, cams, plan.integrator, args.denoise)
        prof = cProfile.Profile(time.process_time)
        t = time.process_time()
        prof.enable()
        r.with_object(env, lambda: mesh, cams, plan.integrator, bg,
                      plan.region_threshold if plan.region_search else None)
        prof.disable()
        row = {"total": time.process_time() - t}
        st = pstats.Stats(prof).stats
        for part, fns in PARTS.items():
            row[part] = sum(v[3] for (_, _, fn), v in st.items() if fn in fns)
        if k:  # the first: warm-up
            rows.append(row)
    return {key: float(np.median([r[key] for r in rows])) for key in rows[0]}


def region_vs_whole(name: str, args) -> dict:
    pack, env, cams, mesh, plan = setup(name, args.views, args.resolution, args.target_vertices)
    cache: dict = {}
    out = {}
    for spp in args.region_vs_whole:
        t_of: dict = {"region": [], "whole": []}
        share = []
        for k in range(args.reps + 1):
            r = renderer(spp, k, cache)
            bg = r.background(pack, env, cams, plan.integrator)
            for mode in (("region", "whole") if k % 2 else ("whole", "region")):
                t = time.process_time()
                o = r.with_object(env, lambda: mesh, cams, plan.integrator, bg,
                                  plan.region_threshold if mode == "region" else None, region_min_spp=1)
                if k:
                    t_of[mode].append(time.process_time() - t)
                if mode == "region" and o.region is not None:
                    share.append(float(o.region.mean()))
        out[spp] = {"region_s": float(np.median(t_of["region"])), "whole_s": float(np.median(t_of["whole"])),
                    "region_share": float(np.mean(share)) if share else 1.0}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="meadow,split")
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--denoise", default="oidn-through", help="the denoiser ('off': none)")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=96)
    ap.add_argument("--target-vertices", type=int, default=8000)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--region-vs-whole", default="", help="comma-separated spp: region search against whole frames")
    args = ap.parse_args()
    args.denoise = "" if args.denoise == "off" else args.denoise
    try:
        args.region_vs_whole = [int(x) for x in args.region_vs_whole.split(",") if x]
    except ValueError:
        ap.error(f"--region-vs-whole: {args.region_vs_whole!r} is not a comma-separated list of spp")
    if args.reps < 1:
        ap.error("--reps must be >= 1")
    from optimizer import backend

    backend.init()
    for name in args.scenes.split(","):
        if args.region_vs_whole:
            res = region_vs_whole(name, args)
            cells = ", ".join(f"{s} spp: {v['region_s']:.3f} / {v['whole_s']:.3f} s (whole {v['whole_s'] / v['region_s']:.2f}x"
                              f", region {v['region_share']:.0%})" for s, v in res.items())
            print(f"{name}: region / whole frames, CPU s: {cells}", flush=True)
        else:
            res = parts(name, args)
            cells = ", ".join(f"{k} {v:.3f}" for k, v in res.items())
            print(f"{name} {args.spp} spp {args.denoise or 'off'}: CPU s {cells}", flush=True)


if __name__ == "__main__":
    main()
