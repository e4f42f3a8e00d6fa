"""bench/metric_agreement.py: the LPIPS-vs-proxy agreement page's numbers on hand-made rows with known answers
(Kendall / Spearman by hand, the paired z of a known difference, which method pairs disagree) and the coverage it
states for a partly finished grid folder."""

from __future__ import annotations

import json
import math

import pandas as pd
import pytest


@pytest.fixture(scope="module")
def ma(bench_module):
    return bench_module("metric_agreement")


def test_corr_matches_hand_computed_tau_and_rho(ma):
    # one discordant pair of 6: tau = (5 - 1) / 6; rho = 1 - 6 * sum(d^2) / (n (n^2 - 1)) = 1 - 12 / 60
    tau, rho, n = ma.corr(pd.Series([1.0, 2, 3, 4]).to_numpy(), pd.Series([1.0, 3, 2, 4]).to_numpy())
    assert (round(tau, 6), round(rho, 6), n) == (round(4 / 6, 6), 0.8, 4)
    tau, rho, _ = ma.corr(pd.Series([1.0, 2, 3]).to_numpy(), pd.Series([3.0, 2, 1]).to_numpy())
    assert (tau, rho) == (-1.0, -1.0)
    # a constant column or fewer than 3 finite points has no correlation
    assert math.isnan(ma.corr(pd.Series([1.0, 2, 3]).to_numpy(), pd.Series([1.0, 1, 1]).to_numpy())[0])
    assert ma.corr(pd.Series([1.0, 2, math.nan]).to_numpy(), pd.Series([1.0, 2, 3]).to_numpy())[2] == 2


def _rows():
    """One scene, methods A, B over three views. LPIPS: A hides better (0.1 vs 0.2, 0.3). LPIPS-proxy orders them
    the other way, clearly; PSNR (higher = better, so negated) and SSIM agree; SIFID-proxy disagrees within the
    view-to-view spread (per-view differences 1.0, -1.0, 0.5)."""
    rows = []
    for v, (la, lb) in enumerate([(0.10, 0.20), (0.10, 0.30), (0.10, 0.40)]):
        rows.append(dict(scene="s", label="A", run="a", view=v, lpips=la, lpips_proxy=0.5 + v * 0.01,
                         ssim=0.9, psnr=30.0, sifid_proxy=2.0))
        rows.append(dict(scene="s", label="B", run="b", view=v, lpips=lb, lpips_proxy=0.4, ssim=0.8, psnr=20.0 + v,
                         sifid_proxy=(1.0, 3.0, 1.5)[v]))
    return pd.DataFrame(rows)


def test_agreement_finds_the_disagreeing_pairs_with_metric_orientation(ma):
    lines, dis = ma.agreement(_rows(), "g")
    assert sorted(d["metric"] for d in dis) == ["lpips_proxy", "sifid_proxy"]
    d = next(d for d in dis if d["metric"] == "lpips_proxy")
    assert (d["lpips_says"], d["metric_says"]) == ("A", "B")
    assert d["lpips"] == pytest.approx((0.1, 0.3))
    assert d["value"] == pytest.approx((0.51, 0.4))
    # LPIPS difference per view: -0.1, -0.2, -0.3: mean 0.2, sd 0.1, se 0.1 / sqrt(3)
    assert d["z"][0] == pytest.approx(0.2 / (0.1 / math.sqrt(3)))
    assert math.isinf(d["z"][1]) is False and d["z"][1] == pytest.approx(0.11 / (0.01 / math.sqrt(3)))
    assert ma.paired_z(_rows().groupby(["label", "view"])[["sifid_proxy"]].mean(), "A", "B", "sifid_proxy") \
        == pytest.approx((1 / 6) / (math.sqrt(((5 / 6) ** 2 + (7 / 6) ** 2 + (1 / 3) ** 2) / 2) / math.sqrt(3)))
    pooled = next(line for line in lines if line.startswith("| **pooled"))
    assert pooled.split("|")[2].strip() == "6"
    assert ma.pair_counts(_rows(), dis) == ["LPIPS-proxy 1 of 1 (1 clear on both)", "SSIM 0 of 1 (0 clear on both)",
                                            "PSNR 0 of 1 (0 clear on both)", "SIFID-proxy 1 of 1 (0 clear on both)"]


def test_coverage_counts_scenes_with_every_method_finished(ma, tmp_path):
    def cell(key, scene, done):
        d = tmp_path / "cells" / key
        d.mkdir(parents=True)
        (d / "cell.json").write_text(json.dumps({"scene_label": scene, "method": key}))
        if done:
            (d / "eval" / key).mkdir(parents=True)
            (d / "eval" / key / "metrics.parquet").write_bytes(b"")

    cell("a1", "p/a.toml", True)
    cell("a2", "p/a.toml", True)
    cell("b1", "p/b.toml", True)
    cell("b2", "p/b.toml", False)
    cell("c1", "p/c.toml", False)
    assert ma.coverage(tmp_path) == (1, 2, 3)
    assert ma._scenes(tmp_path) == "1 of 3 scenes with every method, 1 partly"
