"""``camo grid run`` and ``camo grid status``: run the cells of a grid, merge their metrics, write the report.

Output folder::

    DIR/grid.toml, DIR/grid.json   the grid file as given and its resolved cells (keys, run specs)
    DIR/cells/<key>/               one folder per cell (see camo.grid.cell)
    DIR/metrics.parquet, .csv      every finished cell's evaluation rows (evaluation.evaluate.COLUMNS) plus
                                   cell (key), run_seed (the optimisation seed) and label (the Table II row)
    DIR/report/                    report.md, report.html, grids/ (evaluation.report.write_report over the
                                   finished cells' evaluation folders): Table II with its ablation rows
    DIR/.lock                      held by the running `camo grid run` (a second one on DIR is refused)
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import Any

from camo_base.errors import CamoError
from camo.grid.cell import CELL_JSON, cell_state
from camo.grid.executors import Job, LocalExecutor, RayExecutor
from camo.grid.spec import Cell, Grid, load_grid
from camo_base.tables import read_parquet, write_parquet

GRID_JSON = "grid.json"
LOCK = ".lock"


def cell_dir(out: Path, cell: Cell) -> Path:
    return Path(out) / "cells" / cell.key


def states(grid_cells: list[Cell], out: Path) -> dict[str, tuple[str, str]]:
    return {c.key: cell_state(c, cell_dir(out, c)) for c in grid_cells}


def _counts(st: dict[str, tuple[str, str]]) -> dict[str, int]:
    out = {"done": 0, "failed": 0, "running": 0, "partial": 0, "pending": 0}
    for s, _ in st.values():
        out[s] += 1
    return out


def _summary(c: dict[str, int]) -> str:
    return ", ".join(f"{c[k]} {k}" for k in ("done", "failed", "running", "partial", "pending") if k != "running" or c[k])


def _check_out(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise CamoError(f"--out {out} exists and is not a folder")
    if out.is_dir() and any(p.name != LOCK for p in out.iterdir()) and not (out / GRID_JSON).is_file() \
            and not (out / "cells").is_dir():
        raise CamoError(f"--out {out} is a non-empty folder that is not a grid output; use a new or empty folder")


@contextlib.contextmanager
def _driver_lock(out: Path):
    """One `camo grid run` per output folder at a time (an advisory lock on DIR/.lock, released on exit)."""
    import fcntl

    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            other = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            raise CamoError(f"{out} is in use by another `camo grid run` ({other}); wait for it or stop it") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}".encode(), 0)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def _prepare_out(out: Path, grid: Grid) -> None:
    from camo_base import atomic

    (out / "cells").mkdir(parents=True, exist_ok=True)
    atomic.write_text(out / "grid.toml", grid.source)
    atomic.write_json(out / GRID_JSON, grid.to_dict())
    for c in grid.cells:
        cd = cell_dir(out, c)
        try:
            same = json.loads((cd / CELL_JSON).read_text(encoding="utf-8")) == json.loads(json.dumps(c.to_dict()))
        except (OSError, ValueError):
            same = False
        if not same:  # new, or written by an older camo (command lines instead of a run spec): same key, same work
            atomic.write_json(cd / CELL_JSON, c.to_dict())


def print_cells(cells: list[Cell], st: dict[str, tuple[str, str]], file=None) -> None:
    file = file or sys.stdout
    width = max([len(c.name) for c in cells] + [4])
    print(f"{'state':8} {'key':16} {'cell':{width}} detail", file=file)
    for c in cells:
        s, detail = st[c.key]
        print(f"{s:8} {c.key:16} {c.name:{width}} {detail}", file=file)


def run_grid(grid_path: str | Path, out: str | Path, executor: str = "local", workers: int = 1,
             ray_address: str | None = None, skip_failed: bool = False, dry_run: bool = False,
             progress: bool = True) -> int:
    """Run every unfinished cell of the grid file into ``out``; 0 when all cells are done, 1 otherwise."""
    if workers < 1:
        raise CamoError(f"--workers must be >= 1, got {workers}")
    if executor not in ("local", "ray"):
        raise CamoError(f"--executor must be local or ray, got {executor!r}")
    grid = load_grid(grid_path)
    out = Path(out)
    say = (lambda s: print(s, file=sys.stderr)) if progress else (lambda s: None)
    for note in grid.notes:
        print(f"note: {grid.path}: {note}", file=sys.stderr)
    if dry_run:
        st = states(grid.cells, out) if out.is_dir() else {c.key: ("pending", "") for c in grid.cells}
        print(f"grid {grid.name}: {len(grid.cells)} cell(s): {_summary(_counts(st))}")
        print_cells(grid.cells, st)
        return 0
    if executor == "ray":
        from camo.grid.executors import import_ray

        import_ray()  # the missing-extra error comes before anything is written
    from camo.grid.spec import check_metrics_available

    check_metrics_available(grid)  # e.g. lpips without its installed weights: one line, before any cell runs
    _check_out(out)
    with _driver_lock(out):
        _prepare_out(out, grid)
        st = states(grid.cells, out)
        todo = [c for c in grid.cells if st[c.key][0] in ("pending", "partial") or
                (st[c.key][0] == "failed" and not skip_failed)]  # "running": a worker of another driver has it
        counts = _counts(st)
        say(f"grid {grid.name}: {len(grid.cells)} cell(s): {_summary(counts)}; {len(todo)} to run")
        if todo:
            ex = RayExecutor(workers, ray_address) if executor == "ray" else LocalExecutor(workers)
            try:
                cores = ex.start()
                active = min(workers, len(todo))
                threads = max(1, cores // active)
                say(f"executor {ex.name}: {active} worker(s) x {threads} render thread(s) ({cores} cores)")
                _execute(ex, grid, out, todo, threads, progress, counts["done"])
            finally:
                ex.close()
        st = states(grid.cells, out)
        counts = _counts(st)
        merged = merge_results(grid, out, st)
    if merged is not None:
        say(f"wrote {out / 'metrics.parquet'} ({merged} rows) and {out / 'report' / 'report.md'}")
    failed = [c for c in grid.cells if st[c.key][0] == "failed"]
    for c in failed:
        say(f"failed: {c.name} ({c.key}): {st[c.key][1]}")
    say(f"grid {grid.name}: {_summary(counts)}" + (f" (see camo grid status {out})" if failed else ""))
    return 0 if counts["done"] == len(grid.cells) else 1


def _execute(ex, grid: Grid, out: Path, todo: list[Cell], threads: int, progress: bool, done_before: int) -> None:
    from tqdm import tqdm

    bar = tqdm(total=len(grid.cells), initial=done_before, desc="cells", unit="cell", disable=not progress,
               file=sys.stderr, dynamic_ncols=True)
    tally = {"done": 0, "failed": 0}

    def on_result(job: Job, res: dict[str, Any]) -> None:
        status = res.get("status", "failed")
        tally[status] = tally.get(status, 0) + 1
        if status == "done":
            bar.update(1)
            line = f"done    {job.cell.name} ({job.cell.key}) in {float(res.get('seconds', 0)):.1f} s"
        elif status == "busy":
            line = f"busy    {job.cell.name} ({job.cell.key}): {res.get('error', '')}; left alone"
        else:
            line = f"FAILED  {job.cell.name} ({job.cell.key}): {res.get('error', '')}"
        bar.set_postfix(failed=tally.get("failed", 0))
        if progress:
            bar.write(line, file=sys.stderr)

    t0 = time.perf_counter()
    try:
        ex.run([Job(c, cell_dir(out, c)) for c in todo], threads, on_result)
    finally:
        bar.close()
    if progress:
        print(f"ran {sum(tally.values())} cell(s) in {time.perf_counter() - t0:.1f} s", file=sys.stderr)


def merge_results(grid: Grid, out: Path, st: dict[str, tuple[str, str]] | None = None) -> int | None:
    """Merge the finished cells' metrics into DIR/metrics.parquet/.csv and write DIR/report; rows or None."""
    import pandas as pd

    from evaluation.report import method_label, write_report

    from camo_base import atomic

    st = st or states(grid.cells, out)
    frames, eval_dirs = [], []
    for c in grid.cells:
        if st[c.key][0] != "done":
            continue
        ed = c.eval_dir(cell_dir(out, c))
        p = ed / "metrics.parquet"
        if not p.is_file():
            print(f"warning: finished cell {c.name} ({c.key}) has no {p}; left out of the merged table",
                  file=sys.stderr)
            continue
        df = read_parquet(p)
        df["cell"] = c.key
        df["run_seed"] = c.seed
        frames.append(df)
        eval_dirs.append(ed)
    if not frames:
        return None
    table = pd.concat(frames, ignore_index=True, sort=False)
    table["label"] = [method_label(m, a) for m, a in zip(table["method"], table["ablation"])]
    with atomic.atomic_path(out / "metrics.parquet") as tmp:
        write_parquet(table, tmp)
    with atomic.atomic_path(out / "metrics.csv") as tmp:
        table.to_csv(tmp, index=False)
    write_report(eval_dirs, out / "report")
    return len(table)


def load_out(out: str | Path) -> tuple[dict[str, Any], list[Cell]]:
    out = Path(out)
    p = out / GRID_JSON
    if not p.is_file():
        raise CamoError(f"{out}: no {GRID_JSON} (is this an output folder of `camo grid run`?)")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
        cells = [Cell.from_dict(d) for d in doc["cells"]]
    except CamoError as exc:
        raise CamoError(f"{p}: {exc}") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise CamoError(f"{p}: unreadable ({type(exc).__name__})") from None
    return doc, cells


def status(out: str | Path, as_json: bool = False) -> int:
    doc, cells = load_out(out)
    st = states(cells, Path(out))
    counts = _counts(st)
    if as_json:
        print(json.dumps({"name": doc.get("name"), "counts": counts,
                          "cells": [{"key": c.key, "name": c.name, "scene": c.scene_label, "method": c.method,
                                     "ablation": c.ablation, "seed": c.seed, "state": st[c.key][0],
                                     "detail": st[c.key][1]} for c in cells]}, indent=1))
        return 0
    print(f"grid {doc.get('name')} ({out}): {len(cells)} cell(s): {_summary(counts)}")
    print_cells(cells, st)
    return 0
