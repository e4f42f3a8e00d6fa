"""bench/observer_results.py: the sampling error of the observer's Kendall tau (docs/results/observer.md)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest


def _study(found: dict[str, int], n: int = 200, views: int = 4):
    """Per-stimulus rows, per-trial rows and crop metrics of one scene: label -> number of misses over all its
    stimuli (spread over the first views), ``n`` trials each, every find at 2.0 s; psnr ranks the labels in the
    order given (first = least hidden)."""
    vrows, trows, mrows = [], [], []
    for k, (lab, misses) in enumerate(found.items()):
        for v in range(views):
            sid = f"{lab}-{v}"
            miss = np.zeros(n, bool)
            miss[: max(0, min(n, misses - v * n))] = True
            vrows.append({"id": sid, "scene": "s", "label": lab, "run": lab, "view": str(v),
                          "p_found": 1.0 - miss.mean(), "mean_time_found_s": 2.0})
            trows += [{"id": sid, "trial": i, "found": not m, "rt_s": 2.0} for i, m in enumerate(miss)]
        mrows.append({"scene": "s", "label": lab, "run": lab, "region": "crop", "psnr": 20.0 + k})
    return pd.DataFrame(mrows), pd.DataFrame(vrows), pd.DataFrame(trows)


def test_an_order_set_by_one_missed_trial_is_a_tie_within_sampling_error(bench_module):
    ob = bench_module("observer_results")
    # psnr: a least hidden .. d best hidden; the observer: d missed once in 800 trials, the rest never -- so d is
    # "better hidden" on one trial and a, b, c tie: tau +0.50 at the point, but the one miss is not settled
    df, views, trials = _study({"a": 0, "b": 0, "c": 0, "d": 1})
    (row,) = [r for r in ob.tau_uncertainty(df, views, trials, n_boot=100) if r["metric"] == "psnr"]
    assert row["tau"] == pytest.approx(0.5)
    assert row["settled"] == 3 and row["pairs"] == 6  # a, b, c tie in every resample; d's pairs go either way
    assert row["lo"] == pytest.approx(0.0) and row["hi"] == pytest.approx(0.5)
    assert ob.tau_sign(row) == "?"


def test_an_order_set_by_many_misses_is_settled(bench_module):
    ob = bench_module("observer_results")
    # the observer's order the reverse of psnr's, each step 100 misses in 800 trials apart
    df, views, trials = _study({"a": 300, "b": 200, "c": 100, "d": 0})
    (row,) = [r for r in ob.tau_uncertainty(df, views, trials, n_boot=100) if r["metric"] == "psnr"]
    assert row["tau"] == pytest.approx(-1.0)
    assert row["lo"] == row["hi"] == pytest.approx(-1.0)
    assert row["settled"] == 6
    assert ob.tau_sign(row) == "-"
