"""Where a Stage 1 step's seconds go, the training plan against full light transport, per scene.

The bench's Stage 1 probe (``bench_planner.py --only grad``: the run's starting state, the training plan measured
by the pilot, 4 views at 64 px) split into its phases, each closed by a ``dr.sync_thread``: the parameter mapping
pushed into the scene (displacement, pose, the BVH rebuild: ``apply``), every view's primal render and loss
(``forward``), the adjoint pass (``backward``: path replay plus the primary-silhouette term on the step's silhouette
views) and the gradients read back (``read``). Settings: the plan at ``--levels`` spp; ``full-lt`` (depth 12, whole
frames, the plan's projective settings, the bench's comparator) at ``--spp``; the plan at ``--spp`` without the
silhouette term on any view (``no-sil``) and on whole frames at its depth (``no-window``): what each of the plan's
decisions changes in a step. CPU seconds (this process, every thread), least of ``--reps`` after the untimed warm-up
steps that compile every view's kernels (:func:`bench_planner.warmup_iterations`; their seconds are printed as the
one-off cost); the syncs cost a little pipelining, so the phases sum to slightly more than a step of
``bench_planner.py``.

    python bench/bench_stage1_phases.py --scenes meadow,room [--views 4] [--resolution 64] [--spp 4] [--reps 3]

``--sequence N`` instead times the plan's (``--sequence-of full-lt``: full-lt's) first ``N`` steps at ``--spp`` in order, with no warm-up, each with the view
its silhouette term ran on: what the JIT costs a run the first time each view has its silhouette pass.
``--windows per-view`` gives each view its own training window (before issue 28: every window compiled its own
kernels); run it with a fresh Dr.Jit kernel cache (``HOME=$(mktemp -d)``) to see a first run's compiles.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

PHASES = ("apply", "forward", "backward", "read")


def step_phases(s1, iteration: int, silhouette: bool = True) -> dict[str, float]:
    """One Stage 1 gradient (:meth:`Stage1._photometric_backward` with the plain per-view loss) timed by phase."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.optimise.adam import dr_numpy

    clock = time.process_time
    s1.iteration = iteration
    views = s1.views_for_step()
    out = {}
    t = clock()
    s1._apply()
    dr.sync_thread()
    out["apply"] = clock() - t
    t = clock()
    s1._choose_silhouette_views(views)
    integ = s1.scene.integrator()
    if not silhouette and hasattr(integ, "silhouette_views"):
        integ.silhouette_views = {}  # no view: the primary-silhouette pass is skipped everywhere
    total = mi.Float(0.0)
    for v in views:
        s, sg = s1._seeds(v)
        img = mi.render(s1.scene, s1.params, sensor=v, spp=s1.render_spp, seed=s, seed_grad=sg)
        lv, _ = s1._view_loss(img, v)
        total += lv / len(views)
    photo = dr.detach(total)
    dr.eval(photo)
    dr.sync_thread()
    out["forward"] = clock() - t
    t = clock()
    dr.backward(total)
    dr.sync_thread()
    out["backward"] = clock() - t
    t = clock()
    for name in s1.opt.values:
        dr_numpy(dr.grad(s1.opt[name]))
        dr.clear_grad(s1.opt[name])
    out["read"] = clock() - t
    out["step"] = sum(out[p] for p in PHASES)
    out["loss"] = float(photo[0])
    return out


def sequence(name: str, args) -> list[dict]:
    """The first ``args.sequence`` Stage 1 steps of the plan (or of ``full-lt``) in order (module doc)."""
    import dataclasses

    from optimizer.optimise.stage1 import Stage1

    st, plan, base, (pack, env, prepared, cams, app) = _setup(name, args)
    if args.sequence_of == "full-lt":
        deep = {"type": plan.integrator["type"], "max_depth": 12, "rr_depth": 5, "sppi": 0}
        full_lt = dataclasses.replace(plan, integrator={**plan.integrator, **deep}, max_depth=12, region=False)
        st = Stage1(pack, env, prepared, cams, full_lt, base, app, initial=st.current_values()).prepare(
            targets=st.targets)
    print(f"{name}: training windows {st.windows}", flush=True)
    out = []
    for k in range(args.sequence):
        p = step_phases(st, 40_000 + k)
        views = st.scene.integrator().silhouette_views
        out.append({"step": k, "seconds": p["step"], "silhouette_views": sorted(views) if views else "all"})
        print(f"{name} step {k}: {p['step']:.2f} CPU s, silhouette on {out[-1]['silhouette_views']}", flush=True)
    return out


def _setup(name: str, args):
    """The plan's Stage 1 at ``args.spp`` and what the other settings are built from."""
    from bench_planner import load_pack

    from optimizer.optimise.planning import measure_plan
    from optimizer.optimise.stage1 import Stage1, Stage1Config
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.rendering.placement import prepare_object
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment

    pack = load_pack(name, args.views, args.resolution, args.target_vertices)
    env = get_environment(pack.environment)
    prepared = prepare_object(pack, target_vertices=args.target_vertices)
    cams = cameras(pack)
    app = AppearanceConfig(map_resolution=args.map_resolution, displacement_resolution=args.map_resolution // 2)
    plan = measure_plan(pack, env, prepared, cams, app, args.seed, {"training": args.spp, "targets": 32})
    base = Stage1Config(spp=args.spp, target_spp=32, seed=args.seed)
    first = Stage1(pack, env, prepared, cams, plan, base, app).prepare()
    return first, plan, base, (pack, env, prepared, cams, app)


def bench_scene(name: str, args) -> dict:
    from bench_planner import warmup_iterations

    from optimizer.optimise.stage1 import Stage1

    first, plan, base, (pack, env, prepared, cams, app) = _setup(name, args)
    targets, values = first.targets, first.current_values()
    deep = {"type": plan.integrator["type"], "max_depth": 12, "rr_depth": 5, "sppi": 0}
    full_lt = dataclasses.replace(plan, integrator={**plan.integrator, **deep}, max_depth=12, region=False)
    settings = [(f"plan@{s}", plan, s, True) for s in args.levels] + [
        (f"full-lt@{args.spp}", full_lt, args.spp, True),
        (f"no-sil@{args.spp}", plan, args.spp, False),
        (f"no-window@{args.spp}", dataclasses.replace(plan, region=False), args.spp, True)]
    stages, warm = {}, {}
    for label, pl, spp, sil in settings:
        st = Stage1(pack, env, prepared, cams, pl, dataclasses.replace(base, spp=spp), app,
                    initial=values).prepare(targets=targets)
        t = time.process_time()
        for k in warmup_iterations(st, 1, 30_000):  # the JIT compiles, every view's silhouette pass among them
            step_phases(st, k, sil)
        warm[label] = time.process_time() - t
        stages[label] = (st, sil)
    rows = {label: [] for label in stages}
    for rep in range(args.reps):  # interleaved: the load hits every setting alike
        for label, (st, sil) in stages.items():
            rows[label].append(step_phases(st, 40_000 + rep, sil))
    summary = {label: {k: float(np.min([r[k] for r in rs])) for k in (*PHASES, "step")} for label, rs in rows.items()}
    window = float(np.mean([(b[2] - b[0]) * (b[3] - b[1]) / args.resolution ** 2 for b in first.windows])) \
        if first.windows else 1.0
    return {"scene": name, "max_depth": plan.max_depth, "integrator": plan.integrator["type"], "window": window,
            "phases": summary, "warmup_seconds": warm, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="meadow,room")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--target-vertices", type=int, default=8000)
    ap.add_argument("--map-resolution", type=int, default=128)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--levels", default="1,4", help="the plan's spp levels")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sequence", type=int, default=0, help="time the plan's first N steps in order instead")
    ap.add_argument("--sequence-of", choices=("plan", "full-lt"), default="plan")
    ap.add_argument("--windows", choices=("shared", "per-view"), default="shared",
                    help="one training window for all views (the default) or one per view (before issue 28)")
    ap.add_argument("--out", default="bench_out/stage1_phases.json")
    args = ap.parse_args()
    args.levels = [int(x) for x in args.levels.split(",") if x]
    if args.views < 1 or args.resolution < 8 or args.spp < 1 or args.reps < 1 or not args.levels:
        ap.error("--views, --spp, --reps >= 1, --resolution >= 8, --levels not empty")

    from optimizer import backend
    from optimizer.optimise.stage1 import Stage1

    backend.init()
    Stage1.shared_window = args.windows == "shared"
    out = []
    for name in [s for s in args.scenes.split(",") if s]:
        if args.sequence > 0:
            out.append({"scene": name, "sequence": sequence(name, args)})
            continue
        r = bench_scene(name, args)
        out.append(r)
        print(f"\n{name}: plan {r['integrator']} depth {r['max_depth']}, window {r['window']:.0%} of the frame "
              f"({args.views} views at {args.resolution} px); CPU s, least of {args.reps}")
        print("| setting | " + " | ".join(PHASES) + " | step | warm-up (compiles) |")
        print("|---" * (len(PHASES) + 3) + "|")
        for label, p in r["phases"].items():
            print(f"| {label} | " + " | ".join(f"{p[k]:.2f}" for k in PHASES) + f" | {p['step']:.2f} | "
                  f"{r['warmup_seconds'][label]:.1f} |")
        sys.stdout.flush()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"args": vars(args), "scenes": out}, indent=1))


if __name__ == "__main__":
    main()
