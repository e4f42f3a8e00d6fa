"""Accuracy vs time of Stage 1: what each setting costs and what it buys.

Sweeps spp (1, 4, 16), resolution (64, 128, 256), iterations (10, 25, 50, 100) and the
effect planner (on / off = always full path tracing). By default one factor at a time
around a base setting (spp 4, resolution 64, 25 iterations, planner on); ``--grid full``
runs the whole product. Iteration counts share one run (snapshots at 10, 25, 50, 100).
Planner off costs ~100x per iteration (full path tracing with projective indirect
sampling), so that arm runs ``--full-iterations`` (default 3) and the base setting also
snapshots there: same iterations, planner on vs off, side by side.

For each setting it prints the wall time of the iterations, the final loss on the training
views and the loss on jittered held-out views (+-0.25 at radius 4), both rendered with the
path tracer at ``--eval-spp``, and writes ``tradeoff.md`` and ``tradeoff.png`` (time vs
held-out loss, Pareto points marked) into ``--out``.

    python bench/bench_tradeoff.py [--scene gravel] [--views 8] [--out bench_out/tradeoff] [--grid full]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import time
from pathlib import Path

import numpy as np


def heldout_loss(s1, values, cams, eval_spp: int, seed: int) -> float:
    from optimizer.rendering import scene as scn
    from optimizer.optimise.loss import gated_loss_np
    from optimizer.rendering.render import coverage_and_depth, render_shaded
    from optimizer.assets.result import Result, render_result
    from optimizer.optimise.stage1 import influence_domain

    integ = s1.shading_integrator()
    bg = render_shaded(s1.env.build(), None, cams, integ, eval_spp, seed)
    res = Result(s1.pack, s1.env, cams, s1.geometry, values, s1.app, integ, eval_spp, None)
    fin = render_result(res, seed=seed + 1)
    obj = s1._object()
    sc = scn.build_scene(s1.env.build(), obj)
    losses = []
    for v, c in enumerate(cams):
        cov, _ = coverage_and_depth(sc, c, obj)
        dom = influence_domain(bg[v], fin[v], cov, 0.05, max(1, round(0.04 * c.width)))
        losses.append(gated_loss_np(fin[v], bg[v], dom))
    return float(np.mean(losses))


def train_loss(s1, values, eval_spp: int) -> float:
    from optimizer.optimise.loss import gated_loss_np
    from optimizer.assets.result import Result, render_result

    res = Result(s1.pack, s1.env, s1.cams, s1.geometry, values, s1.app, s1.shading_integrator(), eval_spp, None)
    fin = render_result(res, seed=4242)
    return float(np.mean([gated_loss_np(fin[v], s1.targets.background[v], s1.targets.domain[v]) for v in range(len(fin))]))


def pareto(points: list[tuple[float, float]]) -> list[bool]:
    return [not any(t2 <= t and l2 <= l and (t2, l2) != (t, l) for t2, l2 in points) for t, l in points]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="gravel")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--target-vertices", type=int, default=8000)
    ap.add_argument("--map-resolution", type=int, default=256)
    ap.add_argument("--eval-spp", type=int, default=64)
    ap.add_argument("--grid", choices=("oat", "full"), default="oat")
    ap.add_argument("--full-iterations", type=int, default=3, help="iterations of the planner-off (full) arm")
    ap.add_argument("--out", default="bench_out/tradeoff")
    args = ap.parse_args()

    from optimizer import backend
    from optimizer.scenes import builtin_scenes
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.scenes.cameras import cameras, jitter
    from optimizer.scenes.environments import get_environment
    from optimizer.rendering.placement import prepare_object
    from optimizer.optimise.planning import measure_plan
    from optimizer.rendering.planner import full_plan
    from optimizer.optimise.stage1 import Stage1, Stage1Config

    info = backend.init()
    spps, resolutions, its, planners = (1, 4, 16), (64, 128, 256), (10, 25, 50, 100), (True, False)
    base = (4, 64, True)
    if args.grid == "full":
        settings = list(itertools.product(spps, resolutions, planners))
    else:
        settings = sorted({base} | {(s, base[1], base[2]) for s in spps} | {(base[0], r, base[2]) for r in resolutions}
                          | {(base[0], base[1], p) for p in planners}, key=lambda x: (x[2], x[1], x[0]))
    env = None
    rows = []
    for spp, res, planner in settings:
        pack = builtin_scenes.get(args.scene)
        pack.cameras = dataclasses.replace(pack.cameras, views=args.views)
        pack.render = dataclasses.replace(pack.render, resolution=(res, res))
        env = env or get_environment(pack.environment)
        prepared = prepare_object(pack, target_vertices=args.target_vertices)
        app = AppearanceConfig(map_resolution=args.map_resolution, displacement_resolution=args.map_resolution // 2)
        cams = cameras(pack)
        pl = measure_plan(pack, env, prepared, cams, app, 0, {"training": spp, "targets": args.eval_spp}) if planner \
            else full_plan("optimize", geometry=True)
        held = jitter(cams, 0.25, pack.cameras.radius, seed=11)
        s1 = Stage1(pack, env, prepared, cams, pl, Stage1Config(spp=spp, target_spp=args.eval_spp, seed=0), app).prepare()
        if not planner:
            wanted = (args.full_iterations,)
        elif (spp, res, planner) == base or args.grid == "full":
            wanted = tuple(sorted({*its, args.full_iterations}))
        else:
            wanted = (25,)
        elapsed = 0.0
        for n in sorted(wanted):
            while s1.iteration < n:
                t = time.perf_counter()
                s1.step()
                elapsed += time.perf_counter() - t
            vals = s1.current_values()
            rows.append({"spp": spp, "resolution": res, "iterations": n, "planner": planner, "seconds": elapsed,
                         "train_loss": train_loss(s1, vals, args.eval_spp),
                         "heldout_loss": heldout_loss(s1, vals, held, args.eval_spp, seed=77)})
            print(rows[-1], flush=True)

    front = pareto([(r["seconds"], r["heldout_loss"]) for r in rows])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"Stage 1 accuracy vs time — scene {args.scene}, {args.views} views, {args.target_vertices} vertices, "
             f"maps {args.map_resolution}^2, {info.variant} on {info.threads} threads; losses at {args.eval_spp} spp", "",
             "| spp | resolution | iterations | planner | seconds | train loss | held-out loss | Pareto |",
             "|---|---|---|---|---|---|---|---|"]
    for r, p in zip(rows, front):
        lines.append(f"| {r['spp']} | {r['resolution']} | {r['iterations']} | {'on' if r['planner'] else 'off (full)'} | "
                     f"{r['seconds']:.1f} | {r['train_loss']:.4f} | {r['heldout_loss']:.4f} | {'*' if p else ''} |")
    table = "\n".join(lines)
    (out / "tradeoff.md").write_text(table + "\n")
    print("\n" + table)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4), dpi=110)
    for r, p in zip(rows, front):
        ax.scatter(r["seconds"], r["heldout_loss"], c="tab:red" if p else "tab:blue", s=30)
        ax.annotate(f"{r['spp']}spp {r['resolution']}px {r['iterations']}it{'' if r['planner'] else ' full'}",
                    (r["seconds"], r["heldout_loss"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("seconds (Stage 1 iterations)")
    ax.set_ylabel("held-out loss (jittered views)")
    ax.set_title("accuracy vs time (red: Pareto front)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "tradeoff.png")
    print(f"wrote {out / 'tradeoff.md'} and {out / 'tradeoff.png'}")


if __name__ == "__main__":
    main()
