"""Analysis numbers against hand-computed values on small synthetic tables."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from study_site.analysis import bootstrap_confusion, durations, holm, pairwise_tests, table_i, two_proportion_z, wilson_ci


def _trials(rows):
    """rows: (participant, method, outcome, rt_s) with outcome in {'hit', 'miss', 'timeout'}."""
    df = pd.DataFrame(rows, columns=["participant", "condition", "outcome", "rt_s"])
    df["label"] = "label of " + df["condition"]
    df["hit"] = df["outcome"] == "hit"
    df["timed_out"] = df["outcome"] == "timeout"
    df["time_limit_s"] = 40.0
    df["found"] = df["hit"] & ~df["timed_out"] & (df["rt_s"] <= df["time_limit_s"])
    df["time_on_trial_s"] = np.where(df["timed_out"], df["time_limit_s"], df["rt_s"])
    return df


def test_wilson_known_values():
    # 5/10: centre 0.5, half-width z*sqrt(.025 + z^2/400)/(1 + z^2/10) = 0.26340
    lo, hi = wilson_ci(5, 10)
    assert lo == pytest.approx(0.236593, abs=1e-6) and hi == pytest.approx(0.763407, abs=1e-6)
    # 0/10: upper bound z^2/(n + z^2) = 3.841459/13.841459
    assert wilson_ci(0, 10) == pytest.approx((0.0, 0.277533), abs=1e-6)
    from scipy.stats import binomtest

    ci = binomtest(37, 120).proportion_ci(method="wilson")
    assert wilson_ci(37, 120) == pytest.approx((ci.low, ci.high), abs=1e-12)
    assert all(math.isnan(v) for v in wilson_ci(0, 0))


def test_holm_hand_example():
    # sorted: .005*4=.02, .01*3=.03, .03*2=.06, .04*1=.04 -> max(.06,.04)=.06
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5, 0.6]) == pytest.approx([1.0, 1.0])
    out = holm([0.01, np.nan, 0.02])
    assert out[0] == pytest.approx(0.02) and math.isnan(out[1]) and out[2] == pytest.approx(0.02)


def test_two_proportion_z_hand_value():
    # p1=.3, p2=.2, pooled=.25, se=sqrt(.25*.75*.02)=.0612372 -> z=1.632993; R prop.test(correct=F): p=0.1025
    z, p = two_proportion_z(30, 100, 20, 100)
    assert z == pytest.approx(1.632993, abs=1e-6) and p == pytest.approx(0.102470, abs=1e-5)
    assert two_proportion_z(0, 10, 0, 12) == (0.0, 1.0)


def test_table_i_hand_computed():
    rows = [
        (1, "A", "hit", 2.0), (1, "A", "miss", 3.0), (2, "A", "hit", 4.0), (2, "A", "timeout", 40.02),
        (1, "B", "hit", 1.0), (1, "B", "hit", 2.0), (2, "B", "hit", 3.0), (2, "B", "hit", 4.0), (3, "B", "hit", 5.0),
    ]
    t = table_i(_trials(rows), n_boot=500, seed=1).set_index("condition")
    assert t["label"].tolist() == ["label of A", "label of B"]
    a, b = t.loc["A"], t.loc["B"]
    assert (a.n_trials, a.n_found, a.n_missed, a.n_timeout, a.n_participants) == (4, 2, 1, 1, 2)
    assert a.confusion_rate == 0.5 and b.confusion_rate == 0.0
    assert (a.confusion_wilson_lo, a.confusion_wilson_hi) == pytest.approx(wilson_ci(2, 4))
    assert a.mean_time_found_s == pytest.approx(3.0) and a.median_time_found_s == pytest.approx(3.0)
    # all trials: 2, 3 (miss at click), 4, 40 (timeout at limit)
    assert a.mean_time_all_s == pytest.approx(12.25) and a.median_time_all_s == pytest.approx(3.5)
    assert b.mean_time_found_s == pytest.approx(3.0) and b.median_time_found_s == pytest.approx(3.0)
    # KM: A events at 2, 4 of 4 at risk -> S(2)=.75, S(4)=.5 -> median 4; B: S(3)=.4 -> median 3
    assert a.km_median_s == pytest.approx(4.0) and b.km_median_s == pytest.approx(3.0)
    assert (b.confusion_boot_lo, b.confusion_boot_hi) == (0.0, 0.0)


def test_km_median_infinite_when_mostly_hidden():
    rows = [(1, "A", "timeout", 40.0), (2, "A", "miss", 5.0), (3, "A", "hit", 7.0)]
    assert math.isinf(table_i(_trials(rows), n_boot=0).iloc[0].km_median_s)


def test_durations_censoring():
    df = _trials([(1, "A", "hit", 2.0), (1, "A", "miss", 3.0), (1, "A", "timeout", 40.1)])
    d, e = durations(df)
    assert d.tolist() == [2.0, 40.0, 40.0] and e.tolist() == [True, False, False]
    d, e = durations(df, miss_censor="click")
    assert d.tolist() == [2.0, 3.0, 40.0] and e.tolist() == [True, False, False]


def test_bootstrap_resamples_participants():
    # P1: 2 trials not found; P2: 2 trials found. Replicates: {P1,P1}->1, {P2,P2}->0, mixed->.5
    df = _trials([(1, "A", "miss", 1.0), (1, "A", "timeout", 40.0), (2, "A", "hit", 1.0), (2, "A", "hit", 2.0)])
    ci = bootstrap_confusion(df, ["A"], n_boot=4000, seed=7)["A"]
    assert ci == (0.0, 1.0)
    again = bootstrap_confusion(df, ["A"], n_boot=4000, seed=7)["A"]
    assert again == ci  # seeded
    # one participant: no between-participant variation -> degenerate interval at the estimate
    one = _trials([(1, "A", "miss", 1.0), (1, "A", "hit", 2.0), (1, "A", "hit", 2.0), (1, "A", "hit", 2.0)])
    assert bootstrap_confusion(one, ["A"], n_boot=100, seed=0)["A"] == (0.25, 0.25)


def test_pairwise_tests_and_holm():
    from scipy.stats import fisher_exact

    rows = [(p, "A", "miss" if p <= 6 else "hit", 2.0) for p in range(1, 11)]
    rows += [(p, "B", "hit", 1.0 + p / 10) for p in range(1, 11)]
    rows += [(p, "C", "miss" if p <= 2 else "hit", 3.0) for p in range(1, 11)]
    pw = pairwise_tests(_trials(rows)).set_index(["condition_a", "condition_b"])
    ab = pw.loc[("A", "B")]
    assert (ab.confusion_a, ab.confusion_b, ab["diff"]) == pytest.approx((0.6, 0.0, 0.6))
    assert ab.p_fisher == pytest.approx(fisher_exact([[6, 4], [0, 10]])[1])
    assert ab.p_z == pytest.approx(two_proportion_z(6, 10, 0, 10)[1])
    assert pw["p_fisher_holm"].to_numpy() == pytest.approx(holm(pw["p_fisher"].to_numpy()))
    assert (pw["p_z_holm"] >= pw["p_z"]).all() and (pw["p_logrank_holm"] >= pw["p_logrank"]).all()
    assert ab.p_logrank < 0.05 and ab.logrank_chi2 > 0
