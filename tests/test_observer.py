"""The simulated observer (evaluation/observer.py): sanity checks of the search model on known images."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from evaluation.observer import ObserverConfig, make_cells, predict_stimulus, predicted_table, simulate_search, srgb_to_lab
from camo_base.errors import CamoError

N = 256


def grass(seed: int = 0, n: int = N) -> np.ndarray:
    """A green 1/f texture with pixel noise, sRGB (n, n, 3) float32: a stand-in for the meadow's ground."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(n)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    fr[0, 0] = 1.0
    tex = np.real(np.fft.ifft2((rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))) / fr))
    tex = (tex - tex.mean()) / tex.std()
    t = 0.5 + 0.12 * tex + 0.06 * rng.normal(size=(n, n))
    return np.clip(np.stack([0.35 * t, 0.75 * t, 0.25 * t], -1), 0, 1).astype(np.float32)


def disc(cx: float, cy: float, r: float, n: int = N) -> np.ndarray:
    yy, xx = np.mgrid[0:n, 0:n]
    return (yy - cy) ** 2 + (xx - cx) ** 2 < r * r


RED = np.array([0.9, 0.05, 0.05], np.float32)


def with_object(bg: np.ndarray, mask: np.ndarray, alpha: float) -> np.ndarray:
    """The red object mixed into the background: alpha 0 = saturated red, 1 = invisible (background only)."""
    img = bg.copy()
    img[mask] = alpha * bg[mask] + (1 - alpha) * RED
    return img


def test_lab_known_values():
    lab = srgb_to_lab(np.array([[1.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], np.float32))
    np.testing.assert_allclose(lab[0], [100.0, 0.0, 0.0], atol=0.01)
    np.testing.assert_allclose(lab[1], [53.24, 80.09, 67.20], atol=0.05)  # CIE L*a*b* of sRGB red (D65)
    np.testing.assert_allclose(lab[2], [0.0, 0.0, 0.0], atol=1e-3)


def test_red_object_on_grass_is_found_in_the_first_fixations():
    bg = grass()
    mask = disc(70, 170, 14)  # 4.7 deg from the centre at 16 deg per image height
    p = predict_stimulus(with_object(bg, mask, 0.0), mask, n=200, seed=1)
    assert p.p_found >= 0.97
    assert np.median(p.result.fixations) <= 2 and p.result.fixations.max() <= 4
    assert np.median(p.rt_found_s) < 1.5
    assert p.max_d_object > 5  # far above the criterion (3.5)


def test_first_fixation_detection_time_is_fixation_plus_fitts():
    """A large red disc at the centre is seen at the first fixation: rt = fixation + Fitts' law to the click."""
    bg = grass(2)
    mask = disc(128, 128, 40)
    cfg = ObserverConfig()
    img = with_object(bg, mask, 0.0)
    cells = make_cells(img, cfg)
    res = simulate_search(img, n=50, seed=0, config=cfg, mask=mask, cells=cells)
    assert res.found.all() and (res.fixations == 1).all()
    # which cell was clicked: the one whose click point equals the recorded click
    idx = [int(np.flatnonzero((cells.click_px[:, 0] == x) & (cells.click_px[:, 1] == y))[0])
           for x, y in zip(res.click_x, res.click_y)]
    d = np.linalg.norm(cells.pos_deg[idx] - [cells.width_deg / 2, cells.height_deg / 2], axis=1)
    expected = cfg.fixation_s + cfg.fitts_a_s + cfg.fitts_b_s * np.log2(d / cfg.fitts_width_deg + 1)
    np.testing.assert_allclose(res.rt_s, expected, rtol=1e-12)


def test_blending_the_object_into_the_background_raises_the_time_monotonically():
    bg = grass(3)
    mask = disc(190, 80, 16)
    alphas = (0.0, 0.6, 0.8, 0.88, 0.94, 1.0)
    preds = [predict_stimulus(with_object(bg, mask, a), mask, n=300, seed=5) for a in alphas]
    times = [float(p.time_to_find_s.mean()) for p in preds]  # misses and timeouts at the limit
    found = [p.p_found for p in preds]
    d_obj = [p.max_d_object for p in preds]
    assert all(b >= a - 1e-9 for a, b in zip(times, times[1:])), times
    assert all(b <= a + 1e-9 for a, b in zip(found, found[1:])), found
    assert all(b < a for a, b in zip(d_obj, d_obj[1:])), d_obj  # discriminability falls strictly
    assert times[0] < 2.0 and times[-1] > 35.0  # from found at once to (almost) never found
    assert found[0] >= 0.97 and found[-1] <= 0.05


def test_without_the_object_found_only_by_chance_and_the_mask_is_never_seen():
    bg = grass(4)
    rng = np.random.default_rng(0)
    rates, shares = [], []
    clicks = None
    for k in range(12):
        cx, cy = rng.uniform(30, N - 30, 2)
        mask = disc(cx, cy, 14)
        res = simulate_search(bg, n=100, seed=9, mask=mask)
        # same image and seed, another mask: the observer behaves identically (it never sees the mask)
        c = (res.click_x.copy(), res.click_y.copy(), res.rt_s.copy())
        if clicks is not None:
            for a, b in zip(clicks, c):
                np.testing.assert_array_equal(a, b)
        clicks = c
        rates.append(res.found.mean())
        shares.append(mask.mean())
    # a chance click hits a 14 px disc about as often as its share of the image (~1 %); allow generous slack
    assert np.mean(rates) <= 3 * np.mean(shares) + 0.02
    assert np.mean(rates) < 0.1


def test_time_limit_bounds_the_search():
    cfg = ObserverConfig(time_limit_s=2.0)
    res = simulate_search(grass(5), n=40, seed=0, config=cfg)
    assert (res.rt_s <= 2.0).all()
    assert (res.rt_s[res.timed_out] == 2.0).all() and (res.click_x[res.timed_out] == -1).all()
    assert res.fixations.max() <= math.ceil(2.0 / cfg.fixation_s) + 1


def test_deterministic_for_a_seed():
    img = with_object(grass(6), disc(60, 60, 12), 0.85)
    a = simulate_search(img, n=30, seed=3)
    b = simulate_search(img, n=30, seed=3)
    np.testing.assert_array_equal(a.rt_s, b.rt_s)
    np.testing.assert_array_equal(a.click_x, b.click_x)


def test_bad_input_is_camoerror():
    img = grass(7, 64)
    with pytest.raises(CamoError, match="expected an"):
        simulate_search(img[..., 0])
    bad = img.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(CamoError, match="finite sRGB"):
        simulate_search(bad)
    with pytest.raises(CamoError, match="mask is"):
        simulate_search(img, n=2, mask=np.zeros((10, 10), bool))
    with pytest.raises(CamoError, match="must be > 0"):
        simulate_search(img, config=ObserverConfig(fixation_s=0))
    with pytest.raises(CamoError, match="start"):
        simulate_search(img, config=ObserverConfig(start="left"))
    with pytest.raises(CamoError, match="n must be"):
        simulate_search(img, n=0)


def test_predicted_table_means_and_times():
    views = pd.DataFrame({
        "scene": ["a", "b", "a", "b"], "method": ["m1", "m1", "m2", "m2"], "p_found": [1.0, 0.5, 0.2, 0.0],
        "p_miss": [0.0, 0.25, 0.3, 0.5], "p_timeout": [0.0, 0.25, 0.5, 0.5], "mean_time_found_s": [1, 3, 10, np.nan],
        "median_time_found_s": [1, 3, 10, np.nan], "mean_time_all_s": [1, 20, 30, 40], "median_time_all_s": [1, 20, 30, 40],
    })
    trials = pd.DataFrame({"method": ["m1"] * 3 + ["m2"] * 2, "found": [True, True, False, True, False],
                           "rt_s": [1.0, 2.0, 40.0, 9.0, 40.0]})
    t = predicted_table(views, trials=trials).set_index("method")
    assert t.loc["m1", "confusion_rate"] == pytest.approx(0.25)
    assert t.loc["m2", "confusion_rate"] == pytest.approx(0.9)
    assert t.loc["m1", "mean_time_found_s"] == pytest.approx(1.5)
    assert t.loc["m1", "median_time_all_s"] == pytest.approx(2.0)
    assert t.loc["m2", "mean_time_all_s"] == pytest.approx(24.5)
    assert t.loc["m1", "easy_views"] == 1 and t.loc["m2", "easy_views"] == 0


# ---------------------------------------------------------------------------
# evaluation directories and the report's "simulated" section
# ---------------------------------------------------------------------------


def test_predict_eval_dir_writes_predictions_that_match_the_library(tmp_path):
    import json

    from PIL import Image

    from evaluation.observer import PREDICTION_COLUMNS, TRIAL_COLUMNS, predict_eval_dir
    from study_site.testing import make_fake_eval_dir

    entries = make_fake_eval_dir(tmp_path, scenes=("s1",), methods=("ours", "mean"), views=2, size=(64, 48))
    # one view with an empty mask (object hidden): skipped
    Image.fromarray(np.zeros((48, 64), np.uint8)).save(tmp_path / entries[-1]["mask"])
    views, trials = predict_eval_dir(tmp_path, n=20, seed=4)
    assert list(views.columns) == list(PREDICTION_COLUMNS) and list(trials.columns) == list(TRIAL_COLUMNS)
    assert len(views) == 3 and len(trials) == 3 * 20
    for f in ("simulated.parquet", "simulated.csv", "simulated_trials.parquet", "simulated_config.json"):
        assert (tmp_path / f).stat().st_size > 0
    cfg = json.loads((tmp_path / "simulated_config.json").read_text())
    assert cfg["observer"]["start"] == "random" and cfg["trials_per_view"] == 20
    # the stored figures are the library's for that image, mask and seed
    e = entries[1]
    img = np.asarray(Image.open(tmp_path / e["image"]).convert("RGB"))
    mask = np.asarray(Image.open(tmp_path / e["mask"]).convert("L")) >= 128
    p = predict_stimulus(img, mask, 20, 4 + 7919 * 1, ObserverConfig(start="random"))
    row = views.iloc[1]
    assert row["p_found"] == pytest.approx(p.p_found) and row["p_timeout"] == pytest.approx(p.p_timeout)
    t = trials[(trials["run"] == e["run"]) & (trials["view"] == e["view"])]
    np.testing.assert_allclose(t["rt_s"].to_numpy(), p.result.rt_s)
    assert (views["p_found"] + views["p_miss"] + views["p_timeout"]).round(9).eq(1.0).all()


def test_predict_eval_dir_bad_input(tmp_path):
    from evaluation.observer import predict_eval_dir

    with pytest.raises(CamoError, match="no renders.json"):
        predict_eval_dir(tmp_path)
    (tmp_path / "renders.json").write_text("{oops")
    with pytest.raises(CamoError, match="not valid JSON"):
        predict_eval_dir(tmp_path)
    (tmp_path / "renders.json").write_text('[{"run": "r", "image": "nope.png", "mask": "nope_mask.png"}]')
    with pytest.raises(CamoError, match="missing render"):
        predict_eval_dir(tmp_path)
    assert not (tmp_path / "simulated.parquet").exists()


def test_observer_agreement_lists_the_pairs_ordered_differently():
    from evaluation.report import _kendall, observer_agreement

    assert _kendall([1, 2, 3], [10, 20, 30]) == pytest.approx(1.0)
    assert _kendall([1, 2, 3], [30, 20, 10]) == pytest.approx(-1.0)
    assert _kendall([1, 2, 3], [10, 30, 20]) == pytest.approx(1 / 3)
    df = pd.DataFrame({
        "region": ["crop"] * 3, "scene": ["s"] * 3, "run": ["a", "b", "c"], "label": ["A", "B", "C"],
        "psnr": [30.0, 25.0, 20.0],  # PSNR says A best hidden, then B, then C
        "lpips_proxy": [0.1, 0.3, 0.2],  # LPIPS-proxy: A, C, B
    })
    views = pd.DataFrame({"scene": ["s"] * 3, "run": ["a", "b", "c"], "label": ["A", "B", "C"],
                          "p_found": [0.2, 0.5, 0.8]})  # observer: A hidden best, then B, then C
    taus, dis = observer_agreement(df, views)
    by = {x["metric"]: x["tau"] for x in taus}
    assert by["psnr"] == pytest.approx(1.0) and by["lpips_proxy"] == pytest.approx(1 / 3)
    assert [(x["metric"], x["better_by_metric"], x["better_by_observer"]) for x in dis] == [("lpips_proxy", "C", "B")]


# ---------------------------------------------------------------------------
# a learned map from local TorchScript weights (tiny, made here)
# ---------------------------------------------------------------------------


def _tiny_net(path, weight_red: bool = True):
    """A 1x1 convolution scoring redness (r - g) or, with random weights, anything: saved as TorchScript."""
    import torch

    net = torch.nn.Conv2d(3, 1, 1)
    with torch.no_grad():
        if weight_red:
            net.weight[:] = torch.tensor([1.0, -1.0, 0.0]).view(1, 3, 1, 1)
            net.bias.zero_()
        else:
            torch.manual_seed(0)
            net.weight.normal_()
    torch.jit.save(torch.jit.script(net), str(path))
    return path


def test_learned_saliency_map_from_local_torchscript(tmp_path):
    from evaluation.observer import discriminability_map

    bg = grass(8)
    mask = disc(200, 60, 14)
    img = with_object(bg, mask, 0.0)
    cfg = ObserverConfig(saliency_model=str(_tiny_net(tmp_path / "red.pt")))
    d = discriminability_map(img, cfg)
    assert d.shape == discriminability_map(img).shape  # same grid as the weight-free map
    # the map is the network's output (r - g), z-scored: its peak lies on the red disc
    y, x = np.unravel_index(d.argmax(), d.shape)
    assert mask[int((y + 0.5) * N / d.shape[0]), int((x + 0.5) * N / d.shape[1])]
    p = predict_stimulus(img, mask, n=50, seed=0, config=cfg)
    assert p.p_found >= 0.95
    assert "saliency_model_sha256" in cfg.to_dict() and len(cfg.to_dict()["saliency_model_sha256"]) == 64
    # random tiny weights run too (any TorchScript map); bad files are one-line errors
    rnd = ObserverConfig(saliency_model=str(_tiny_net(tmp_path / "rnd.pt", weight_red=False)))
    assert np.isfinite(discriminability_map(img, rnd)).all()
    (tmp_path / "bad.pt").write_bytes(b"not a model")
    with pytest.raises(CamoError, match="not a TorchScript file"):
        discriminability_map(img, ObserverConfig(saliency_model=str(tmp_path / "bad.pt")))
    with pytest.raises(CamoError, match="file not found"):
        simulate_search(img, config=ObserverConfig(saliency_model=str(tmp_path / "missing.pt")))


def test_simulated_section_of_the_report(tmp_path):
    import json

    from evaluation.observer import PREDICTION_COLUMNS
    from evaluation.report import simulated_section

    rows = []
    for run, method, pf, med in (("s-ours", "ours", 0.2, 5.0), ("s-mean", "mean", 1.0, 1.1)):
        for v in range(2):
            rows.append({c: 0 for c in PREDICTION_COLUMNS} | {
                "run": run, "scene": "s", "object": "o", "method": method, "ablation": "none", "view": v, "n": 10,
                "p_found": pf, "p_miss": 0.0, "p_timeout": 1 - pf, "median_time_found_s": med, "mean_time_found_s": med,
                "mean_time_all_s": 30.0, "median_time_all_s": 30.0})
    pd.DataFrame(rows).to_parquet(tmp_path / "simulated.parquet")
    (tmp_path / "simulated_config.json").write_text(json.dumps({"observer": {"display_deg": 16.0}, "trials_per_view": 10}))
    df = pd.DataFrame({"region": ["crop"] * 4, "scene": ["s"] * 4, "run": ["s-ours"] * 2 + ["s-mean"] * 2,
                       "label": ["Ours"] * 2 + ["Mean [6]"] * 2, "_order": [(5, 0, "")] * 2 + [(0, 1, "")] * 2,
                       "method": ["ours"] * 2 + ["mean"] * 2, "view": [0, 1, 0, 1],
                       "psnr": [20.0, 20.0, 30.0, 30.0]})  # PSNR prefers Mean, the observer Ours
    for m in ("ssim", "lpips", "lpips_proxy", "sifid", "sifid_proxy", "dreamsim"):
        df[m] = np.nan
    md, ht = simulated_section(df, [tmp_path])
    text = "\n".join(md)
    assert "| Ours | 80.0% |" in text and "| Mean [6] | 0.0% |" in text  # predicted confusion = 1 - p found
    assert "s-mean view 0 (p found 1.00, median 1.10 s)" in text and "s-ours view" not in text.split("Easy views")[1]
    assert "| s | PSNR↑ | Mean [6] | Ours | 30.00 / 20.00 | 0.0% / 80.0% |" in text
    assert any("Simulated observer" in h for h in ht)
    assert simulated_section(df, [tmp_path / "nothing"]) == ([], [])
