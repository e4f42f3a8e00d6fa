"""One grid cell: its run spec's optimisation, then ``camo evaluate``, into ``DIR/cells/<key>/``, in a worker process.

Cell folder::

    cell.json        the cell's resolved config, with its run spec (written before it first runs)
    attempts.jsonl   one JSON line per event: start (with mode fresh / resume / restart / evaluate), optimized,
                     done, failed -- the number of "start" lines is the number of times the cell was run
    log.txt          everything the cell's commands printed
    run/<name>/      the run directory (`camo optimize`); <name> is the `run` column of the metrics
    OPTIMIZED        written when the optimisation finished (a rerun then only evaluates)
    eval/<name>/     the evaluation directory (`camo evaluate`)
    DONE             JSON: the config, timings, host; written last -- a cell with DONE is never run again
    ERROR, error.log the one-line error and its traceback when the cell failed (removed when it is retried)
    .lock            held by the worker running the cell (`camo grid status` shows it as running)

A partial cell (started, no DONE) is resumed when its run directory has a checkpoint (method ``ours``; baselines
have none), otherwise restarted over its files. The optimisation runs the cell's run spec as stored
(:func:`optimizer.optimise.run.run`, as ``camo optimize`` does after filling one); the evaluation calls
:func:`evaluation.evaluate.evaluate` with the cell's evaluation settings, as ``camo evaluate`` does with its flags'.

This module is imported by spawned worker processes: keep its imports light.
"""

from __future__ import annotations

import datetime
import json
import os
import socket
import time
import traceback
from pathlib import Path
from typing import Any

from camo_base.errors import CamoError

CELL_JSON = "cell.json"
ATTEMPTS = "attempts.jsonl"
LOG = "log.txt"
OPTIMIZED = "OPTIMIZED"
DONE = "DONE"
ERROR = "ERROR"
ERROR_LOG = "error.log"
CELL_LOCK = ".lock"

#: Test hook: a cell whose name contains this string kills its worker process (simulates a crash).
CRASH_ENV = "CAMO_GRID_TEST_CRASH"


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _append(path: Path, record: dict[str, Any]) -> None:
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(record, sort_keys=True) + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_attempts(cell_dir: Path) -> list[dict[str, Any]]:
    p = Path(cell_dir) / ATTEMPTS
    if not p.is_file():
        return []
    out = []
    for line in p.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:  # a line cut by a kill: ignore it
            continue
    return out


def read_done(cell_dir: Path, key: str) -> dict[str, Any] | None:
    """The DONE record of a finished cell with this key, else None."""
    p = Path(cell_dir) / DONE
    if not p.is_file():
        return None
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (ValueError, OSError):
        return None
    if not isinstance(d, dict) or d.get("key") != key:
        return None
    return d


def checkpoint_progress(run_dir: Path) -> str | None:
    """``"stage S, iteration N"`` of the checkpoint a resume of a run directory would continue (its unfinished
    staging folder's, else its own), else None."""
    from optimizer.assets.rundir import CHECKPOINT, resumable

    folder = resumable(run_dir)
    if folder is None:
        return None
    p = folder / CHECKPOINT
    try:
        import numpy as np

        with np.load(p, allow_pickle=False) as z:
            it = int(z["iteration"]) if "iteration" in z.files else None
            st = int(z["stage"]) if "stage" in z.files else 1
    except Exception:  # noqa: BLE001 - a status line must not fail on a damaged checkpoint
        return "checkpoint unreadable"
    return f"checkpoint at stage {st}" + (f", iteration {it}" if it is not None else "")


class _CellLock:
    """An advisory lock on ``cell_dir/.lock`` held while a worker runs the cell, so that one cell never runs
    twice at once (e.g. a worker orphaned by a killed driver and a new driver). File systems without locks
    (some network mounts) run unlocked."""

    def __init__(self, cell_dir: Path):
        self.path = Path(cell_dir) / CELL_LOCK
        self.fd: int | None = None

    def acquire(self, shared: bool = False) -> str | None:
        """None when acquired (or locking is unsupported); else who holds it."""
        import fcntl

        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(self.fd, 128, 0).decode(errors="replace").strip() or "another process"
            self.release()
            return holder
        except OSError:  # no locking here
            return None
        if not shared:
            os.ftruncate(self.fd, 0)
            os.pwrite(self.fd, f"pid {os.getpid()} on {socket.gethostname()}".encode(), 0)
        return None

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def cell_state(cell, cell_dir: Path) -> tuple[str, str]:
    """``(state, detail)``: state is done, failed, running (a worker holds the cell's lock), partial (started,
    not finished) or pending (never started)."""
    cell_dir = Path(cell_dir)
    done = read_done(cell_dir, cell.key)
    if done is not None:
        secs = float(done.get("seconds_optimize", 0)) + float(done.get("seconds_evaluate", 0))
        return "done", f"{secs:.1f} s, finished {done.get('finished_at', '?')}"
    if (cell_dir / CELL_LOCK).is_file():
        probe = _CellLock(cell_dir)
        holder = probe.acquire(shared=True)
        probe.release()
        if holder is not None:
            return "running", holder
    if (cell_dir / ERROR).is_file():
        text = (cell_dir / ERROR).read_text(encoding="utf-8", errors="replace").strip().splitlines()
        return "failed", text[0] if text else "failed"
    starts = [a for a in read_attempts(cell_dir) if a.get("event") == "start"]
    if not starts:
        return "pending", ""
    if (cell_dir / OPTIMIZED).is_file():
        return "partial", "optimised, not evaluated"
    prog = checkpoint_progress(cell.run_dir(cell_dir))
    return "partial", prog or "started, no checkpoint (will restart)"


def _one_line(text: str) -> str:
    return " ".join(str(text).split()) or "error"


def evaluate_cell(cell, cell_dir: Path, threads: int | None) -> None:
    """Evaluate the cell's run directory with its evaluation settings (:meth:`camo.grid.spec.Cell.
    evaluation_settings`: the grid's ``[evaluate]`` options), as ``camo evaluate`` does; CamoError for bad input."""
    from evaluation.evaluate import evaluate
    from evaluation.inputs import InputSpec

    evaluate([InputSpec("run", str(cell.run_dir(cell_dir)))], str(cell.eval_dir(cell_dir)),
             cell.evaluation_settings(threads))


def optimize_cell(cell, cell_dir: Path, threads: int | None, mode: str = "fresh") -> Path:
    """Run the cell's run spec into its run directory; ``mode``: fresh, resume (from its checkpoint) or restart
    (over its files). CamoError for a bad spec or a failed resume."""
    from optimizer.optimise.run import run

    run_dir = cell.run_dir(cell_dir)
    print(f"$ camo optimize {cell.scene} --out {run_dir} [the run spec of {CELL_JSON}: method {cell.spec.get('method')}, "
          f"seed {cell.spec.get('seed', 0)}] --threads {threads or 'default'}"
          f"{' --resume' if mode == 'resume' else ' --overwrite' if mode == 'restart' else ''}", flush=True)
    return run(cell.run_spec(), run_dir, resume=mode == "resume", overwrite=mode == "restart", progress=False,
               threads=threads)


def _limit_threads(threads: int | None) -> None:
    if not threads:
        return
    os.environ["CAMO_THREADS"] = str(threads)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    try:
        import torch

        torch.set_num_threads(threads)
    except ImportError:  # pragma: no cover - torch is a dependency
        pass


class _Redirect:
    """Send fd 1 and 2 (and everything printed) to the cell's log.txt; restore on exit."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self):
        import sys

        for s in (sys.stdout, sys.stderr):
            try:
                s.flush()
            except (OSError, ValueError):
                pass
        self.log = open(self.path, "a", encoding="utf-8", buffering=1)
        self.saved = []
        for fd in (1, 2):
            try:
                self.saved.append((fd, os.dup(fd)))
                os.dup2(self.log.fileno(), fd)
            except OSError:
                pass
        return self

    def __exit__(self, *exc):
        import sys

        for s in (sys.stdout, sys.stderr):
            try:
                s.flush()
            except (OSError, ValueError):
                pass
        for fd, saved in self.saved:
            os.dup2(saved, fd)
            os.close(saved)
        self.log.close()
        return False


def run_cell(cell_dict: dict[str, Any], cell_dir: str, threads: int | None) -> dict[str, Any]:
    """Run (or finish) one cell; never raises for a failing cell: returns ``{key, name, status, error,
    seconds}`` with status ``done`` or ``failed`` (and writes DONE / ERROR), or ``busy`` when another process
    holds the cell's lock. KeyboardInterrupt passes through and leaves the cell partial."""
    from camo.grid.spec import Cell

    cell = Cell.from_dict(cell_dict)
    cdir = Path(cell_dir)
    cdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    lock = _CellLock(cdir)
    holder = lock.acquire()
    if holder is not None:  # a worker of another driver runs it: leave it alone
        return {"key": cell.key, "name": cell.name, "status": "busy", "error": f"running elsewhere ({holder})",
                "seconds": 0.0}
    try:
        if read_done(cdir, cell.key) is not None:  # finished meanwhile: nothing to do
            return {"key": cell.key, "name": cell.name, "status": "done", "error": "", "seconds": 0.0}
        with _Redirect(cdir / LOG):
            print(f"==== {_now()} cell {cell.name} ({cell.key}) on {socket.gethostname()} pid {os.getpid()}, "
                  f"{threads or 'default'} thread(s)", flush=True)
            return _run(cell, cdir, threads, t0)
    finally:
        lock.release()


def _run(cell, cdir: Path, threads: int | None, t0: float) -> dict[str, Any]:
    from camo_base import atomic

    from optimizer.assets.rundir import resumable, staging_dir

    run_dir = cell.run_dir(cdir)
    optimized = (cdir / OPTIMIZED).is_file()
    if optimized:
        mode = "evaluate"
    elif resumable(run_dir) is not None and cell.method == "ours":
        mode = "resume"
    elif (run_dir.exists() and any(run_dir.iterdir())) or staging_dir(run_dir).exists():
        mode = "restart"
    else:
        mode = "fresh"
    n = sum(1 for a in read_attempts(cdir) if a.get("event") == "start") + 1
    _append(cdir / ATTEMPTS, {"event": "start", "attempt": n, "mode": mode, "time": _now(), "pid": os.getpid(),
                              "host": socket.gethostname(), "threads": threads})
    for stale in (ERROR, ERROR_LOG):
        (cdir / stale).unlink(missing_ok=True)
    crash = os.environ.get(CRASH_ENV)
    if crash and crash in cell.name:
        print(f"{CRASH_ENV}={crash}: killing this worker", flush=True)
        os._exit(70)
    _limit_threads(threads)
    phase = "optimize"
    seconds_opt = 0.0
    try:
        if not optimized:
            t = time.perf_counter()
            try:
                optimize_cell(cell, cdir, threads, mode)
            except CamoError as exc:
                refused = "resume" in getattr(exc, "names", ()) or "checkpoint" in str(exc)  # (not resumable)
                if mode != "resume" or not refused:
                    raise
                print(f"resume failed ({exc}); restarting the run", flush=True)
                _append(cdir / ATTEMPTS, {"event": "restart", "reason": _one_line(exc), "time": _now()})
                optimize_cell(cell, cdir, threads, "restart")
            seconds_opt = time.perf_counter() - t
            atomic.write_json(cdir / OPTIMIZED, {"key": cell.key, "seconds": seconds_opt, "time": _now()})
            _append(cdir / ATTEMPTS, {"event": "optimized", "seconds": seconds_opt, "time": _now()})
        else:
            seconds_opt = float(json.loads((cdir / OPTIMIZED).read_text()).get("seconds", 0.0))
        phase = "evaluate"
        t = time.perf_counter()
        eval_root = cell.eval_dir(cdir).parent
        if eval_root.exists():  # a partial evaluation: start it again
            import shutil

            shutil.rmtree(eval_root)
        print(f"$ camo {' '.join(cell.evaluate_command(cdir, threads))}", flush=True)
        evaluate_cell(cell, cdir, threads)
        seconds_eval = time.perf_counter() - t
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - every failure of a cell is recorded, never raised
        msg = f"{phase}: {exc if isinstance(exc, CamoError) else f'{type(exc).__name__}: {exc}'}"
        msg = _one_line(msg)
        tb = traceback.format_exc()
        print(tb, flush=True)
        atomic.write_text(cdir / ERROR_LOG, f"{msg}\n\n{tb}")
        atomic.write_text(cdir / ERROR, msg + "\n")
        _append(cdir / ATTEMPTS, {"event": "failed", "error": msg, "time": _now()})
        return {"key": cell.key, "name": cell.name, "status": "failed", "error": msg,
                "seconds": time.perf_counter() - t0}
    record = {"key": cell.key, "name": cell.name, "config": cell.to_dict(), "finished_at": _now(),
              "seconds_optimize": seconds_opt, "seconds_evaluate": seconds_eval, "threads": threads,
              "host": socket.gethostname(), "attempts": n}
    atomic.write_json(cdir / DONE, record)
    _append(cdir / ATTEMPTS, {"event": "done", "time": _now(), "seconds": time.perf_counter() - t0})
    print(f"==== {_now()} cell {cell.name} done", flush=True)
    return {"key": cell.key, "name": cell.name, "status": "done", "error": "", "seconds": time.perf_counter() - t0}


def record_crash(cell, cell_dir: Path, why: str) -> dict[str, Any]:
    """Record a cell whose worker process died (written by the driver: the worker could not)."""
    from camo_base import atomic

    cdir = Path(cell_dir)
    msg = _one_line(f"worker: {why}; see {cdir / LOG}")
    atomic.write_text(cdir / ERROR_LOG, msg + "\n")
    atomic.write_text(cdir / ERROR, msg + "\n")
    _append(cdir / ATTEMPTS, {"event": "failed", "error": msg, "time": _now()})
    return {"key": cell.key, "name": cell.name, "status": "failed", "error": msg, "seconds": 0.0}
