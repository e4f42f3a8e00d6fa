"""Quality against seconds: time-to-quality curves of ``camo optimize`` presets on every built-in scene.

For each scene and variant (default: ``fast``, the default preset, and ``paper``, the paper's schedule) one
``camo optimize`` run is made at the demo's sizes with ``--snapshot-every N``; every snapshot (the parameters
after N iterations, with the wall-clock seconds of the optimisation so far: warm start + Stage 1 + Stage 2
iterations and held-out checks, set-up excluded, as ``summary.json`` records them) and the run's result (with
held-out selection, the chosen iterate; ``kind = result`` in the CSV, a star in the plot) are then scored exactly like ``camo evaluate``:
rendered on jittered novel views (``--eval-views``, default 8, +-0.25 at radius 4, seed 0) at ``--eval-spp``
(default 64) with the evaluation path tracer, 8-bit sRGB, GANmouflage object crop, mean over views of crop
PSNR, SSIM, LPIPS-proxy and SIFID-proxy. All variants of a scene share the background render and cameras.

Outputs in ``--out``: ``curves.csv`` (one row per scene x variant x snapshot), ``curves.png`` (one panel per
scene and metric: quality vs seconds), ``marks.md`` (each variant's quality at the last snapshot taken within
20 / 60 / 180 s) and the with-object renders of the final snapshot per variant (``final_<scene>_<variant>.png``:
background row over object row). Variants run one after another in one process tree, so they see the same
machine load.

    python bench/bench_convergence.py [--scenes meadow,gravel] [--variants fast,paper] [--out bench_out/convergence]
    python bench/bench_convergence.py --scenes meadow --variants fast,paper,mean   # a baseline as a variant
    python bench/bench_convergence.py --scenes pack:meadow:backpack                # a user pack (paper start)
    python bench/bench_convergence.py --paper-sizes --scenes gravel                # 16 views, 128 px, 30k, 800 px

A variant is a preset name, a baseline method (``mean``, ``random``, ``greedy``: one point), or
``NAME=FLAGS`` with extra ``camo optimize`` flags, e.g. ``"t1=--init transmittance=1"``. ``NAME=@DIR [FLAGS]`` runs
``camo optimize`` from another checkout ``DIR`` (e.g. a ``git worktree`` of an older commit; its own default
preset unless FLAGS name one), so old and new code are timed side by side at the same machine load:

    python bench/bench_convergence.py --scenes gravel --variants "fast;old=@/tmp/wt-e2fc840" --no-score

Seconds (``timing.md``, printed too): per run its wall seconds and the CPU seconds of its process tree (user +
sys, ``getrusage(RUSAGE_CHILDREN)``: what the run cost, less swayed by other jobs than wall seconds), the load
average around it, and its phases as ``summary.json`` and ``log.jsonl`` record them (set-up, turn search, start
search, warm start, Stage 1 with its median step, Stage 2, the held-out checks). Above them, a **reference
render** timed in the same process before the runs: a fixed Cornell box (64 x 64 px, 128 spp, path depth 6, one
render thread, best of 3 after a compiling warm-up) in CPU seconds. It is what ties seconds to the machine: the
2026-11-26 code itself needs ~4-5x the CPU seconds per Stage 1 step on the machine of 2026-11-28 than it took on its
own (docs/results/convergence.md, "Seconds depend on the machine"), so rows with different reference seconds do not
compare in seconds.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DEMO = ["--views", "8", "--resolution", "96", "--target-vertices", "10000", "--map-resolution", "256",
        "--displacement-resolution", "128", "--spp", "4", "--target-spp", "32"]
PAPER_SIZES = ["--views", "16", "--resolution", "128", "--target-vertices", "30000", "--map-resolution", "800",
               "--displacement-resolution", "256", "--spp", "4", "--target-spp", "64"]
BASELINES = ("mean", "random", "greedy")
#: Size flags only `ours` reads: a baseline refuses them (``camo optimize --method mean --spp 4`` is an error).
OURS_ONLY = ("--displacement-resolution", "--spp")
METRICS = ("psnr", "ssim", "lpips_proxy", "sifid_proxy")
MARKS = (20.0, 60.0, 180.0)


def scene_label(name: str) -> str:
    """A scene's name in output paths: ``pack:ENV:OBJECT`` -> ``pack_ENV_OBJECT``, a pack file -> its stem."""
    if name.endswith(".toml"):
        return Path(name).stem
    return name.replace(":", "_")


def scene_arg(name: str, workdir: Path) -> str:
    """``pack:ENV:OBJECT`` -> a user pack file around a built-in environment (the paper's initial material)."""
    if not name.startswith("pack:"):
        return name
    _, env, obj = (name.split(":") + ["backpack"])[:3]
    path = workdir / f"pack_{env}_{obj}.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'name = "user-{env}-{obj}"\n[object]\nprimitive = "{obj}"\n[environment]\nbuiltin = "{env}"\n')
    return str(path)


def variant_flags(variant: str) -> tuple[str, list[str]]:
    name, _, flags = variant.partition("=")
    if name in BASELINES:
        return name, ["--method", name]
    if flags:
        return name, shlex.split(flags)
    return name, ["--preset", name]


def split_checkout(flags: list[str]) -> tuple[Path | None, list[str]]:
    """``["@DIR", *rest]`` -> ``(DIR, rest)``: the variant runs another checkout's ``camo``; else ``(None, flags)``.
    ValueError when DIR holds no ``camo`` package."""
    if not flags or not flags[0].startswith("@"):
        return None, flags
    checkout = Path(flags[0][1:]).expanduser().resolve()
    if not (checkout / "camo" / "cli.py").is_file():
        raise ValueError(f"{flags[0]}: no checkout of this project there (no camo/cli.py)")
    return checkout, flags[1:]


def child_cpu_seconds() -> float:
    """User + system CPU seconds of this process's finished children so far."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_variant(camo: str, scene: str, variant: str, sizes: list[str], out: Path, every: int) -> tuple[Path, dict]:
    """Run one variant; returns its run directory and ``{wall, cpu, load_before, load_after}`` (seconds of the
    whole ``camo optimize`` process tree, set-up included; load: the 1-minute load average)."""
    name, flags = variant_flags(variant)
    checkout, flags = split_checkout(flags)
    if name in BASELINES:
        pairs = list(zip(sizes[::2], sizes[1::2]))
        sizes = [x for flag, value in pairs if flag not in OURS_ONLY for x in (flag, value)]
    env, cwd = None, None
    if checkout is not None:  # the other checkout's code, this environment's interpreter
        camo_cmd = [sys.executable, "-m", "camo.cli"]
        env, cwd = {**os.environ, "PYTHONPATH": str(checkout)}, str(checkout)
    else:
        camo_cmd = [camo]
    cmd = [*camo_cmd, "optimize", scene, "--out", str(out.resolve()), *sizes, "--overwrite", "--quiet", *flags]
    if name not in BASELINES:
        cmd += ["--snapshot-every", str(every)]
    load0, cpu0, t = os.getloadavg()[0], child_cpu_seconds(), time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=env, cwd=cwd)
    return out, {"wall": time.perf_counter() - t, "cpu": child_cpu_seconds() - cpu0, "load_before": load0,
                 "load_after": os.getloadavg()[0]}


#: ``summary.json`` keys of a run's phases (seconds), in the order a run takes them; absent ones are left out.
PHASES = (("setup", "seconds_setup"), ("turn search", "seconds_pose_search"), ("start search", "seconds_start_search"),
          ("warm start", "seconds_warm_start"), ("Stage 1", "seconds_stage1"), ("Stage 2", "seconds_stage2"))


def phase_seconds(run_dir: Path) -> dict[str, float]:
    """A run's seconds per phase from its ``summary.json`` (:data:`PHASES`), its optimisation seconds, the held-out
    checks' seconds, and from ``log.jsonl`` Stage 1's step count and median step seconds (``s1 steps``,
    ``s1 step``: the step itself, held-out checks excluded)."""
    summary = json.loads((run_dir / "summary.json").read_text())
    out = {label: float(summary[key]) for label, key in PHASES if isinstance(summary.get(key), (int, float))}
    if isinstance(summary.get("seconds_optimisation"), (int, float)):
        out["optimisation"] = float(summary["seconds_optimisation"])
    holdout = summary.get("holdout") or {}
    if isinstance(holdout.get("seconds"), (int, float)):
        out["held-out"] = float(holdout["seconds"])
    log = run_dir / "log.jsonl"
    if log.is_file():
        steps = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
        s1 = [float(r["seconds"]) for r in steps if r.get("stage") == 1 and "seconds" in r]
        if s1:
            out["s1 steps"], out["s1 step"] = len(s1), statistics.median(s1)
    return out


def reference_render(repeats: int = 3) -> dict[str, float]:
    """CPU and wall seconds (best of ``repeats`` after a warm-up that compiles the kernels) of a fixed render on one
    Dr.Jit thread: Mitsuba's Cornell box, 64 x 64 px, 128 spp, path tracer depth 6, seed 0. The same work on every
    checkout and day, so it measures the machine (and the Mitsuba / Dr.Jit build), not the project's code."""
    import drjit as dr
    import mitsuba as mi

    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        scene_dict = mi.cornell_box()
        scene_dict["sensor"]["film"]["width"] = scene_dict["sensor"]["film"]["height"] = 64
        scene_dict["integrator"] = {"type": "path", "max_depth": 6}
        scene = mi.load_dict(scene_dict)
        best = {"cpu": float("inf"), "wall": float("inf")}
        for i in range(repeats + 1):
            c, t = time.process_time(), time.perf_counter()
            img = mi.render(scene, spp=128, seed=0)
            dr.eval(img)
            dr.sync_thread()
            if i:  # the first render compiles
                best = {"cpu": min(best["cpu"], time.process_time() - c), "wall": min(best["wall"], time.perf_counter() - t)}
        return best
    finally:
        dr.set_thread_count(threads)


def timing_table(timings: list[dict], reference: dict[str, float] | None) -> str:
    """``timing.md``: the reference render, then one row per run: wall / CPU seconds, load, phases."""
    cols = ["optimisation", "setup", "turn search", "start search", "warm start", "Stage 1", "s1 steps", "s1 step",
            "Stage 2", "held-out"]
    lines = []
    if reference is not None:
        lines += [f"Reference render (Cornell box 64 px, 128 spp, depth 6, 1 thread, best of 3): "
                  f"{reference['cpu']:.3f} CPU s, {reference['wall']:.3f} s wall", ""]
    lines += ["| scene | variant | run wall s | run CPU s | load before / after | " + " | ".join(cols) + " |",
              "|---|---|---|---|---|" + "---|" * len(cols)]
    for t in timings:
        cells = []
        for c in cols:
            v = t["phases"].get(c)
            cells.append("-" if v is None else (f"{v:d}" if isinstance(v, int) else f"{v:.2f}" if c == "s1 step" else f"{v:.1f}"))
        lines.append(f"| {t['scene']} | {t['variant']} | {t['wall']:.0f} | {t['cpu']:.0f} | "
                     f"{t['load_before']:.1f} / {t['load_after']:.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


class Scorer:
    """Scores parameter snapshots of one scene on jittered novel views, ``camo evaluate``'s way."""

    def __init__(self, run_dir: Path, views: int, spp: int):
        from evaluation.views import ViewRenderer, evaluation_cameras, evaluation_plan
        from optimizer.assets.rundir import open_run
        from optimizer.scenes.environments import get_environment

        run = open_run(run_dir)
        self.pack = run.pack
        self.env = get_environment(self.pack.environment)
        self.cams = evaluation_cameras(self.pack, views, 0.25, 0, tuple(self.pack.render.resolution)).cams
        self.integrator = evaluation_plan(self.pack, self.env, self.cams, spp).integrator
        self.renderer = ViewRenderer(spp, 0)
        self.bg = self.renderer.background(self.pack, self.env, self.cams, self.integrator)

    def score(self, run_dir: Path, values: dict[str, np.ndarray]) -> tuple[dict[str, float], np.ndarray]:
        from evaluation.evaluate import score_view, srgb8
        from optimizer.rendering import scene as scn
        from optimizer.rendering.appearance import Geometry, object_bsdf, world_positions
        from optimizer.rendering.placement import prepare_object
        from optimizer.assets.rundir import open_run

        run = open_run(run_dir)
        geometry = Geometry.build(prepare_object(run.pack), run.pack.object, run.app)

        def mesh():
            return scn.object_mesh(world_positions(geometry, values, run.app), geometry.faces, geometry.uvs,
                                   object_bsdf(values, run.app))

        objr = self.renderer.with_object(self.env, mesh, self.cams, self.integrator)
        acc: dict[str, list[float]] = {m: [] for m in METRICS}
        for v in range(len(self.cams)):
            for row in score_view(srgb8(objr.image[v]), srgb8(self.bg.image[v]), objr.mask[v], METRICS, {}):
                if row["region"] == "crop":
                    for m in METRICS:
                        if np.isfinite(row[m]):
                            acc[m].append(float(row[m]))
        return {m: float(np.mean(x)) if x else float("nan") for m, x in acc.items()}, objr.image


def snapshot_values(path: Path) -> tuple[dict[str, np.ndarray], float, int, int]:
    with np.load(path) as z:
        vals = {k: z[k] for k in z.files if k not in ("seconds", "iteration", "stage")}
        return vals, float(z["seconds"]), int(z["iteration"]), int(z["stage"])


def final_values(run_dir: Path) -> dict[str, np.ndarray]:
    """A baseline's parameters from its run directory (maps as optimised; no displacement, no pose)."""
    from optimizer.assets.rundir import open_run

    run = open_run(run_dir)
    maps = run.asset().values()
    rd = run.app.displacement_resolution
    return {**{k: v if v.ndim == 3 else v[..., None] for k, v in maps.items()},
            "displacement": np.zeros((rd, rd, 1), np.float32), "translation": np.zeros(3, np.float32),
            "rotation": np.zeros(1, np.float32)}


def at_mark(rows: list[dict], mark: float) -> dict | None:
    """The last snapshot taken within ``mark`` seconds; a run finished within the mark counts with its result (with
    held-out selection, the chosen iterate, which may be older than its last snapshot)."""
    inside = [r for r in rows if r["seconds"] <= mark + 1e-9]
    return max(inside, key=lambda r: (r["seconds"], r.get("kind") == "result")) if inside else None


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = plt.subplots(len(scenes), 2, figsize=(10, 3 * len(scenes)), squeeze=False)
    for i, sc in enumerate(scenes):
        for j, metric in enumerate(("psnr", "lpips_proxy")):
            ax = axes[i, j]
            for var in dict.fromkeys(r["variant"] for r in rows if r["scene"] == sc):
                mine = [r for r in rows if r["scene"] == sc and r["variant"] == var]
                pts = sorted((r["seconds"], r[metric]) for r in mine if r.get("kind") != "result")
                res = [(r["seconds"], r[metric]) for r in mine if r.get("kind") == "result"]
                if pts:
                    xs, ys = zip(*pts)
                    line, = ax.plot(xs, ys, "o-" if len(xs) > 1 else "s", label=var, ms=3)
                    colour = line.get_color()
                else:
                    colour = None
                if res:  # the run's result (held-out selection: the chosen iterate): a star at the run's end
                    ax.plot(*zip(*res), "*", ms=9, color=colour, label=None if pts else var)
            for m in MARKS:
                ax.axvline(m, color="0.8", lw=0.8, zorder=0)
            ax.set_title(f"{sc}: crop {metric} ({'higher' if metric == 'psnr' else 'lower'} is better)", fontsize=9)
            ax.set_xlabel("seconds of optimisation (2 CPU cores)")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="meadow,gravel,split,room,occluded,panorama")
    ap.add_argument("--variants", default="fast,paper", help="comma list; use ';' between variants whose flags hold commas")
    ap.add_argument("--every", type=int, default=5, help="snapshot every N iterations")
    ap.add_argument("--eval-views", type=int, default=8)
    ap.add_argument("--eval-spp", type=int, default=64)
    ap.add_argument("--paper-sizes", action="store_true", help="16 views, 128 px, 30k vertices, 800 px maps")
    ap.add_argument("--out", default="bench_out/convergence")
    ap.add_argument("--no-score", action="store_true", help="time the runs only (timing.md); no snapshot scoring")
    ap.add_argument("--no-reference", action="store_true", help="skip the reference render that times the machine")
    args = ap.parse_args()
    sep = ";" if ";" in args.variants else ","
    variants = [v.strip() for v in args.variants.split(sep) if v.strip()]
    try:
        for v in variants:
            split_checkout(variant_flags(v)[1])
    except ValueError as exc:
        ap.error(str(exc))

    from optimizer import backend
    from camo_base.imaging import linear_to_srgb, save_png

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    camo = str(Path(sys.executable).with_name("camo"))
    sizes = PAPER_SIZES if args.paper_sizes else DEMO
    backend.init()
    reference = None if args.no_reference else reference_render()
    if reference is not None:
        print(f"reference render: {reference['cpu']:.3f} CPU s, {reference['wall']:.3f} s wall", flush=True)
    rows: list[dict] = []
    timings: list[dict] = []
    finals: dict[tuple[str, str], float] = {}
    for scene in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        sarg = scene_arg(scene, out / "packs")
        scorer = None
        for variant in variants:
            name, _ = variant_flags(variant)
            run_dir = out / "runs" / scene_label(scene) / name
            _, cost = run_variant(camo, sarg, variant, sizes, run_dir, args.every)
            timings.append({"scene": scene, "variant": name, **cost, "phases": phase_seconds(run_dir)})
            print(json.dumps({"timing": timings[-1]}), flush=True)
            (out / "timing.md").write_text(timing_table(timings, reference))
            if args.no_score:
                continue
            if split_checkout(variant_flags(variant)[1])[0] is not None and not (run_dir / "snapshots").is_dir():
                print(f"{scene} {name}: another checkout's run without snapshots: timed, not scored", flush=True)
                continue
            scorer = scorer or Scorer(run_dir, args.eval_views, args.eval_spp)
            summary = json.loads((run_dir / "summary.json").read_text())
            if name in BASELINES:
                snaps = [(final_values(run_dir), float(summary["seconds_method"]), 0, 0, "result")]
            else:
                # every snapshot (the iterate at that time), then the run's result (with held-out selection: the
                # chosen iterate) at the run's end: at equal seconds the result sorts last
                snaps = [(*snapshot_values(p), "snapshot") for p in sorted((run_dir / "snapshots").glob("s*_*.npz"))]
                if (run_dir / "snapshots" / "result.npz").is_file():
                    snaps.append((*snapshot_values(run_dir / "snapshots" / "result.npz"), "result"))
                snaps.sort(key=lambda s: (s[1], s[4] == "result"))
            img = None
            for vals, secs, it, stage, kind in snaps:
                scores, img = scorer.score(run_dir, vals)
                rows.append({"scene": scene, "variant": name, "kind": kind, "stage": stage, "iteration": it,
                             "seconds": round(secs, 2), **{k: round(v, 4) for k, v in scores.items()}})
                print(json.dumps(rows[-1]), flush=True)
            finals[(scene, name)] = cost["wall"]
            if img is not None:
                strip = np.concatenate([np.concatenate(list(scorer.bg.image), 1), np.concatenate(list(img), 1)], 0)
                save_png(out / f"final_{scene_label(scene)}_{name}.png", linear_to_srgb(strip))
    print(timing_table(timings, reference))
    if args.no_score:
        return
    with open(out / "curves.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, out / "curves.png")
    lines = ["| scene | variant | " + " | ".join(f"{m:g} s: PSNR / LPIPS-proxy" for m in MARKS) + " | final (s) |",
             "|---|---|" + "---|" * (len(MARKS) + 1)]
    for scene, name in finals:
        rs = [r for r in rows if r["scene"] == scene and r["variant"] == name]
        cells = []
        for m in MARKS:
            r = at_mark(rs, m)
            cells.append(f"{r['psnr']:.2f} / {r['lpips_proxy']:.3f}" if r else "-")
        last = max(rs, key=lambda r: (r["seconds"], r["kind"] == "result"))
        cells.append(f"{last['psnr']:.2f} / {last['lpips_proxy']:.3f} ({last['seconds']:.0f})")
        lines.append(f"| {scene} | {name} | " + " | ".join(cells) + " |")
    (out / "marks.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
