"""``camo study power``: resampled power through the study's own pairwise tests, against analytic cases."""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import pytest

from camo_base.errors import CamoError
from camo_base.tables import read_parquet, write_parquet
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


def test_vectorised_tests_equal_the_study_analysis_replicate_by_replicate():
    """The vectorised Fisher and log-rank p-values (Holm) of every simulated study are those of
    study_site.analysis.pairwise_tests on the same trials -- with tied times, misses and timeouts."""
    from study_site.analysis import pairwise_tests
    from study_site.power import _cell_arrays, draw_replicates, replicate_frame, replicate_pvalues

    rng = np.random.default_rng(0)
    c = cells({"a": 0.3, "b": 0.5, "c": 0.55}, scenes=("s1", "s2", "s3"), n=120)
    c.loc[c["found"], "rt_s"] = np.round(rng.gamma(2, 3, int(c["found"].sum())), 1)  # ties
    c.loc[~c["found"] & (rng.random(len(c)) < 0.5), "timed_out"] = False  # misses
    arrays = _cell_arrays(c)
    times = np.unique(np.concatenate([np.where(f, rt, lim) for f, _, rt, lim in arrays.values()]))
    draws = draw_replicates(arrays, 30, 15, rng, times)
    pv = replicate_pvalues(draws, len(times))
    for r in range(15):
        for row in pairwise_tests(replicate_frame(draws, r)).itertuples():
            for test in ("p_fisher_holm", "p_logrank_holm"):
                assert pv[(row.condition_a, row.condition_b)][test][r] == pytest.approx(getattr(row, test), rel=1e-9)


def test_fisher_matches_scipy_on_random_tables():
    from scipy.stats import fisher_exact

    from study_site.power import fisher_two_sided

    rng = np.random.default_rng(1)
    ka, kb = rng.integers(0, 31, 200), rng.integers(0, 41, 200)
    p = fisher_two_sided(ka, 30, kb, 40)
    ref = [fisher_exact([[a, 30 - a], [b, 40 - b]])[1] for a, b in zip(ka, kb)]
    np.testing.assert_allclose(p, ref, rtol=1e-9)


def _stimulus_set_with_predictions(root, n=50):
    """A stimulus set (two scenes, ours and mean) whose predicted_trials.parquet holds ``cells`` outcomes."""
    c = cells({"ours": 0.7, "mean": 0.2}, n=n)
    t = c.assign(id=[f"id{i // n}" for i in range(len(c))], view="0", practice=False, trial=np.arange(len(c)) % n)
    root.mkdir(parents=True, exist_ok=True)
    write_parquet(t, root / "predicted_trials.parquet")
    write_parquet(pd.DataFrame({"id": t["id"].unique()}), root / "predicted.parquet")
    return root


def test_cli_power_from_predicted_stimuli(tmp_path, capsys):
    from study_site.cli import register

    stim = _stimulus_set_with_predictions(tmp_path / "stim")
    p = argparse.ArgumentParser(prog="camo")
    register(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(["study", "power", "--predicted", str(stim), "--out", str(tmp_path / "pw"),
                         "--participants", "10,60", "--reps", "30", "--quiet"])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "mean vs ours" in out and "simulated studies in" in out and (tmp_path / "pw" / "power.png").is_file()
    # an evaluation directory is not what people see: a one-line error says to build the stimuli
    ev = tmp_path / "ev"
    ev.mkdir()
    (ev / "renders.json").write_text("[]")
    args = p.parse_args(["study", "power", "--predicted", str(ev), "--out", str(tmp_path / "pw2")])
    with pytest.raises(CamoError, match="build-stimuli"):
        args.func(args)
    assert not (tmp_path / "pw2").exists()
    with pytest.raises(SystemExit):  # out of range: refused by the flag's type (tests/test_cli_ranges.py)
        p.parse_args(["study", "power", "--predicted", str(stim), "--out", str(tmp_path / "x"), "--reps", "0"])


def test_end_to_end_build_stimuli_to_power(tmp_path, capsys):
    """build-stimuli (copying evaluation renders) runs the observer on every stimulus it writes; `camo study
    power --predicted` reads those predictions (the report's section on them: tests/test_observer.py)."""
    import json

    from study_site.cli import register
    from study_site.testing import make_fake_eval_dir

    ev = tmp_path / "eval"
    make_fake_eval_dir(ev, scenes=("sa",), methods=("mean", "ours"), views=2, size=(96, 96))
    p = argparse.ArgumentParser(prog="camo")
    register(p.add_subparsers(dest="command", required=True))
    stim = tmp_path / "stim"
    args = p.parse_args(["study", "build-stimuli", str(ev), "--out", str(stim), "--copy", "--synthetic-practice",
                         "0", "--observer-trials", "20"])
    assert args.func(args) == 0
    assert "predicted mean: confusion" in capsys.readouterr().out
    views = read_parquet(stim / "predicted.parquet")
    trials = read_parquet(stim / "predicted_trials.parquet")
    manifest = json.loads((stim / "manifest.json").read_text())
    assert sorted(views["id"]) == sorted(s["id"] for s in manifest["stimuli"])  # every stimulus it built
    assert len(trials) == 20 * len(views)
    assert set(trials["method"]) == {"mean", "ours"}
    assert (views["p_found"] + views["p_miss"] + views["p_timeout"]).round(9).eq(1.0).all()
    assert (stim / "predicted_power" / "power.png").is_file()
    cfg = json.loads((stim / "predicted_config.json").read_text())
    assert cfg["trials_per_stimulus"] == 20 and cfg["observer"]["time_limit_s"] == 40.0
    args = p.parse_args(["study", "power", "--predicted", str(stim), "--out", str(tmp_path / "pw"),
                         "--participants", "10,20", "--reps", "20", "--quiet"])
    assert args.func(args) == 0
    assert (tmp_path / "pw" / "power_needed.csv").is_file()
