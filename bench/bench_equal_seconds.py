"""Issue 32's glint defences on the built-in scenes at equal seconds: off vs on, several seeds, scored like ``camo
evaluate``.

Issue 32 keeps a robustness change only if neither the hard-case benchmark (``bench/bench_hard_cases.py``) nor the
built-in scenes get worse *at equal seconds*. This benchmark runs, for each built-in scene and each seed, the two
variants of ``bench_hard_cases.VARIANTS``:

* ``before``: the fast preset with the three parts off (``--loss-clamp 0 --grad-clip 0 --init-search off``);
* ``after``: the fast preset as it is (``--loss-clamp 8 --grad-clip 4 --init-search on``; on a built-in scene without
  ``--init`` the init search has nothing to try, so the two differ by the clamp and the clip);

each as its own ``camo optimize`` process (the CLI a user runs: no kernel or scene cache in memory shared between
the variants) with the same ``--time-budget`` and no iteration cap, at small sizes (4 views at 64 px, 128 px maps,
64 px displacement, 2,000 vertices, 32-spp targets), on one LLVM thread (``--threads 1``).

**Equal CPU seconds, not wall seconds.** ``--time-budget`` counts wall-clock seconds of warm start + searches +
Stage 1 + Stage 2 iterations. On a shared machine that is no budget at all: at a load average of 11.6 on 2 cores a
75 s budget bought the ``before`` run of occluded 1 Stage 1 iteration (51 CPU seconds in 275 wall seconds, its
first iteration 86 s) and the ``after`` run 6 (30 CPU seconds in 155 s). So each run's process points the
optimiser's clock (``time.perf_counter``, read by the budget, the stage timers and the log) at ``time.process_time``
before ``camo.cli.main`` starts (:data:`CHILD`): the budget is then CPU seconds of the process, which another
engineer's load does not consume, and the run's seconds in ``log.jsonl`` / ``summary.json`` are CPU seconds too. With
one LLVM thread a CPU second is a second of one core. Nothing in the optimiser waits on that clock (no timeouts or
sleeps read it), so only the budget's and the timers' unit changes.

Before each measured run the same command runs once unscored with a budget of :data:`WARMUP_BUDGET` (same scene,
variant and seed): a cold first run spent 51 CPU seconds where the same run warm took 15, compiling kernels that
Dr.Jit keeps in its on-disk cache for later processes, and a warm-up with another seed and fixed iterations did not
warm them (the measured runs' first Stage 1 iteration still took 7-11 CPU s against 0.5 for their third). The
measured runs go in alternating order from seed to seed (``before`` first for even seed indices). ``--jobs N`` runs
N tasks at a time (one per scene and seed: its warm-ups, then its variants back to back; then one ``camo evaluate``
per scene): the budget is CPU time, so the number of jobs and the load do not change what a run gets. Wall and CPU
seconds of each whole process (set-up and final render included: ``getrusage`` of the child) are reported beside the
iterations each budget bought.

All runs of a scene are then scored together by one ``camo evaluate`` process: 8 jittered novel views (jitter 0.25,
the evaluation's seed ``EVAL_SEED``, not any run's), 64 spp with the evaluation's noise matching, shared background
renders, metrics ``psnr`` and ``lpips`` (AlexNet v0.1 with the installed weights) on the GANmouflage object crop
(``region == "crop"``), averaged over the views. The table gives, per scene, each variant's mean and sample standard
deviation over seeds, the paired difference ``after - before`` (same seed) with its standard deviation, and a
verdict: **worse** when the mean paired difference is worse than zero by more than two standard errors (``2 sd /
sqrt(n)``) on either metric, **better** when better by that much on either and worse on neither, **same** otherwise.
With 3 seeds that is a loose test (it flags "worse" readily), which is the safe side for a keep-only-if-not-worse
rule.

    python bench/bench_equal_seconds.py --jobs 2 --write            # six scenes, 3 seeds, 60 CPU s: the doc's table
    python bench/bench_equal_seconds.py --scenes occluded --seeds 0,1,2,3,4 --budget 90
    python bench/bench_equal_seconds.py --rows runs.json --write    # re-table an earlier --json, no runs
    python bench/bench_equal_seconds.py --rows a.json b.json --write # merge runs made at different times
    python bench/bench_equal_seconds.py --variants before,after,no-clamp --scenes occluded

Without ``--write`` nothing but the printed table and (``--json``) the per-run rows is written.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _hard_cases():
    """``bench/bench_hard_cases.py`` as a module (bench/ is not a package): its variants, sizes and Markdown block
    writer are shared so that the two benchmarks compare the same things."""
    name = "bench_hard_cases"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / "bench" / "bench_hard_cases.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod  # dataclasses look their module up
        spec.loader.exec_module(mod)
    return sys.modules[name]


HC = _hard_cases()
SCENES = HC.BUILTIN
#: Run sizes: 4 views at 64 px, the hard cases' maps and mesh (``bench_hard_cases.SIZES``), no iteration caps.
SIZES = {"views": 4, "resolution": 64, "map_resolution": 128, "displacement_resolution": 64, "target_vertices": 2000,
         "target_spp": 32, "threads": 1}
DEFAULT_SEEDS = (0, 1, 2)
#: CPU seconds of optimisation per run (``--time-budget`` on the process clock, module doc).
DEFAULT_BUDGET = 60.0
#: The child process: ``camo optimize`` with the optimiser's clock on the process's CPU time (module doc).
CHILD = "import sys, time; time.perf_counter = time.process_time; from camo.cli import main; sys.exit(main())"
#: CPU seconds of the unscored warm-up that runs the measured command first (module doc): it fills Dr.Jit's on-disk
#: kernel cache, so that no measured run pays compilation from its budget.
WARMUP_BUDGET = 1.0
#: The evaluation's camera-jitter and sampler seed (no run uses it).
EVAL_SEED = 4099
EVAL_VIEWS = 8
EVAL_SPP = 64
METRICS = ("psnr", "lpips")
#: Metric -> +1 when higher is better, -1 when lower is better.
SENSE = {"psnr": 1.0, "lpips": -1.0}
DOC = ROOT / "docs" / "results" / "hard_cases.md"
BLOCK = "equal_seconds"


# ------------------------------------------------------------------------------------------------------------------
# running

def cli_args(options: dict[str, Any]) -> list[str]:
    """``camo optimize`` arguments of ``{option: value}`` (the scene first, then ``--name value`` flags).

    >>> cli_args({"scene": "meadow", "views": 4, "loss_clamp": 0.0, "init_search": "off"})
    ['meadow', '--views', '4', '--loss-clamp', '0.0', '--init-search', 'off']
    """
    args = [str(options["scene"])]
    for k, v in options.items():
        if k != "scene":
            args += [f"--{k.replace('_', '-')}", str(v)]
    return args


def optimise(scene: str, variant: str, seed: int, budget: float, out: Path, say) -> dict[str, Any]:
    """One ``camo optimize`` process of ``scene`` / ``variant`` / ``seed`` with ``--time-budget budget`` (CPU
    seconds) into ``out``; its seconds (wall, CPU of the process, the optimiser's own), iterations and held-out
    record."""
    options = {"scene": scene, **SIZES, **HC.VARIANTS[variant], "seed": seed, "time_budget": budget,
               "snapshot_every": 100_000}
    cmd = [sys.executable, "-c", CHILD, "optimize", *cli_args(options), "--out", str(out), "--quiet"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out.parent.mkdir(parents=True, exist_ok=True)
    log = out.parent / f"{out.name}.log"
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own CPU time (other jobs' children run meanwhile)
        proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    cpu = usage.ru_utime + usage.ru_stime
    if proc.returncode != 0:
        tail = log.read_text().strip().splitlines()[-1:] or ["(no output)"]
        raise RuntimeError(f"camo optimize {scene} ({variant}, seed {seed}) failed: {tail[0]} (log: {log})")
    recs = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines() if line.strip()]
    summary = json.loads((out / "summary.json").read_text())
    s1 = [r for r in recs if r.get("stage") == 1]
    s2 = [r for r in recs if r.get("stage") == 2]
    row = {"scene": scene, "variant": variant, "seed": seed, "budget": budget, "run": str(out),
           "wall_seconds": wall, "cpu_seconds": cpu, "stage1_iterations": len(s1), "stage2_iterations": len(s2),
           "clipped_steps": sum(bool(r.get("grad_clipped")) for r in recs),
           "spike": HC.loss_spike([r["loss_photo"] for r in s1]),
           "spike_linear": HC.loss_spike([r.get("loss_linear", r["loss_photo"]) for r in s1]),
           "holdout_best": max((c["psnr"] for c in (summary.get("holdout") or {}).get("checks", [])),
                               default=float("nan"))}
    say(f"  {variant:>8} seed {seed}: {len(s1)} + {len(s2)} iterations in {wall:.0f} s wall, {cpu:.0f} s CPU")
    return row


def score(rows: list[dict[str, Any]], out: Path) -> None:
    """Add each row's crop ``psnr`` and ``lpips`` (means over the evaluation views) from one ``camo evaluate``
    process over all the rows' runs (one scene: the background renders are shared)."""
    import pandas as pd

    cmd = [sys.executable, "-m", "camo.cli", "evaluate", *[r["run"] for r in rows], "--out", str(out),
           "--views", str(EVAL_VIEWS), "--spp", str(EVAL_SPP), "--seed", str(EVAL_SEED), "--metrics", ",".join(METRICS),
           "--quiet"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["(no output)"]
        raise RuntimeError(f"camo evaluate {out.name} failed: {tail[0]}")
    table = pd.read_csv(out / "metrics.csv")
    crop = table[table["region"] == "crop"]
    names = {Path(r["run"]).name: r for r in rows}
    for run, group in crop.groupby("run"):
        row = names[str(run)]
        for m in METRICS:
            row[m] = float(group[m].mean())
        row["eval_views"] = int(len(group))


def order(variants: list[str], index: int) -> list[str]:
    """The variants' running order for the ``index``-th seed: as given for even indices, reversed for odd ones.

    >>> order(["before", "after"], 0), order(["before", "after"], 1)
    (['before', 'after'], ['after', 'before'])
    """
    return list(variants) if index % 2 == 0 else list(reversed(variants))


# ------------------------------------------------------------------------------------------------------------------
# the table

def mean_sd(xs: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (``ddof = 1``; nan for fewer than two values).

    >>> mean_sd([1.0, 2.0, 3.0])
    (2.0, 1.0)
    """
    a = np.asarray([x for x in xs if math.isfinite(x)], float)
    if a.size == 0:
        return float("nan"), float("nan")
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else float("nan")


def paired(rows: list[dict[str, Any]], scene: str, metric: str, a: str, b: str) -> list[float]:
    """``b - a`` of ``metric`` on ``scene`` for every seed both variants ran."""
    by = {(r["variant"], r["seed"]): r.get(metric, float("nan")) for r in rows if r["scene"] == scene}
    return [by[(b, s)] - by[(a, s)] for (v, s) in sorted(by) if v == a and (b, s) in by]


def verdict(diffs: dict[str, list[float]]) -> str:
    """``worse`` / ``better`` / ``same`` from the paired differences of each metric (module doc).

    >>> verdict({"psnr": [-0.3, -0.2, -0.25], "lpips": [0.0, 0.001, -0.001]})
    'worse'
    >>> verdict({"psnr": [0.1, -0.2, 0.05], "lpips": [0.001, -0.002, 0.0]})
    'same'
    """
    worse = better = False
    for metric, d in diffs.items():
        m, sd = mean_sd(d)
        if not math.isfinite(m) or len(d) < 2:
            continue
        margin = 2.0 * sd / math.sqrt(len(d))
        signed = SENSE[metric] * m
        worse |= signed < -margin
        better |= signed > margin
    return "worse" if worse else "better" if better else "same"


def table(rows: list[dict[str, Any]], variants: list[str]) -> str:
    """Per scene: each variant's crop PSNR and LPIPS (mean ± sd over seeds), iterations and seconds, then the paired
    difference of every other variant from the first, with its verdict."""
    def pm(x: tuple[float, float], d: int) -> str:
        m, s = x
        if not math.isfinite(m):
            return "n/a"
        return f"{m:.{d}f} ± {s:.{d}f}" if math.isfinite(s) else f"{m:.{d}f}"

    base = variants[0]
    head = ("| scene | variant | seeds | crop PSNR dB | crop LPIPS | Stage 1 + 2 iterations | wall s | CPU s |\n"
            "|---|---|---:|---:|---:|---:|---:|---:|\n")
    lines = []
    diff_lines = []
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    for scene in scenes:
        for v in variants:
            rs = [r for r in rows if r["scene"] == scene and r["variant"] == v]
            if not rs:
                continue
            its1 = mean_sd([r["stage1_iterations"] for r in rs])[0]
            its2 = mean_sd([r["stage2_iterations"] for r in rs])[0]
            lines.append(f"| {scene} | {v} | {len(rs)} | {pm(mean_sd([r.get('psnr', math.nan) for r in rs]), 2)} | "
                         f"{pm(mean_sd([r.get('lpips', math.nan) for r in rs]), 4)} | {its1:.1f} + {its2:.1f} | "
                         f"{mean_sd([r['wall_seconds'] for r in rs])[0]:.0f} | "
                         f"{mean_sd([r['cpu_seconds'] for r in rs])[0]:.0f} |")
        for v in variants[1:]:
            diffs = {m: paired(rows, scene, m, base, v) for m in METRICS}
            if not diffs["psnr"]:
                continue
            diff_lines.append(f"| {scene} | {v} - {base} | {len(diffs['psnr'])} | {pm(mean_sd(diffs['psnr']), 2)} | "
                              f"{pm(mean_sd(diffs['lpips']), 4)} | "
                              f"{sum(SENSE['psnr'] * x > 0 for x in diffs['psnr'])} of {len(diffs['psnr'])} | "
                              f"**{verdict(diffs)}** |")
    diff_head = ("| scene | difference (same seed) | seeds | Δ crop PSNR dB | Δ crop LPIPS | seeds with higher PSNR "
                 "| verdict |\n|---|---|---:|---:|---:|---:|---|\n")
    return head + "\n".join(lines) + "\n\n" + diff_head + "\n".join(diff_lines) + "\n"


def _made(meta: dict[str, Any]) -> str:
    """How one invocation ran: its seconds, processes at a time and load average."""
    return (f"{meta['seconds']:.0f} s in all ({meta.get('jobs', 1)} at a time), load average "
            f"{meta['load_start']:.1f} at the start and {meta['load_end']:.1f} at the end")


def report(rows: list[dict[str, Any]], variants: list[str], metas: list[dict[str, Any]], write: str | None) -> int:
    """Print (and with ``write``, regenerate the block of) the table; ``metas``: one per invocation whose rows
    these are (several when ``--rows`` merges runs made at different times, each named by its scenes)."""
    budget = ", ".join(sorted({f"{r['budget']:g} s" for r in rows}))
    text = table(rows, variants)
    made = (_made(metas[0]) if len(metas) == 1 else
            "; ".join(f"{', '.join(m['scenes'])}: {_made(m)}" for m in metas))
    text += (f"\n{len(rows)} runs of `--time-budget {budget}` (CPU seconds of one LLVM thread), {SIZES['views']} "
             f"views at {SIZES['resolution']} px; "
             f"scored on {EVAL_VIEWS} jittered views at {EVAL_SPP} spp (evaluation seed {EVAL_SEED}); "
             f"{made}.\n")
    print(text)
    if write:
        HC.write_block(Path(write), text, BLOCK)
    return 0


def merged_rows(paths: list[str], variants: list[str]) -> tuple[list[dict[str, Any]], list[str], list[dict]]:
    """The rows, variants and per-file metas (each with the ``scenes`` it holds) of the ``--json`` files at
    ``paths``; raises SystemExit when two files hold the same scene, variant and seed or differ in variants."""
    rows: list[dict[str, Any]] = []
    metas: list[dict[str, Any]] = []
    seen: dict[tuple, str] = {}
    got_variants = None
    for p in paths:
        saved = json.loads(Path(p).read_text())
        vs = saved.get("variants", variants)
        if got_variants is not None and vs != got_variants:
            raise SystemExit(f"error: {p} compares {', '.join(vs)}, the others {', '.join(got_variants)}")
        got_variants = vs
        for r in saved["rows"]:
            key = (r["scene"], r["variant"], r["seed"])
            if key in seen:
                raise SystemExit(f"error: {p} and {seen[key]} both hold {key[0]} {key[1]} seed {key[2]}")
            seen[key] = p
        rows += saved["rows"]
        metas.append({**saved["meta"], "scenes": list(dict.fromkeys(r["scene"] for r in saved["rows"]))})
    order = {s: i for i, s in enumerate(SCENES)}
    rows.sort(key=lambda r: (order.get(r["scene"], len(order)), r["seed"], got_variants.index(r["variant"])))
    return rows, got_variants, metas


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma list of built-in scenes (default: all six)")
    ap.add_argument("--variants", default="before,after",
                    help=f"comma list of {', '.join(HC.VARIANTS)}; the first is the reference (default before,after)")
    ap.add_argument("--seeds", default=",".join(map(str, DEFAULT_SEEDS)),
                    help="comma list of run seeds (default 0,1,2)")
    ap.add_argument("--budget", type=float, default=DEFAULT_BUDGET,
                    help=f"--time-budget of every run, seconds (default {DEFAULT_BUDGET:g})")
    ap.add_argument("--jobs", type=int, default=1,
                    help="processes at a time (default 1; the budget is CPU time, so their number does not matter)")
    ap.add_argument("--work", default=None, help="keep the run and evaluation folders here (default: temporary)")
    ap.add_argument("--json", default=None, help="also write every run's row to this JSON file")
    ap.add_argument("--rows", nargs="+", default=None, metavar="JSON",
                    help="no runs: the table of the rows earlier --json files wrote (several are merged; a scene "
                         "and seed in two of them is an error)")
    ap.add_argument("--write", nargs="?", const=str(DOC), default=None,
                    help=f"write the table into this Markdown file's generated block (default {DOC.relative_to(ROOT)})")
    args = ap.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    bad = [v for v in variants if v not in HC.VARIANTS]
    if bad or len(variants) < 2:
        ap.error(f"--variants: give two or more of {', '.join(HC.VARIANTS)}" +
                 (f" (unknown: {', '.join(bad)})" if bad else ""))
    scenes = [s for s in args.scenes.split(",") if s]
    unknown = [s for s in scenes if s not in SCENES]
    if unknown:
        ap.error(f"--scenes: unknown scene(s) {', '.join(unknown)}; choose from {', '.join(SCENES)}")
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s]
    except ValueError:
        ap.error(f"--seeds: a comma list of integers, got {args.seeds!r}")
    if not seeds or args.budget <= 0 or args.jobs < 1:
        ap.error("--seeds must name at least one seed, --budget must be > 0 and --jobs >= 1")
    if args.rows:
        return report(*merged_rows(args.rows, variants), args.write)
    say = lambda s: print(s, flush=True)  # noqa: E731
    meta = {"load_start": os.getloadavg()[0], "jobs": args.jobs}
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []

    def pmap(fn, items) -> list:
        with ThreadPoolExecutor(max_workers=args.jobs) as pool:  # threads only wait on child processes
            return list(pool.map(lambda item: fn(*item), items))

    def pair(scene: str, i: int, seed: int) -> list[dict[str, Any]]:
        for v in variants:  # unscored: the kernels of this seed and variant are compiled before any measured run
            optimise(scene, v, seed, WARMUP_BUDGET, work / "warmup" / f"{scene}_{v}_s{seed}",
                     lambda t: say(f"{scene}: warm-up {t.strip()}"))
        return [optimise(scene, v, seed, args.budget, work / f"{scene}_{v}_s{seed}",
                         lambda t: say(f"{scene}: {t.strip()}")) for v in order(variants, i)]

    def evaluate(scene: str) -> None:
        scene_rows = [r for r in rows if r["scene"] == scene]
        score(scene_rows, work / f"eval_{scene}")
        for r in sorted(scene_rows, key=lambda r: (r["seed"], r["variant"])):
            say(f"{scene}: {r['variant']:>8} seed {r['seed']}: crop PSNR {r['psnr']:.2f} dB, LPIPS {r['lpips']:.4f}")

    with tempfile.TemporaryDirectory(prefix="equal_seconds_") as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        taken = [s for s in scenes if any(work.glob(f"{s}_*_s*"))]
        if taken:
            raise SystemExit(f"error: {work} already holds runs of {', '.join(taken)}; give a new --work folder")
        # the measured runs: one task per scene and seed, its warm-ups and then its variants back to back
        for got in pmap(pair, [(scene, i, seed) for i, seed in enumerate(seeds) for scene in scenes]):
            rows += got
        # scoring: one camo evaluate per scene
        pmap(evaluate, [(scene,) for scene in scenes])
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "variants": variants, "meta": {
            **meta, "seconds": time.perf_counter() - t0, "load_end": os.getloadavg()[0]}}, indent=1, default=float))
    rows.sort(key=lambda r: (scenes.index(r["scene"]), r["seed"], variants.index(r["variant"])))
    meta.update(seconds=time.perf_counter() - t0, load_end=os.getloadavg()[0])
    return report(rows, variants, [meta], args.write)


if __name__ == "__main__":
    sys.exit(main())
