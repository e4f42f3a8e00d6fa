"""Where grid cells run: a local process pool (default) or a Ray cluster.

Both run :func:`camo.grid.cell.run_cell` in a fresh process per cell (Dr.Jit / Mitsuba are not fork-safe
and keep global state): ``ProcessPoolExecutor`` with the *spawn* start method and ``max_tasks_per_child=1``;
Ray tasks with ``max_calls=1``. At most ``workers`` cells run at once, each with ``threads`` render threads.

A worker process that dies (a segfault, the OOM killer) breaks a process pool: every cell in flight then fails
with it. Those cells are re-run one at a time, so a crash is charged to the cell that caused it; a cell whose
process dies twice is recorded as failed. Ctrl-C (KeyboardInterrupt) terminates the workers at once; their cells
stay partial and are resumed by the next ``camo grid run``.
"""

from __future__ import annotations

import dataclasses
import os
from collections import deque
from pathlib import Path
from typing import Any, Callable

from camo_base.errors import CamoError

#: Test hook: the driver raises KeyboardInterrupt after this many cells finished (simulates Ctrl-C).
STOP_AFTER_ENV = "CAMO_GRID_STOP_AFTER"


@dataclasses.dataclass
class Job:
    cell: Any  # camo.grid.spec.Cell
    dir: Path


OnResult = Callable[[Job, dict], None]


def available_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class _StopHook:
    def __init__(self):
        try:
            self.limit = int(os.environ.get(STOP_AFTER_ENV, "0") or 0)
        except ValueError:
            self.limit = 0
        self.count = 0

    def tick(self) -> None:
        self.count += 1
        if self.limit and self.count >= self.limit:
            raise KeyboardInterrupt(f"{STOP_AFTER_ENV}={self.limit}")


# --------------------------------------------------------------------------------------------------------------
# local process pool
# --------------------------------------------------------------------------------------------------------------


class LocalExecutor:
    name = "local"

    def __init__(self, workers: int):
        self.workers = workers

    def start(self) -> int:
        """Cores available to the cells."""
        return available_cores()

    def close(self) -> None:
        pass

    @staticmethod
    def _pool(workers: int):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                   max_tasks_per_child=1)

    @staticmethod
    def _terminate(pool) -> None:
        if pool is None:
            return
        procs = list((getattr(pool, "_processes", None) or {}).values())
        term = getattr(pool, "terminate_workers", None)  # Python >= 3.14
        if term is not None:
            term()
            return
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(timeout=10)
            if p.is_alive():
                p.kill()
                p.join(timeout=5)

    def run(self, jobs: list[Job], threads: int, on_result: OnResult) -> None:
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        from camo.grid.cell import record_crash, run_cell

        queue: deque[Job] = deque(jobs)
        solo: deque[Job] = deque()  # cells in flight when a worker died: re-run one at a time
        crashes: dict[str, int] = {}
        inflight: dict[Any, Job] = {}
        solo_running = False
        stop = _StopHook()
        pool = None
        try:
            while queue or solo or inflight:
                if pool is None:
                    pool = self._pool(self.workers)
                if solo and not inflight:
                    job = solo.popleft()
                    inflight[pool.submit(run_cell, job.cell.to_dict(), str(job.dir), threads)] = job
                    solo_running = True
                while not solo and not solo_running and queue and len(inflight) < self.workers:
                    job = queue.popleft()
                    inflight[pool.submit(run_cell, job.cell.to_dict(), str(job.dir), threads)] = job
                done, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
                died: list[Job] = []
                for fut in done:
                    job = inflight.pop(fut)
                    try:
                        res = fut.result()
                    except BrokenProcessPool:
                        died.append(job)
                        continue
                    except Exception as exc:  # noqa: BLE001 - e.g. the result could not be sent back
                        res = record_crash(job.cell, job.dir, f"{type(exc).__name__}: {exc}")
                    if solo_running:
                        solo_running = False
                    on_result(job, res)
                    stop.tick()
                if died:
                    # a dead worker breaks the pool: every future still in flight fails the same way
                    died += list(inflight.values())
                    inflight.clear()
                    self._terminate(pool)
                    pool = None
                    alone = len(died) == 1
                    solo_running = False
                    for job in died:
                        if alone:
                            crashes[job.cell.key] = crashes.get(job.cell.key, 0) + 1
                        if crashes.get(job.cell.key, 0) >= 2:
                            on_result(job, record_crash(job.cell, job.dir, "the worker process died twice"))
                            stop.tick()
                        else:
                            solo.append(job)
        except BaseException:
            self._terminate(pool)
            pool = None
            raise
        finally:
            if pool is not None:
                pool.shutdown(wait=True)


# --------------------------------------------------------------------------------------------------------------
# Ray
# --------------------------------------------------------------------------------------------------------------


def import_ray():
    """Import Ray; a one-line CamoError with the install hint when it is missing."""
    try:
        import ray
    except ImportError:
        raise CamoError("--executor ray needs Ray: pip install 'camo-toolkit[cluster]' (ray>=2.9)") from None
    return ray


class RayExecutor:
    """Ray tasks (``num_cpus=threads``, ``max_calls=1``). ``address``: an existing cluster (``ray.init(address=)``,
    also from ``RAY_ADDRESS``); without one, a Ray that is already initialised in this process is used, else a
    local one is started with ``num_cpus`` = the cores here, bound to 127.0.0.1, no dashboard, and shut down at
    the end. On a cluster, DIR must be on a file system every node sees under the same path, and camo must be
    installed on every node."""

    name = "ray"

    def __init__(self, workers: int, address: str | None = None):
        self.workers = workers
        self.address = address
        self.started = False
        self.ray = None

    def start(self) -> int:
        if not self.address:
            # A local Ray listens on the loopback address only (Ray otherwise picks the host's public IP).
            # Read when Ray is imported; set before the import.
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        ray = import_ray()
        self.ray = ray
        if self.address:
            try:
                ray.init(address=self.address, log_to_driver=False, ignore_reinit_error=True)
            except Exception as exc:  # noqa: BLE001 - ConnectionError, ValueError, RuntimeError ...
                raise CamoError(f"cannot connect to Ray at {self.address!r}: {' '.join(str(exc).split())[:300]}") \
                    from None
        elif not ray.is_initialized():
            cores = available_cores()
            try:
                from ray._private import ray_constants  # a Ray imported before we set the variable

                ray_constants.ENABLE_RAY_CLUSTER = False
            except Exception:  # noqa: BLE001 - private API; the env variable covers fresh imports
                pass
            saved = os.environ.pop("RAY_ADDRESS", None)  # ray.init() would connect to it instead
            try:
                ray.init(num_cpus=cores, include_dashboard=False, _node_ip_address="127.0.0.1",
                         log_to_driver=False)
            except Exception as exc:  # noqa: BLE001
                raise CamoError(f"cannot start a local Ray: {' '.join(str(exc).split())[:300]}") from None
            finally:
                if saved is not None:
                    os.environ["RAY_ADDRESS"] = saved
            self.started = True
        return max(1, int(ray.cluster_resources().get("CPU", 1)))

    def close(self) -> None:
        if self.started and self.ray is not None:
            self.ray.shutdown()
            self.started = False

    def run(self, jobs: list[Job], threads: int, on_result: OnResult) -> None:
        from camo.grid.cell import record_crash, run_cell

        ray = self.ray
        remote = ray.remote(num_cpus=threads, max_calls=1, max_retries=1)(run_cell)
        queue: deque[Job] = deque(jobs)
        inflight: dict[Any, Job] = {}
        stop = _StopHook()
        try:
            while queue or inflight:
                while queue and len(inflight) < self.workers:
                    job = queue.popleft()
                    inflight[remote.remote(job.cell.to_dict(), str(job.dir), threads)] = job
                ready, _ = ray.wait(list(inflight), num_returns=1)
                for ref in ready:
                    job = inflight.pop(ref)
                    try:
                        res = ray.get(ref)
                    except Exception as exc:  # noqa: BLE001 - WorkerCrashedError, RayTaskError, ...
                        res = record_crash(job.cell, job.dir, f"Ray task failed: {type(exc).__name__}: "
                                           f"{str(exc).splitlines()[0] if str(exc) else ''}")
                    on_result(job, res)
                    stop.tick()
        except BaseException:
            for ref in inflight:
                try:
                    ray.cancel(ref, force=True)
                except Exception:  # noqa: BLE001
                    pass
            raise
