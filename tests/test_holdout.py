"""Held-out views (optimizer/optimise/holdout.py): the score against hand-computed values, the cameras, the
selection and patience rules on scripted scores, and end to end through ``camo optimize`` on a tiny scene (the
result is the chosen iterate, a resumed run chooses what an uninterrupted one does, the seconds are counted)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from camo.cli import main
from optimizer.optimise.holdout import Holdout, HoldoutSettings, holdout_cameras, psnr_of

TINY = ["--views", "3", "--resolution", "32", "--map-resolution", "48", "--displacement-resolution", "16",
        "--target-vertices", "800", "--spp", "2", "--target-spp", "16", "--quiet", "--threads", "1"]


# --- the score, by hand ---------------------------------------------------------------------------------------

def test_split_error_matches_hand_computed_values():
    """Linear 0.5 vs 0.25 in sRGB: 0.7353569 vs 0.5370987, d = 0.1982582. Two equal pairs: bias^2 = d^2, variance 0;
    pairs with differences a and b: bias^2 = a b, variance (a - b)^2 / 2; only weighted pixels count, weights
    scale them, HDR is clipped at 1 like an 8-bit image, NaN reads as black, zero weights give (0, 0)."""
    from optimizer.optimise.holdout import split_error

    srgb = lambda x: 1.055 * x ** (1 / 2.4) - 0.055  # noqa: E731 (x > 0.0031308)
    bg = np.full((1, 2, 2, 3), 0.25, np.float32)
    img = bg.copy()
    img[0, 0, 0] = 0.5
    d = srgb(0.5) - srgb(0.25)
    w = np.zeros((1, 2, 2))
    w[0, 0, 0] = 1.0
    b2, var = split_error(img, bg, img, bg, w)
    assert b2 == pytest.approx(d * d, rel=1e-6) and var == pytest.approx(0.0, abs=1e-12)
    img2 = bg.copy()
    img2[0, 0, 0] = 0.3
    e = srgb(0.3) - srgb(0.25)
    b2, var = split_error(img, bg, img2, bg, w)
    assert b2 == pytest.approx(d * e, rel=1e-6) and var == pytest.approx((d - e) ** 2 / 2, rel=1e-6)
    w[0, 1, 1] = 3.0  # a matching pixel with weight 3: the mean over 4 weight units
    assert split_error(img, bg, img, bg, w)[0] == pytest.approx(d * d / 4, rel=1e-6)
    hdr, nan = img.copy(), img.copy()
    hdr[0, 0, 0] = 7.0  # clipped to 1 -> sRGB 1
    nan[0, 0, 0] = np.nan  # black
    w1 = np.zeros((1, 2, 2))
    w1[0, 0, 0] = 1.0
    assert split_error(hdr, bg, hdr, bg, w1)[0] == pytest.approx((1 - srgb(0.25)) ** 2, rel=1e-6)
    assert split_error(nan, bg, nan, bg, w1)[0] == pytest.approx(srgb(0.25) ** 2, rel=1e-6)
    assert split_error(img, bg, img, bg, np.zeros((1, 2, 2))) == (0.0, 0.0)
    assert psnr_of(0.01) == pytest.approx(20.0) and psnr_of(0.0) == math.inf


def test_the_score_is_bias_squared_plus_the_evaluation_s_noise():
    """Scripted renders whose two pairs differ from the background by b + n and b - n (one pixel of two): the check
    records bias2 = d(b+n) d(b-n) / 2 and variance = (d(b+n) - d(b-n))^2 / 4 (sRGB differences d), and its score is
    bias2 + variance * spp / noise_spp (16 / 64): a quarter of the check's own noise, as a 64-spp evaluation sees it."""
    from optimizer.scenes.builtin_scenes import resolve_scene

    bg = np.full((1, 1, 2, 3), 0.2, np.float32)
    srgb = lambda x: 1.055 * x ** (1 / 2.4) - 0.055  # noqa: E731

    def render(values, cams, spp, seed):
        img = bg.copy()
        bias, noise = values["x"]
        img[0, 0, 0] += bias + (noise if seed == h.render_seeds[0] else -noise)
        return img

    h = Holdout(HoldoutSettings(views=1, every=1, spp=16, noise_spp=64), resolve_scene("gravel"), 0, render,
                lambda cams, spp, seed: bg, lambda values, cams: np.ones((1, 1, 2)), 0.05, 0.0)
    assert h.render_seeds[1] == h.render_seeds[0] + 1
    rec = h.check({"x": np.array([0.05, 0.02])}, 1, 0, 0.0)
    d_plus, d_minus = srgb(0.27) - srgb(0.2), srgb(0.23) - srgb(0.2)
    assert rec["bias2"] == pytest.approx(d_plus * d_minus / 2, rel=1e-5)
    assert rec["variance"] == pytest.approx((d_plus - d_minus) ** 2 / 4, rel=1e-5)
    assert rec["mse"] == pytest.approx(rec["bias2"] + rec["variance"] / 4, rel=1e-6)


def test_holdout_cameras_are_new_views_of_the_rig_and_reproducible():
    """Evenly spaced over the rig, moved off every training camera, the same for the same seed, different for
    another seed, and never the evaluation's novel views (another seed stream)."""
    from evaluation.views import evaluation_cameras
    from optimizer.scenes.builtin_scenes import resolve_scene
    from optimizer.scenes.cameras import cameras

    pack = resolve_scene("gravel")
    train = cameras(pack)
    a = holdout_cameras(pack, 4, 0)
    assert len(a) == 4 and a == holdout_cameras(pack, 4, 0)
    assert all(c.origin not in {t.origin for t in train} for c in a)
    assert [c.origin for c in a] != [c.origin for c in holdout_cameras(pack, 4, 1)]
    ev = {c.origin for c in evaluation_cameras(pack, 8, seed=0).cams}
    assert not ev & {c.origin for c in holdout_cameras(pack, 8, 0)}
    # each held-out camera stays within the jitter box of its training camera: +-0.25 * radius / 4 per axis
    r = float(pack.cameras.radius)
    base = [train[int(round(i * len(train) / 4)) % len(train)] for i in range(4)]
    for c, t in zip(a, base):
        assert np.abs(np.subtract(c.origin, t.origin)).max() <= 0.25 * r / 4 + 1e-9


# --- selection and patience on scripted scores ------------------------------------------------------------------

def scripted(errors, patience=0, every=1):
    """A Holdout whose with-object render at check k differs from the background by ``errors[k]`` (linear, one
    pixel), so its score is known; the parameters are ``{"x": k}``."""
    bg = np.full((1, 2, 2, 3), 0.2, np.float32)

    def render(values, cams, spp, seed):
        img = bg.copy()
        img[0, 0, 0] += errors[int(values["x"][0])]
        return img

    from optimizer.scenes.builtin_scenes import resolve_scene

    h = Holdout(HoldoutSettings(views=1, every=every, spp=1, patience=patience), resolve_scene("gravel"), 0, render,
                lambda cams, spp, seed: bg, lambda values, cams: np.ones((1, 2, 2)), 0.05, 0.0)
    return h, None


def test_the_best_scoring_iterate_is_kept_and_patience_counts_checks_without_a_better_one():
    errors = [0.3, 0.1, 0.2, 0.05, 0.15, 0.2]
    h, _ = scripted(errors, patience=2)
    spent = []
    for k in range(len(errors)):
        rec = h.check({"x": np.array([k])}, 1 if k < 4 else 2, k, float(k))
        spent.append(h.patience_spent())
        assert rec["best"] == (k in (0, 1, 3))
    assert int(h.best["x"][0]) == 3 and h.best_check["iteration"] == 3
    assert spent == [False, False, False, False, False, True]
    mses = [c["mse"] for c in h.checks]
    assert np.argsort(mses, kind="stable").tolist() == np.argsort(errors, kind="stable").tolist()
    s = h.summary()
    assert s["chosen"]["iteration"] == 3 and len(s["checks"]) == 6 and s["views"] == 1
    # the checkpoint state restores the same choice
    h2, _ = scripted(errors, patience=2)
    h2.load_state(h.state())
    assert int(h2.best["x"][0]) == 3 and h2.best_check == h.best_check and h2.patience_spent()
    assert h.due(0, False) and h.due(7, False) and scripted(errors, every=5)[0].due(5, False)
    assert not scripted(errors, every=5)[0].due(7, False) and scripted(errors, every=5)[0].due(7, True)


def test_a_stage_loop_stops_when_patience_is_spent_and_counts_the_checks_seconds():
    """run._loop with a scripted stage: Stage 1 ends after `patience` checks without a better iterate, every check's
    seconds land in the stage clock and the log record (`seconds_holdout`, the first with the start's check)."""
    import io

    from optimizer.optimise.run import _loop, stage_seconds

    errors = [0.3, 0.1, 0.2, 0.25, 0.3, 0.0, 0.0]
    h, _ = scripted(errors, patience=2)

    class Stage:
        STAGE = 1
        total_iterations = 6

        def __init__(self):
            self.iteration, self.elapsed, self.stop_requested = 0, 0.0, False

        def step(self):
            self.iteration += 1
            self.elapsed += 1.0
            return {"iteration": self.iteration, "stage": 1, "loss": 0.0, "loss_photo": 0.0, "seconds": 1.0,
                    "nonfinite_grads": 0}

        def done(self):
            return self.stop_requested or self.iteration >= self.total_iterations

        def current_values(self):
            return {"x": np.array([self.iteration])}

    st, history = Stage(), []
    _loop(st, "stage 1", False, io.StringIO(), history, lambda s: None, 100, None, h, {"offset": 0.0})
    assert st.iteration == 3  # checks 0 (0.3), 1 (0.1 best), 2, 3 -> two without a better one
    assert int(h.best["x"][0]) == 1
    assert all("seconds_holdout" in r and "holdout_mse" in r for r in history)
    assert st.elapsed == pytest.approx(3.0 + h.seconds)
    assert stage_seconds(history, 1) == pytest.approx(3.0 + h.seconds)


# --- end to end ---------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def held(tmp_path_factory):
    out = tmp_path_factory.mktemp("holdout") / "run"
    assert main(["optimize", "gravel", "--out", str(out), *TINY, "--iterations", "6", "--stage2-iterations", "2",
                 "--holdout-views", "2", "--holdout-every", "2", "--holdout-spp", "4", "--snapshot-every", "1"]) == 0
    return out


def test_the_result_is_the_chosen_iterate(held):
    """summary.json lists a check at Stage 1's start, every 2 iterations and each stage's end; the chosen one has
    the lowest score; the run's maps (maps/*.npy) are that iterate's parameters (its snapshot), and
    snapshots/result.npz holds them with the run's total seconds."""
    s = json.loads((held / "summary.json").read_text())
    h = s["holdout"]
    where = [(c["stage"], c["iteration"]) for c in h["checks"]]
    assert where == [(1, 0), (1, 2), (1, 4), (1, 6), (2, 2)]
    best = min(h["checks"], key=lambda c: c["mse"])
    assert (h["chosen"]["stage"], h["chosen"]["iteration"]) == (best["stage"], best["iteration"])
    assert all(c["psnr"] == pytest.approx(-10 * math.log10(c["mse"])) for c in h["checks"])
    snap = np.load(held / "snapshots" / f"s{best['stage']}_{best['iteration']:04d}.npz")
    res = np.load(held / "snapshots" / "result.npz")
    for k in ("albedo", "metallic", "transmittance", "displacement", "translation", "rotation"):
        np.testing.assert_array_equal(res[k], snap[k])
    np.testing.assert_array_equal(np.load(held / "maps" / "albedo.npy"), snap["albedo"])
    np.testing.assert_array_equal(np.load(held / "maps" / "transmittance.npy"), snap["transmittance"])
    assert (int(res["stage"]), int(res["iteration"])) == (best["stage"], best["iteration"])
    # the checks' seconds are part of the run's seconds
    log = [json.loads(x) for x in (held / "log.jsonl").read_text().splitlines()]
    hold_s = sum(r.get("seconds_holdout", 0.0) for r in log)
    assert hold_s == pytest.approx(h["seconds"], rel=1e-6) and hold_s > 0
    assert float(res["seconds"]) == pytest.approx(s["seconds_optimisation"], rel=1e-6)
    assert s["seconds_optimisation"] >= s["seconds_warm_start"] + hold_s


def test_a_resumed_run_chooses_what_an_uninterrupted_one_does(tmp_path):
    """A run "killed" after its checkpoint at iteration 4 (a 4-iteration run; --iterations is resumable) and resumed
    to 6 makes the same checks with the same scores and chooses the same iterate as an uninterrupted 6-iteration
    run (one thread: bit-exact); the held-out state travels in the checkpoint."""
    args = [*TINY, "--stages", "1", "--holdout-views", "2", "--holdout-every", "2", "--holdout-spp", "4",
            "--checkpoint-every", "4"]
    full, resumed = tmp_path / "full", tmp_path / "resumed"
    assert main(["optimize", "gravel", "--out", str(full), *args, "--iterations", "6"]) == 0
    assert main(["optimize", "gravel", "--out", str(resumed), *args, "--iterations", "4"]) == 0
    assert "holdout/checks" in np.load(resumed / "checkpoint.npz").files
    assert main(["optimize", "gravel", "--out", str(resumed), *args, "--iterations", "6", "--resume"]) == 0
    a = json.loads((full / "summary.json").read_text())["holdout"]
    b = json.loads((resumed / "summary.json").read_text())["holdout"]
    assert [(c["iteration"], c["mse"]) for c in b["checks"]] == [(c["iteration"], c["mse"]) for c in a["checks"]]
    assert b["chosen"]["iteration"] == a["chosen"]["iteration"]
    np.testing.assert_array_equal(np.load(resumed / "maps" / "albedo.npy"), np.load(full / "maps" / "albedo.npy"))


def test_holdout_off_keeps_the_last_iterate(tmp_path):
    """--holdout-views 0 (the paper preset's setting): no checks, no `holdout` in the summary, the maps are the
    last iterate's."""
    out = tmp_path / "off"
    assert main(["optimize", "gravel", "--out", str(out), *TINY, "--iterations", "3", "--stages", "1",
                 "--holdout-views", "0", "--snapshot-every", "1"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["holdout"] is None
    last = np.load(out / "snapshots" / "s1_0003.npz")
    np.testing.assert_array_equal(np.load(out / "maps" / "albedo.npy"), last["albedo"])
    log = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    assert not any("seconds_holdout" in r for r in log)


@pytest.mark.parametrize("flags, message", [
    (["--holdout-views", "-1"], "--holdout-views: must be an integer in [0, "),
    (["--holdout-every", "0"], "--holdout-every: must be an integer in [1, "),
    (["--holdout-spp", "0"], "--holdout-spp: must be an integer in [1, "),
    (["--holdout-views", "0", "--patience", "2"], "--patience needs held-out views"),
    (["--method", "mean", "--holdout-views", "2"], "--holdout-views does not apply to --method mean"),
])
def test_bad_holdout_flags_are_one_line_errors(tmp_path, capsys, flags, message):
    assert main(["optimize", "gravel", "--out", str(tmp_path / "x"), "--quiet", *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_presets_say_whether_the_holdout_picks_the_result():
    from optimizer.optimise.presets import PRESETS

    assert PRESETS["paper"].holdout == {}
    assert PRESETS["fast"].holdout["views"] >= 1


def test_nonfinite_held_out_renders_score_finite_and_never_win_by_accident():
    """Hard case: a held-out render with NaN and +-Inf pixels (a NaN-prone BSDF lobe, a firefly). sRGB encoding reads
    NaN as black and clips Inf to white (as an 8-bit image would), so the score stays finite; an iterate whose render
    is all NaN scores as a black object and loses to a close match."""
    from optimizer.scenes.builtin_scenes import resolve_scene

    bg = np.full((1, 2, 2, 3), 0.2, np.float32)

    def render(values, cams, spp, seed):
        kind = int(values["x"][0])
        img = bg.copy()
        if kind == 0:
            img[0, 0, 0] = [np.nan, np.inf, -np.inf]
        elif kind == 1:
            img[:] = np.nan
        else:
            img[0, 0, 0] += 0.01
        return img

    h = Holdout(HoldoutSettings(views=1), resolve_scene("gravel"), 0, render, lambda cams, spp, seed: bg,
                lambda values, cams: np.ones((1, 2, 2)), 0.05, 0.0)
    recs = [h.check({"x": np.array([k])}, 1, k, 0.0) for k in range(3)]
    assert all(math.isfinite(r["mse"]) and math.isfinite(r["psnr"]) for r in recs)
    assert int(h.best["x"][0]) == 2


def test_iterate_average_is_the_result_and_survives_a_resume(tmp_path, capsys):
    """--average 0.8: the maps written are the moving average of the iterates (not the last iterate), a run
    resumed from its checkpoint at 4 ends bit-exact with an uninterrupted 6-iteration run (the average travels in
    the checkpoint), the spec records the decay; a decay outside [0, 0.999] is a one-line error."""
    args = [*TINY, "--stages", "1", "--holdout-views", "0", "--checkpoint-every", "4", "--average", "0.8"]
    full, resumed, plain = tmp_path / "full", tmp_path / "resumed", tmp_path / "plain"
    assert main(["optimize", "gravel", "--out", str(full), *args, "--iterations", "6"]) == 0
    assert main(["optimize", "gravel", "--out", str(resumed), *args, "--iterations", "4"]) == 0
    assert "avg/albedo" in np.load(resumed / "checkpoint.npz").files
    assert main(["optimize", "gravel", "--out", str(resumed), *args, "--iterations", "6", "--resume"]) == 0
    np.testing.assert_array_equal(np.load(resumed / "maps" / "albedo.npy"), np.load(full / "maps" / "albedo.npy"))
    assert "average = 0.8" in (full / "config.toml").read_text()
    assert main(["optimize", "gravel", "--out", str(plain), *args[:-2], "--iterations", "6"]) == 0
    a, p = np.load(full / "maps" / "albedo.npy"), np.load(plain / "maps" / "albedo.npy")
    assert not np.array_equal(a, p) and np.abs(a - p).max() < 0.1  # same descent, averaged read-out
    capsys.readouterr()
    assert main(["optimize", "gravel", "--out", str(tmp_path / "bad"), "--quiet", "--average", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--average: must be a number in [0, 0.999], got '1'" in err and len(err.splitlines()) == 1


def test_parameters_scored_before_are_not_rendered_again():
    """score() of the same arrays returns the same score without rendering (Stage 1's first check of the start the
    start search scored); other arrays, or another dtype, render again."""
    from optimizer.scenes.builtin_scenes import resolve_scene

    calls = []
    bg = np.full((1, 2, 2, 3), 0.2, np.float32)

    def render(values, cams, spp, seed):
        calls.append(seed)
        return bg + float(values["x"][0])

    h = Holdout(HoldoutSettings(views=1), resolve_scene("gravel"), 0, render, lambda cams, spp, seed: bg,
                lambda values, cams: np.ones((1, 2, 2)), 0.05, 0.0)
    a = {"x": np.array([0.05], np.float32)}
    first = h.score(a)
    assert len(calls) == 2 and first[0] > 0
    assert h.score({"x": a["x"].copy()}) == first and len(calls) == 2
    h.score({"x": np.array([0.06], np.float32)})
    h.score({"x": np.array([0.05], np.float64)})
    assert len(calls) == 6
