"""Stage 1 speed: ``camo optimize`` iterations vs raw ``mi.render`` + ``dr.backward``, and a full run.

1. Overhead: per-iteration wall time of :class:`optimizer.optimise.stage1.Stage1` vs the raw
   Mitsuba work of the same scene, views, spp and integrator (each view rendered with
   gradients enabled on fresh leaves of the same parameter values, then ``dr.backward`` of
   its mean; the image is evaluated as a real loss would; every view's silhouette term).
   Target ratio <= 1.15.
2. A whole Stage 1 run on a built-in scene (default 16 views, 128^2, 50 iterations),
   wall time without set-up (target <= 60 s on 2 cores).

    python bench/bench_stage1.py [--scene gravel] [--views 16] [--resolution 128] [--iterations 50]
                                 [--spp 4] [--target-vertices 30000] [--map-resolution 800] [--ablate ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="gravel")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--target-vertices", type=int, default=30000)
    ap.add_argument("--map-resolution", type=int, default=800)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--ablate", default="")
    args = ap.parse_args()

    import drjit as dr
    import mitsuba as mi

    from optimizer import backend
    from optimizer.scenes import builtin_scenes
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment
    from optimizer.rendering.placement import prepare_object
    from optimizer.optimise.planning import measure_plan
    from optimizer.rendering.render import uses_batch
    from optimizer.assets.conditions import ablated_switches, parse_ablations
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.optimise.stage1 import Stage1, Stage1Config

    info = backend.init()
    pack = builtin_scenes.get(args.scene)
    pack.cameras = dataclasses.replace(pack.cameras, views=args.views)
    pack.render = dataclasses.replace(pack.render, resolution=(args.resolution, args.resolution))
    app = dataclasses.replace(AppearanceConfig(), **ablated_switches(parse_ablations(args.ablate)),
                              map_resolution=args.map_resolution)
    env = get_environment(pack.environment)
    t = time.perf_counter()
    prepared = prepare_object(pack, target_vertices=args.target_vertices)
    t_mesh = time.perf_counter() - t
    cams = cameras(pack)
    pl = measure_plan(pack, env, prepared, cams, app, 0, {"training": args.spp, "targets": 64})  # a run's plan
    t = time.perf_counter()
    s1 = Stage1(pack, env, prepared, cams, pl, Stage1Config(spp=args.spp, iterations=args.iterations), app).prepare()
    t_setup = time.perf_counter() - t

    # --- raw Mitsuba: the same scene and parameters, render + backward per view ---
    params = s1.params
    keys = [k for k in s1._keys.values() if k in params]
    leaves = {}
    for k in keys:
        leaves[k] = type(params[k])(params[k])
        dr.enable_grad(leaves[k])

    integ = s1.scene.integrator()

    def raw_iteration(it: int) -> None:
        saved = getattr(integ, "silhouette_views", None)
        if saved is not None:
            integ.silhouette_views = None  # raw: every view's silhouette term (Stage 1 samples a subset per step)
        try:
            _raw_iteration(it)
        finally:
            if saved is not None:
                integ.silhouette_views = saved

    def _raw_iteration(it: int) -> None:
        if uses_batch(pl.integrator):
            for k in keys:
                params[k] = leaves[k]
            params.update()
            img = mi.render(s1.scene, params, spp=args.spp, seed=it, seed_grad=it + 1)
            dr.eval(img)  # a real loss reads the image; mean() alone would let the primal kernel be skipped
            dr.backward(dr.mean(img.array))
            dr.eval([dr.grad(x) for x in leaves.values()])
        else:
            # Fresh leaves per view, as in Stage 1: backward clears the graph, and re-assigning the same leaf
            # makes the scene skip its update, so views 2..V would send no gradient to the vertex positions
            # (tests/test_stage1_gradients.py). The fresh leaves cost a BVH rebuild per view, like Stage 1's.
            for v in range(len(cams)):
                fresh = []
                for k in keys:
                    x = dr.detach(leaves[k])
                    dr.enable_grad(x)
                    params[k] = x
                    fresh.append(x)
                params.update()
                img = mi.render(s1.scene, params, sensor=v, spp=s1.render_spp, seed=it * 97 + v, seed_grad=it * 97 + v + 1)
                dr.eval(img)
                dr.backward(dr.mean(img.array))
                dr.eval([dr.grad(x) for x in fresh])  # each view's gradients are computed, not left lazy
        dr.eval([dr.grad(x) for x in leaves.values()])  # gradients are lazy: force them, as Adam does
        dr.sync_thread()  # LLVM kernels run asynchronously: wait for them (Stage 1 reads its losses back)

    raw_iteration(0)  # JIT warm-up
    t = time.perf_counter()
    s1.step()
    first_s = time.perf_counter() - t
    raw, ours = [], []
    for r in range(args.reps):  # interleave to share any load drift
        t = time.perf_counter()
        raw_iteration(r + 1)
        raw.append(time.perf_counter() - t)
        t = time.perf_counter()
        s1.step()
        ours.append(time.perf_counter() - t)
    raw_s, ours_s = min(raw), min(ours)

    # --- a whole run (continues the same optimiser; its warm-up is already done) ---
    t = time.perf_counter()
    while s1.iteration < args.iterations:
        s1.step()
    run_s = time.perf_counter() - t
    done = args.iterations - 1 - args.reps
    total = first_s + sum(ours) + run_s

    print(f"\nbackend {info.variant}, {info.threads} threads; scene {args.scene}, {args.views} views at "
          f"{args.resolution}^2, {args.spp} spp, {len(prepared.vertices)} vertices, maps {args.map_resolution}^2, "
          f"integrator {pl.integrator}\n")
    print("| measure | seconds |")
    print("|---|---|")
    print(f"| mesh preparation (cached after the first run) | {t_mesh:.2f} |")
    print(f"| Stage 1 set-up (targets at 64 spp, domain, scene) | {t_setup:.2f} |")
    print(f"| raw mi.render + dr.backward per iteration (best of {args.reps}) | {raw_s:.3f} |")
    print(f"| camo Stage 1 per iteration (best of {args.reps}) | {ours_s:.3f} |")
    print(f"| ratio camo / raw (target <= 1.15) | {ours_s / raw_s:.3f} |")
    print(f"| first iteration (JIT compilation) | {first_s:.2f} |")
    print(f"| {done} further iterations | {run_s:.1f} |")
    print(f"| whole {args.iterations}-iteration Stage 1, excluding set-up | {total:.1f} |")


if __name__ == "__main__":
    main()
