"""A grid run at scale, interrupted once and resumed, on the local pool and on a local Ray; then the notebooks.

For each executor this script

1. starts ``camo grid run GRID --out OUT/<executor> --executor <executor> --workers N`` in its own process group
   (as a terminal would), waits until ``--interrupt-after`` cells are finished *and* an unfinished cell has
   written an optimisation checkpoint (so the interrupt lands mid-optimisation), and sends SIGINT to the group
   (Ctrl-C): the run must exit with status 130 and leave the unfinished cells resumable;
2. runs the same command again: it must exit 0 with every cell done, and must not redo a cell that was finished
   before the interrupt (each such cell has exactly one ``start`` in its ``attempts.jsonl`` and an unchanged
   ``DONE``);
3. executes ``notebooks/table2_metrics.ipynb`` on ``OUT/<executor>/metrics.parquet`` (nbclient, a kernel of this
   interpreter) and writes the executed copy next to it (``table2_metrics.executed.ipynb``), checking that every
   (scene, method) of the grid appears in the notebook's per-scene table.

It prints one line per phase (seconds, cells done, interrupted cells that were resumed from a checkpoint) and a
final table. Exit status 0 only when every check above held.

    python bench/bench_grid_resume.py [--grid grids/smoke.toml] [--out bench_out/grid_resume]
                                      [--executors local,ray] [--workers 2] [--interrupt-after 6]

On the 2-core CI-sized machine the default (27 cells, grids/smoke.toml) takes a few minutes per executor.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from camo_base.tables import read_parquet  # noqa: E402


def done_cells(out: Path) -> list[Path]:
    return sorted(p.parent for p in out.glob("cells/*/DONE"))


def checkpointed_unfinished(out: Path) -> list[Path]:
    """Cells that are not done but whose optimisation has written a checkpoint (partial, mid-run)."""
    return [p for p in (out / "cells").glob("*") if not (p / "DONE").exists() and any(p.glob("run/*/checkpoint.npz"))]


def start_modes(cell: Path) -> list[str]:
    """The mode of every ``start`` event in a cell's attempts.jsonl (fresh / resume / restart / evaluate)."""
    f = cell / "attempts.jsonl"
    if not f.is_file():
        return []
    events = [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
    return [e.get("mode", "?") for e in events if e.get("event") == "start"]


def grid_cmd(grid: Path, out: Path, executor: str, workers: int) -> list[str]:
    return [sys.executable, "-m", "camo.cli", "grid", "run", str(grid), "--out", str(out), "--quiet",
            "--executor", executor, "--workers", str(workers)]


def interrupt_then_resume(grid: Path, out: Path, executor: str, workers: int, after: int, limit: float) -> dict:
    """Phase 1 (SIGINT after ``after`` cells) and phase 2 (resume); returns what was measured, raises on a failed check."""
    if out.exists():
        shutil.rmtree(out)
    cmd = grid_cmd(grid, out, executor, workers)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    while len(done_cells(out)) < after or not checkpointed_unfinished(out):
        if proc.poll() is not None:
            raise RuntimeError(f"{executor}: the run ended (status {proc.returncode}) before {after} cells were done:\n"
                               + proc.stdout.read().decode(errors="replace")[-2000:])
        if time.perf_counter() - t0 > limit:
            os.killpg(proc.pid, signal.SIGKILL)
            raise RuntimeError(f"{executor}: no point with {after} cells done and one mid-run after {limit:.0f} s")
        time.sleep(0.5)
    before = {c.name: (c / "DONE").stat().st_mtime_ns for c in done_cells(out)}
    os.killpg(proc.pid, signal.SIGINT)
    rc = proc.wait(timeout=120)
    text = proc.stdout.read().decode(errors="replace")
    t_first = time.perf_counter() - t0
    if rc != 130 or "camo: interrupted" not in text:
        raise RuntimeError(f"{executor}: after SIGINT expected status 130 and 'camo: interrupted', got {rc}:\n{text[-2000:]}")
    at_interrupt = {c.name for c in done_cells(out)}
    started = {p.parent.name for p in out.glob("cells/*/attempts.jsonl")} - at_interrupt

    t1 = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=limit)
    t_resume = time.perf_counter() - t1
    if res.returncode != 0:
        raise RuntimeError(f"{executor}: resume exited {res.returncode}:\n{res.stdout.decode(errors='replace')[-2000:]}")
    cells = json.loads((out / "grid.json").read_text())["cells"]
    final = {c.name for c in done_cells(out)}
    if final != {c["key"] for c in cells}:
        raise RuntimeError(f"{executor}: {len(cells) - len(final)} cell(s) not done after the resume")
    redone = [k for k, m in before.items() if (out / "cells" / k / "DONE").stat().st_mtime_ns != m or len(start_modes(out / "cells" / k)) != 1]
    if redone:
        raise RuntimeError(f"{executor}: cells finished before the interrupt were run again: {redone}")
    # an in-flight cell's second start says how it went on: "resume" (from its checkpoint) or "evaluate" (its
    # optimisation had finished) rather than "fresh"/"restart"
    partial = {c for c in started if any(m in ("resume", "evaluate") for m in start_modes(out / "cells" / c)[1:])}
    if not partial:
        raise RuntimeError(f"{executor}: no cell interrupted mid-run was resumed from its checkpoint")
    return {"executor": executor, "cells": len(cells), "done_at_interrupt": len(at_interrupt),
            "interrupted_in_flight": len(started), "resumed_from_checkpoint": len(partial),
            "seconds_to_interrupt": t_first, "seconds_resume": t_resume}


def execute_table2(out: Path) -> dict:
    """Run notebooks/table2_metrics.ipynb on OUT/metrics.parquet; check every (scene, method) shows up."""
    import nbclient
    import nbformat
    import pandas as pd

    from camo_base import atomic

    share = Path(tempfile.mkdtemp(prefix="camo_kernel_"))
    spec = share / "kernels" / "camo-bench"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "camo bench kernel", "language": "python"}))
    env = {"JUPYTER_PATH": str(share), "CAMO_METRICS": str(out / "metrics.parquet"),
           "MPLBACKEND": "module://matplotlib_inline.backend_inline"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    t0 = time.perf_counter()
    try:
        nb = nbformat.read(ROOT / "notebooks" / "table2_metrics.ipynb", as_version=4)
        nbclient.NotebookClient(nb, timeout=600, kernel_name="camo-bench",
                                resources={"metadata": {"path": str(ROOT / "notebooks")}}).execute()
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        shutil.rmtree(share, ignore_errors=True)
    seconds = time.perf_counter() - t0
    with atomic.atomic_path(out / "table2_metrics.executed.ipynb") as tmp:
        nbformat.write(nb, str(tmp))
    shown = "\n".join(
        (o.get("text", "") if o.get("output_type") == "stream" else
         "".join(o.get("data", {}).get("text/markdown", "") or o.get("data", {}).get("text/html", "")))
        for c in nb.cells for o in c.get("outputs", []))
    m = read_parquet(out / "metrics.parquet")
    missing = sorted(s for s in set(m["scene"].str.split(":").str[0]) if s not in shown)
    images = sum(1 for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {}))
    if missing or images == 0 or "Table II" not in shown:
        raise RuntimeError(f"notebook on {out}: missing scenes {missing}, {images} plot(s)")
    return {"notebook_seconds": seconds, "notebook_plots": images, "metrics_rows": len(m),
            "runs": int(m["run"].nunique())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", type=Path, default=ROOT / "grids" / "smoke.toml")
    ap.add_argument("--out", type=Path, default=ROOT / "bench_out" / "grid_resume")
    ap.add_argument("--executors", default="local,ray")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--interrupt-after", type=int, default=6, help="finished cells before the SIGINT")
    ap.add_argument("--limit", type=float, default=3600, help="seconds allowed per phase")
    a = ap.parse_args(argv)
    rows = []
    for ex in [e.strip() for e in a.executors.split(",") if e.strip()]:
        out = a.out / ex
        r = interrupt_then_resume(a.grid.resolve(), out.resolve(), ex, a.workers, a.interrupt_after, a.limit)
        print(f"{ex}: {r['done_at_interrupt']}/{r['cells']} cells done at SIGINT after {r['seconds_to_interrupt']:.1f} s "
              f"({r['interrupted_in_flight']} in flight, {r['resumed_from_checkpoint']} with a checkpoint); "
              f"resume finished the rest in {r['seconds_resume']:.1f} s, no finished cell redone", flush=True)
        r.update(execute_table2(out.resolve()))
        print(f"{ex}: table2_metrics.ipynb ran in {r['notebook_seconds']:.1f} s on {r['runs']} runs "
              f"({r['metrics_rows']} metric rows, {r['notebook_plots']} plots) -> {out / 'table2_metrics.executed.ipynb'}",
              flush=True)
        rows.append(r)
    print("\n| executor | cells | done at SIGINT | in flight | resumed from checkpoint | s to SIGINT | s resume | notebook s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['executor']} | {r['cells']} | {r['done_at_interrupt']} | {r['interrupted_in_flight']} | "
              f"{r['resumed_from_checkpoint']} | {r['seconds_to_interrupt']:.1f} | {r['seconds_resume']:.1f} | "
              f"{r['notebook_seconds']:.1f} |")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except RuntimeError as exc:
        print(f"bench_grid_resume: {exc}", file=sys.stderr)
        sys.exit(1)
