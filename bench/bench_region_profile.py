"""Where an evaluation render's seconds go, plan against full path tracing, per scene.

For the scene's object at its start from jittered evaluation cameras (as ``bench_planner.py --only eval``), the
CPU seconds (least of ``--reps``, after one untimed warm-up of each) of: the background render (shared by every input
of a scene), the render with the object over the whole frame at the plan's depth and at full depth 12, the plan's
region render with its search (:func:`optimizer.rendering.region.render_region`: start, growth launches, border
tests), the same region rendered in one launch (the search's own cost is the difference), and the object's own
pixels alone (its coverage, dilated by one pixel). The evaluation pilot's seconds are printed once per scene.

    python bench/bench_region_profile.py --scenes split,panorama [--resolution 96] [--views 4] [--spp 64]

``--converged SPP`` prints instead how much of the frame the object changes at convergence: the with- and
without-object renders at ``SPP`` (common random numbers, depth 6), the share of pixels whose 3 x 3 signed change
(:func:`optimizer.rendering.region.change`) exceeds 0.5, 1 and 2 / 255, and the share bitwise equal to the
background (no path of theirs met the object) -- what a region, however found, must cover to be exact.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="split,panorama")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--resolution", type=int, default=96)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--converged", type=int, default=0, metavar="SPP", help="print the converged change shares "
                    "instead of timing (module doc)")
    a = ap.parse_args()
    if a.converged:
        converged(a)
        return

    from bench.bench_planner import load_pack
    from evaluation.views import evaluation_cameras, evaluation_plan, render_seed
    from optimizer import backend
    from optimizer.rendering import region as R
    from optimizer.rendering import scene as scn
    from optimizer.rendering.placement import prepare_object, static_object_fn
    from optimizer.rendering.render import PathRenderer, coverage_and_depth
    from optimizer.scenes.environments import get_environment

    backend.init()
    clock = time.process_time
    print("| scene | pilot s | background | full frame, depth 12 | full frame, plan depth | region search + render "
          "(launches) | region, one launch | object's pixels alone | region share | object share |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in a.scenes.split(","):
        pack = load_pack(name, a.views, a.resolution, 8000)
        env = get_environment(pack.environment)
        cams = evaluation_cameras(pack, a.views, seed=a.seed).cams
        mesh = static_object_fn(pack, prepare_object(pack, target_vertices=8000))()
        t = clock()
        plan = evaluation_plan(pack, env, cams, a.spp, a.seed)
        pilot = clock() - t
        cov = np.stack([coverage_and_depth(scn.build_scene(env.build(), mesh), c, mesh)[0] for c in cams])
        seed = render_seed(a.seed)
        bg_r = PathRenderer(env.build(), None, cams, plan.integrator, a.spp, seed)
        plan_r = PathRenderer(env.build(), mesh, cams, plan.integrator, a.spp, seed)
        full_r = PathRenderer(env.build(), mesh, cams, {"type": "path", "max_depth": 12, "rr_depth": 5}, a.spp, seed)
        bg = bg_r()
        sc_bg = scn.build_scene(env.build())
        settings = R.RegionSettings(threshold=plan.region_threshold)
        launches: list[float] = []

        def render(m, f):
            launches.append(float(m.mean()))
            return plan_r(m, f)

        _, reg = R.render_region(render, bg, sc_bg, mesh, cams, cov, settings, seed, {})
        obj = np.stack([R.dilate_px(c > 0, 1) for c in cov])
        jobs = {"background": bg_r, "full12": full_r, "full_plan": plan_r,
                "search": lambda: R.render_region(render, bg, sc_bg, mesh, cams, cov, settings, seed, {}),
                "region": lambda: plan_r(reg.masks, bg), "object": lambda: plan_r(obj, bg)}
        for job in jobs.values():  # warm-up: every kernel compiled once
            job()
        best = {k: float("inf") for k in jobs}
        for _ in range(a.reps):
            for k, job in jobs.items():
                launches.clear()
                t = clock()
                job()
                best[k] = min(best[k], clock() - t)
        print(f"| {name} | {pilot:.1f} | {best['background']:.2f} | {best['full12']:.2f} | {best['full_plan']:.2f} | "
              f"{best['search']:.2f} ({reg.steps}) | {best['region']:.2f} | {best['object']:.2f} | "
              f"{reg.masks.mean():.0%} | {obj.mean():.0%} |", flush=True)


def converged(a) -> None:
    from bench.bench_planner import load_pack
    from evaluation.views import evaluation_cameras
    from optimizer import backend
    from optimizer.rendering import region as R
    from optimizer.rendering import scene as scn
    from optimizer.rendering.placement import prepare_object, static_object_fn
    from optimizer.rendering.render import PathRenderer, coverage_and_depth
    from optimizer.scenes.environments import get_environment

    backend.init()
    print(f"| scene | object's pixels | change > 0.5/255 | > 1/255 | > 2/255 | bitwise the background's |")
    print("|---|---|---|---|---|---|")
    integ = {"type": "path", "max_depth": 6, "rr_depth": 5}
    for name in a.scenes.split(","):
        pack = load_pack(name, a.views, a.resolution, 8000)
        env = get_environment(pack.environment)
        cams = evaluation_cameras(pack, a.views, seed=a.seed).cams
        mesh = static_object_fn(pack, prepare_object(pack, target_vertices=8000))()
        cov = np.stack([coverage_and_depth(scn.build_scene(env.build(), mesh), c, mesh)[0] for c in cams])
        bg = PathRenderer(env.build(), None, cams, integ, a.converged, a.seed)()
        wo = PathRenderer(env.build(), mesh, cams, integ, a.converged, a.seed)()
        ch = np.stack([R.change(wo[v], bg[v], np.ones(bg.shape[1:3], bool)) for v in range(len(cams))])
        print(f"| {name} | {np.mean(cov > 0):.0%} | " + " | ".join(f"{np.mean(ch > t / 255):.0%}" for t in (0.5, 1, 2))
              + f" | {np.all(wo == bg, -1).mean():.0%} |", flush=True)


if __name__ == "__main__":
    main()
