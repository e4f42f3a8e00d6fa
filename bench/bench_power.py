"""``camo study power``: the vectorised resampling against the loop it replaced, side by side in one run.

Both draw simulated studies of N participants from the same per-trial outcomes (one trial per scene, methods
rotated) and apply Table I's tests (Fisher, log-rank, Holm). The loop builds each study as a DataFrame and calls
:func:`study_site.analysis.pairwise_tests` (pandas + lifelines per replicate: how `camo study power` ran before
issue 33); the vectorised one (:func:`study_site.power.power_curve`) draws all replicates of an N at once. The
loop's replicate count is kept small and its time scaled to the vectorised one's count; the ratio is the figure
to read (the machine is shared: absolute seconds move with its load, printed with the load average).

Input: a stimulus set's ``predicted_trials.parquet`` (``--predicted STIMULI_DIR``), else synthetic cells of five
methods in one scene (4,000 trials per cell, like 20 stimuli x 200 simulated trials).

Usage: python bench/bench_power.py [--predicted STIMULI_DIR] [--reps 200] [--loop-reps 10]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import pandas as pd


def synthetic_cells(methods=("ours", "ours+inpainting", "mean", "random", "transparent"), n=4000, seed=0):
    rng = np.random.default_rng(seed)
    rows = []
    for k, m in enumerate(methods):
        found = rng.random(n) < 0.2 + 0.15 * k
        rt = np.where(found, rng.gamma(2.0, 1.5 + k, n), 40.0)
        rows.append(pd.DataFrame({"scene": "meadow", "method": m, "found": found, "timed_out": ~found,
                                  "rt_s": np.minimum(rt, 40.0), "time_limit_s": 40.0}))
    return pd.concat(rows, ignore_index=True)


def loop_power(cells, participants, reps, alpha=0.05, seed=0):
    from study_site.analysis import pairwise_tests
    from study_site.power import _cell_arrays, simulate_study

    rng = np.random.default_rng(seed)
    arrays = _cell_arrays(cells)
    hits = {}
    for n in participants:
        for _ in range(reps):
            for r in pairwise_tests(simulate_study(arrays, int(n), rng)).itertuples():
                for test in ("p_fisher_holm", "p_logrank_holm"):
                    p = getattr(r, test)
                    key = (n, r.method_a, r.method_b, test)
                    hits[key] = hits.get(key, 0) + int(bool(np.isfinite(p) and p < alpha))
    return hits


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--predicted", help="a stimulus set with predictions (default: synthetic cells)")
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--loop-reps", type=int, default=10)
    args = ap.parse_args()
    from study_site.power import DEFAULT_PARTICIPANTS, cells_from_predicted, power_curve

    cells = cells_from_predicted([args.predicted]) if args.predicted else synthetic_cells()
    grid = DEFAULT_PARTICIPANTS
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    power_curve(cells, grid, reps=args.reps, seed=0)
    t_vec = time.perf_counter() - t0
    t0 = time.perf_counter()
    loop_power(cells, grid, args.loop_reps)
    t_loop = (time.perf_counter() - t0) * args.reps / args.loop_reps
    print(f"cells: {cells.groupby(['scene', 'method']).ngroups} ({len(cells)} trials, "
          f"{cells['method'].nunique()} methods); grid {len(grid)} numbers of participants x {args.reps} studies; "
          f"load average {load:.1f} at the start")
    print(f"vectorised: {t_vec:.1f} s;  loop (pairwise_tests per study, {args.loop_reps} studies per N timed, "
          f"scaled to {args.reps}): {t_loop:.1f} s;  ratio {t_loop / t_vec:.0f}x")


if __name__ == "__main__":
    main()
