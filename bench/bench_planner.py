"""Effect planner vs always-full path tracing, per built-in scene.

For each built-in scene and the full method's parameters (pose, displacement,
BSDF, transmittance), time one render + backward of the Stage 1 gradient pass
with the planned integrator and with the reference "always full" setting
(``prb_projective``, max_depth 12, indirect visibility sampling on), and
measure the image difference between the planned and the full light transport
(PSNR of path-traced renders at high spp).

    python bench/bench_planner.py [--views 2] [--resolution 64] [--spp 4] [--ref-spp 512] [--scenes meadow,room]

Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    from camo_base.imaging import linear_to_srgb

    mse = float(np.mean((linear_to_srgb(a) - linear_to_srgb(b)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def time_gradient_pass(pack, env, prepared, cams, plan_, spp: int, reps: int) -> float:
    """Seconds per view of render + backward through all Stage 1 parameters (after one warm-up)."""
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.optimise.stage1 import Stage1, Stage1Config

    s1 = Stage1(pack, env, prepared, cams, plan_, Stage1Config(spp=spp, target_spp=4),
                AppearanceConfig(map_resolution=128, displacement_resolution=64)).prepare()
    s1.step()  # JIT compile
    t = time.perf_counter()
    for _ in range(reps):
        s1.step()
    return (time.perf_counter() - t) / reps / len(cams)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--ref-spp", type=int, default=512)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--target-vertices", type=int, default=8000)
    ap.add_argument("--scenes", default="")
    args = ap.parse_args()

    from optimizer import backend
    from optimizer.scenes import builtin_scenes
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment
    from optimizer.rendering.placement import prepare_object, static_object_fn
    from optimizer.rendering.planner import full_plan, plan
    from optimizer.rendering.render import render_shaded

    info = backend.init()
    names = args.scenes.split(",") if args.scenes else builtin_scenes.names()
    params = {"albedo", "pose", "displacement", "bsdf", "transmittance"}
    rows = []
    for name in names:
        pack = builtin_scenes.get(name)
        pack.cameras = dataclasses.replace(pack.cameras, views=args.views)
        pack.render = dataclasses.replace(pack.render, resolution=(args.resolution, args.resolution))
        env = get_environment(pack.environment)
        prepared = prepare_object(pack, target_vertices=args.target_vertices)
        cams = cameras(pack)
        planned, full = plan(pack, env, params), full_plan("optimize", geometry=True)
        t_plan = time_gradient_pass(pack, env, prepared, cams, planned, args.spp, args.reps)
        t_full = time_gradient_pass(pack, env, prepared, cams, full, args.spp, args.reps)
        obj = static_object_fn(pack, prepared)
        img_plan = render_shaded(env.build(), obj(), cams, {"type": "path", "max_depth": planned.max_depth}, args.ref_spp, 1)
        img_full = render_shaded(env.build(), obj(), cams, {"type": "path", "max_depth": 12}, args.ref_spp, 1)
        rows.append((name, planned.integrator, t_plan, t_full, psnr(img_plan, img_full)))
        print(f"{name}: done", flush=True)

    print(f"\nbackend {info.variant}, {info.threads} threads; {args.views} views at {args.resolution}^2, "
          f"{args.spp} spp, {args.target_vertices} vertices; PSNR at {args.ref_spp} spp\n")
    print("| scene | planned integrator | planned s/view | full s/view | speed-up | PSNR planned vs full (dB) |")
    print("|---|---|---|---|---|---|")
    for name, integ, tp, tf, p in rows:
        desc = f"{integ['type']} depth {integ.get('max_depth', 2)}" + (" sppi 0" if integ.get("sppi") == 0 else "")
        print(f"| {name} | {desc} | {tp:.3f} | {tf:.3f} | {tf / tp:.1f}x | {p:.1f} |")


if __name__ == "__main__":
    main()
