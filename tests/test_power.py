"""``camo study power``: resampled power through the study's own pairwise tests, against analytic cases."""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import pytest

from camo_base.errors import CamoError
from study_site.power import parse_participants, participants_needed, power_curve, simulate_study, write_power


def cells(confusion: dict[str, float], scenes=("s1", "s2"), n=400, rt_found=2.0, limit=40.0, seed=0):
    """Per-trial outcomes: in every scene, method m is not found (timeout) with probability confusion[m]."""
    rng = np.random.default_rng(seed)
    rows = []
    for s in scenes:
        for m, c in confusion.items():
            k = int(round(c * n))
            found = np.r_[np.zeros(k, bool), np.ones(n - k, bool)]
            rng.shuffle(found)
            for f in found:
                rows.append((s, m, bool(f), not f, rt_found + rng.uniform(0, 1) if f else limit, limit))
    return pd.DataFrame(rows, columns=["scene", "method", "found", "timed_out", "rt_s", "time_limit_s"])


def test_simulated_study_fills_cells_evenly():
    c = cells({"a": 0.2, "b": 0.5, "c": 0.5}, scenes=("s1", "s2", "s3"))
    st = simulate_study(c, 30, np.random.default_rng(0))
    assert len(st) == 30 * 3 and st["participant"].nunique() == 30
    counts = st.groupby(["scene", "method"]).size()
    assert set(counts) == {10}  # 30 participants / 3 methods in each scene
    assert (st.groupby("participant")["scene"].nunique() == 3).all()  # one trial per scene each
    # each participant sees a different method in each scene (rotation)
    assert (st.groupby("participant")["method"].nunique() == 3).all()


def test_identical_methods_keep_the_false_positive_rate():
    c = cells({"a": 0.4, "b": 0.4})
    curve = power_curve(c, participants=(20, 80), reps=150, alpha=0.05, seed=1)
    assert (curve["power"] <= 0.1).all(), curve


def test_participants_needed_matches_the_two_proportion_formula():
    """Confusion 0.2 vs 0.6 with 2 scenes and 2 methods: each method gets N trials. The normal approximation
    needs (z_.975 + z_.8)^2 (p1 q1 + p2 q2) / (p1 - p2)^2 = 19.6 trials per method; Fisher's exact test is a
    little more conservative."""
    from scipy.stats import norm

    p1, p2 = 0.2, 0.6
    n_formula = (norm.ppf(0.975) + norm.ppf(0.8)) ** 2 * (p1 * (1 - p1) + p2 * (1 - p2)) / (p1 - p2) ** 2
    assert n_formula == pytest.approx(19.6, abs=0.1)
    c = cells({"a": p1, "b": p2})
    grid = (10, 15, 20, 25, 30, 35, 40, 60)
    curve = power_curve(c, participants=grid, reps=200, alpha=0.05, seed=2)
    need = participants_needed(curve, 0.8)
    n_fisher = need.loc[need["test"] == "p_fisher_holm", "participants"].item()
    assert n_formula <= n_fisher <= 35
    fis = curve[curve["test"] == "p_fisher_holm"].sort_values("n_participants")["power"].to_numpy()
    assert fis[0] < 0.6 and fis[-1] > 0.95
    assert np.all(np.diff(fis) > -0.08)  # rises with N (up to resampling noise)
    # times: finds at 2-3 s, non-finds censored at 40 s: the log-rank test sees the same contrast, with
    # comparable power (it is not a test of proportions, so no formula; within the grid)
    lr = need.loc[need["test"] == "p_logrank_holm", "participants"].item()
    assert n_formula <= lr <= 40


def test_write_power_outputs_and_bad_input(tmp_path):
    c = cells({"a": 0.1, "b": 0.7, "c": 0.8})
    res = write_power(c, tmp_path / "pw", participants=(10, 40), reps=20, seed=0, source="test")
    for f in ("power.csv", "power_needed.csv", "power.md", "power.png"):
        assert (tmp_path / "pw" / f).stat().st_size > 0
    assert len(res["needed"]) == 3 * 2  # 3 pairs x 2 tests
    md = (tmp_path / "pw" / "power.md").read_text()
    assert "a vs b" in md and "b vs c" in md
    with pytest.raises(CamoError, match="two methods"):
        power_curve(c[c["method"] == "a"], participants=(10,), reps=2)
    for bad in ("", "x", "1", "10,-4"):
        with pytest.raises(CamoError):
            parse_participants(bad)
    assert parse_participants("40, 10,10") == [10, 40]


def test_cli_power_from_a_predicted_evaluation(tmp_path, capsys):
    from study_site.cli import register

    ev = tmp_path / "ev"
    ev.mkdir()
    c = cells({"ours": 0.7, "mean": 0.2}, n=50)
    t = c.assign(run=c["scene"] + "-" + c["method"], ablation="none", view=0, trial=range(len(c)))
    t.to_parquet(ev / "simulated_trials.parquet")
    p = argparse.ArgumentParser(prog="camo")
    register(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(["study", "power", "--predicted", str(ev), "--out", str(tmp_path / "pw"),
                         "--participants", "10,60", "--reps", "30"])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "mean vs ours" in out and (tmp_path / "pw" / "power.png").is_file()
    for argv in (["study", "power", "--out", str(tmp_path / "x")],  # no source
                 ["study", "power", "--predicted", str(tmp_path), "--out", str(tmp_path / "x")]):  # no parquet
        args = p.parse_args(argv)
        with pytest.raises(CamoError):
            args.func(args)
    with pytest.raises(SystemExit):  # out of range: refused by the flag's type (tests/test_cli_ranges.py)
        p.parse_args(["study", "power", "--predicted", str(ev), "--out", str(tmp_path / "x"), "--reps", "0"])
