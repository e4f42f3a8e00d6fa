"""The simulated observer (evaluation/observer.py): property tests of the search model on synthetic stimuli."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from camo_base.tables import write_parquet
from evaluation.observer import (Cells, ObserverConfig, diffusion_decision, diffusion_parameters, evidence_maps,
                                 ground_segments, make_cells, predict_stimulus, predicted_table, simulate_search,
                                 sky_map, srgb_to_lab)
from camo_base.errors import CamoError

N = 256


def unit_1f(rng: np.random.Generator, n: int, power: float = 1.0) -> np.ndarray:
    """``(n, n)`` noise with amplitude spectrum 1/f^``power`` (1: a natural ground's), mean 0, standard deviation 1."""
    f = np.fft.fftfreq(n)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    fr[0, 0] = 1.0
    tex = np.real(np.fft.ifft2((rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))) / fr**power))
    return (tex - tex.mean()) / tex.std()


def grass(seed: int = 0, n: int = N) -> np.ndarray:
    """A green 1/f texture with pixel noise, sRGB (n, n, 3) float32: a stand-in for the meadow's ground."""
    rng = np.random.default_rng(seed)
    t = 0.5 + 0.12 * unit_1f(rng, n) + 0.06 * rng.normal(size=(n, n))
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


def shadowed(img: np.ndarray, region: np.ndarray, factor: float = 0.35) -> np.ndarray:
    """A cast shadow: the linear radiance of ``region`` scaled by ``factor`` (the light that reaches the ground)."""
    from camo_base.imaging import linear_to_srgb, srgb_to_linear

    lin = srgb_to_linear(img)
    lin[region] *= factor
    return np.clip(linear_to_srgb(lin), 0, 1).astype(np.float32)


def ellipse(cx: float, cy: float, ax: float, ay: float, n: int = N) -> np.ndarray:
    yy, xx = np.mgrid[0:n, 0:n]
    return ((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2 < 1.0


def test_visible_object_is_found_fast():
    bg = grass()
    mask = disc(70, 170, 14)  # 4.7 deg from the centre at 16 deg per image height
    p = predict_stimulus(with_object(bg, mask, 0.0), mask, n=200, seed=1, background=bg)
    assert p.p_found >= 0.97 and p.p_timeout == 0
    assert np.median(p.result.fixations) <= 3 and p.result.fixations.max() <= 5
    # the paper's Transparent: 1.79 s mean, 1.86 s median (human); the human range for visible objects 1.5-6 s
    assert 1.5 <= float(p.rt_found_s.mean()) <= 3.0 and 1.5 <= float(np.median(p.rt_found_s)) <= 3.0
    assert p.object_evidence > 2 * ObserverConfig().criterion  # far above the verification criterion


def test_first_fixation_find_time_is_fixation_decision_verification_and_fitts():
    """A large red disc at the centre is verified at the first fixation after onset (the onset fixation only
    plans the first saccade): rt = 2 fixations + decision time + verification dwell + Fitts' law from the centre
    to the click; the one-shot rule ("threshold") has no decision time, the diffusion the analytic mean
    ``(a / mu) tanh(a mu)`` of the fixated cell's drift."""
    bg = grass(2)
    mask = disc(128, 128, 40)
    img = with_object(bg, mask, 0.0)
    for decision in ("threshold", "diffusion"):
        cfg = ObserverConfig(decision=decision)
        cells = make_cells(img, cfg, background=bg)
        res = simulate_search(img, n=400, seed=0, config=cfg, mask=mask, cells=cells)
        assert res.found.all() and (res.fixations == 2).all()
        d = np.hypot((res.click_x + 0.5) / N * cells.width_deg - cells.width_deg / 2,
                     (res.click_y + 0.5) / N * cells.height_deg - cells.height_deg / 2)
        rest = 2 * cfg.fixation_s + cfg.verify_s + cfg.fitts_a_s + cfg.fitts_b_s * np.log2(d / cfg.fitts_width_deg + 1)
        if decision == "threshold":
            np.testing.assert_allclose(res.rt_s, rest, rtol=1e-12)
        else:
            a, k = diffusion_parameters(cfg)
            mu = k * (cells.v.max() - cfg.criterion)  # the object's cell: the largest evidence
            dt = res.rt_s - rest
            assert (dt > 0).all()
            assert abs(dt.mean() - a / mu * math.tanh(a * mu)) < 0.15 * a / mu + 0.005


@pytest.mark.parametrize("drift", [0.0, 0.5, 2.0, -4.0, 12.0])
def test_diffusion_decision_matches_the_analytic_first_passage(drift):
    """The sampled decision against the first passage of a Wiener process with drift between +-a (Ratcliff 1978;
    Bogacz et al. 2006, eqs. 5-6): P(upper) = 1 / (1 + exp(-2 a mu)), mean time (a / mu) tanh(a mu), a^2 at
    mu = 0."""
    a, n = 0.7, 40_000
    up, t = diffusion_decision(np.full(n, drift), a, np.random.default_rng(1))
    p = 1.0 / (1.0 + math.exp(-2 * a * drift))
    mean_t = a * a if drift == 0 else a / drift * math.tanh(a * drift)
    assert abs(up.mean() - p) < 4 * math.sqrt(p * (1 - p) / n) + 1e-3
    assert abs(t.mean() - mean_t) < 0.03 * mean_t + 0.002
    assert (t > 0).all()


def test_weaker_evidence_gives_longer_finds_and_more_misses():
    """A grid of background cells with evidence one spread below the criterion and one object cell, guided to
    first, with evidence x above it (x = 4 ... 0): as the evidence weakens, the decision at the object slows
    (mean time of finds rises) and fails more often (found falls; misses -- background places verified later --
    rise), monotonically. With the one-shot rule the time of a find does not depend on the evidence."""
    cfg = ObserverConfig()
    yy, xx = np.mgrid[0:16, 0:16]
    pos = np.stack([(xx.ravel() + 0.5), (yy.ravel() + 0.5)], -1) * 1.0  # 1 deg cells over a 16 deg image
    obj = 16 * 4 + 12  # a cell 4.5 deg right and 4 deg above the centre
    mask = np.zeros((160, 160), bool)
    click = (pos * 10).astype(int)
    mask[click[obj, 1], click[obj, 0]] = True
    found, miss, t_found, t_thr = [], [], [], []
    for x in (4.0, 2.0, 1.0, 0.5, 0.0):
        v = np.full(256, cfg.criterion - 1.0)
        v[obj] = cfg.criterion + x
        g = np.zeros(256)
        g[obj] = 8.0  # guided there first
        cells = Cells(g, v, pos, click, 16.0, 16.0, (160, 160))
        r = simulate_search(None, n=3000, seed=7, config=cfg, mask=mask, cells=cells)
        found.append(r.found.mean())
        miss.append((r.clicked & ~r.found).mean())
        first = r.found & (r.fixations == 2)  # found at the first check
        t_found.append(r.rt_s[first].mean())
        thr = simulate_search(None, n=3000, seed=7, config=ObserverConfig(decision="threshold"), mask=mask,
                              cells=cells)
        t_thr.append(thr.rt_s[thr.found & (thr.fixations == 2)].mean())
    assert all(b < a for a, b in zip(found, found[1:])), found
    assert all(b > a for a, b in zip(miss, miss[1:])), miss
    assert all(b > a for a, b in zip(t_found, t_found[1:])), t_found
    assert t_found[-1] - t_found[0] > 0.25  # near the criterion the decision takes ~ decision_time_s
    assert max(t_thr) - min(t_thr) < 1e-9  # the one-shot rule: no evidence in the time
    assert found[0] > 0.95 and 0.4 < found[-1] < 0.6, found  # at the criterion: about a coin flip at the first check


def test_hiding_the_object_more_never_helps_the_observer():
    """The object mixed ever more into its background: its evidence falls strictly, the share found never rises
    and the time to find (non-finds at the limit) never falls, from found at once to (almost) never found; the
    misses that remain come from false verifications."""
    bg = grass(3)
    mask = disc(190, 80, 16)
    alphas = (0.0, 0.6, 0.8, 0.86, 0.9, 0.94, 1.0)
    preds = [predict_stimulus(with_object(bg, mask, a), mask, n=300, seed=5, background=bg) for a in alphas]
    times = [float(p.time_to_find_s.mean()) for p in preds]
    found = [p.p_found for p in preds]
    ev = [p.object_evidence for p in preds]
    assert all(b < a for a, b in zip(ev[:-1], ev[1:-1])), ev  # (the last has no object: background evidence)
    assert not ev[-1] >= ev[-3]  # lower, or NaN: no verified click would land on the invisible object
    assert all(b <= a + 0.02 for a, b in zip(found, found[1:])), found  # common random numbers; 300 trials
    assert all(b >= a - 0.3 for a, b in zip(times, times[1:])), times
    assert found[0] >= 0.97 and times[0] < 2.0
    assert found[-1] <= 0.03 and times[-1] > 35.0
    # not found = a false verification (a click elsewhere) or a timeout; misses rise as the evidence falls
    assert preds[0].p_miss <= 0.02 and preds[-1].p_miss + preds[-1].p_timeout >= 0.97


def test_a_shadow_alone_is_not_clicked_as_the_object():
    """A cast shadow (the ground's light scaled by 0.35) with no object: the observer does not take it for the
    object -- its clicks land in it no more often than its share of the image would give by chance. A red-tinted
    patch of the same shape is found."""
    bg = grass(12)
    region = ellipse(100, 160, 40, 16)
    shadow_only = simulate_search(shadowed(bg, region), n=300, seed=2, mask=region, background=bg)
    assert shadow_only.found.mean() <= max(0.05, 3 * region.mean())
    m = evidence_maps(shadowed(bg, region), background=bg)
    assert float(m.shadow[::4, ::4].max()) > 1.0  # it is seen as a shadow ...
    tinted = predict_stimulus(with_object(bg, region, 0.7), region, n=300, seed=2, background=bg)
    assert tinted.p_found >= 0.95  # ... while an object of the same shape and place is found


def test_an_object_with_its_shadow_is_clicked_on_the_object():
    bg = grass(13)
    obj = disc(150, 110, 14)
    shadow = ellipse(175, 128, 26, 10) & ~obj  # cast to the lower right, touching the object
    img = with_object(shadowed(bg, shadow), obj, 0.75)
    res = simulate_search(img, n=300, seed=4, mask=obj, background=bg)
    on_shadow = shadow[np.maximum(res.click_y, 0), np.maximum(res.click_x, 0)] & res.clicked
    assert res.found.mean() >= 0.9
    assert on_shadow.mean() <= 0.05


def test_an_attached_shadow_does_not_pull_the_click_off_its_object():
    """A faint, light body (a Mean-like object: the ground's texture with 15 % of a pale colour) with a dark cast
    shadow (20 % of the light) hugging its right side and running down past its base -- taller than wide, so the
    shape cue reads it as upright, and darker than the body is distinct: the occluded scene's torus. Without the
    cast-shadow texture test (``cast_shadow="none"``) the shadow carries more object evidence than the body and
    every click lands on it (the test can fail); with it (the default) the shadow keeps the ground's texture, so it
    carries less object evidence than the body, and the body is clicked."""
    bg = grass(41)
    obj = ellipse(120, 130, 13, 24)
    sh = (ellipse(134, 140, 10, 22) | ellipse(140, 154, 14, 9)) & ~obj
    img = shadowed(bg, sh, 0.2)
    img[obj] = 0.85 * bg[obj] + 0.15 * np.array([0.75, 0.7, 0.6], np.float32)
    out = {}
    for cast in ("none", "texture"):
        cfg = ObserverConfig(cast_shadow=cast)
        m = evidence_maps(img, cfg, bg)
        o_obj, o_sh = (float(m.obj[_feature_mask(r, m.obj.shape)].max()) for r in (obj, sh))
        res = simulate_search(img, n=300, seed=4, config=cfg, mask=obj, background=bg)
        on_sh = sh[np.maximum(res.click_y, 0), np.maximum(res.click_x, 0)] & res.clicked
        out[cast] = (o_obj, o_sh, float(res.found.mean()), float(on_sh.mean()))
    # measured: none O 2.98 body / 3.79 shadow, found 0 %, on the shadow 100 %; texture O 2.98 / 2.73, found 100 %
    (oo0, os0, f0, s0), (oo1, os1, f1, s1) = out["none"], out["texture"]
    assert os0 > oo0 and s0 >= 0.5 and f0 <= 0.5, out  # the failure exists without the test
    assert os1 < oo1 and abs(oo1 - oo0) < 0.1, out  # the shadow loses its evidence, the body keeps its own
    assert f1 >= 0.95 and s1 <= 0.02, out


def test_cast_shadow_map_reads_texture_kept_under_a_darkening():
    """:func:`cast_shadow_map`: the grass darkened to 30 % of its light (texture kept) is shadow (>= 0.7 inside, >= 0.6
    with pixel noise of its own);
    the same darkening painted flat (its mean colour: no texture) or the grass of another seed darkened the same
    (a textured surface that is not this ground's) is not (<= 0.2); a light change of 80 % is not (0); an
    untextured ground says nothing (0)."""
    from evaluation.observer import _log_image, _resample, cast_shadow_map

    cfg = ObserverConfig()
    bg = grass(5)
    region = ellipse(128, 128, 50, 40)
    core = ellipse(128, 128, 34, 26)
    flat_bg = np.full_like(bg, 0.4)

    def cast_of(img, ref):
        s = cfg.display_deg * cfg.feature_px_per_deg / N
        c = cast_shadow_map(_log_image(_resample(img, s)), _log_image(_resample(ref, s)),
                            cfg.centre_sigmas_deg[0] * cfg.feature_px_per_deg, cfg)
        return float(np.median(c[_feature_mask(core, c.shape)]))

    assert cast_of(shadowed(bg, region, 0.3), bg) >= 0.7
    # the renders share their sampler's random numbers (common random numbers); with pixel noise of its own in
    # the image (half the texture's contrast, independent of the object-free view's) the shadow still reads
    # (measured 0.81)
    rng = np.random.default_rng(99)
    noisy = np.clip(bg + (0.06 * rng.normal(size=bg.shape[:2]))[..., None] * np.array([0.35, 0.75, 0.25]), 0, 1)
    assert cast_of(shadowed(noisy.astype(np.float32), region, 0.3), bg) >= 0.6
    flat = shadowed(bg, region, 0.3)
    flat[region] = flat[region].mean(0)
    other = bg.copy()
    other[region] = shadowed(grass(6), region, 0.3)[region]
    assert cast_of(flat, bg) <= 0.2 and cast_of(other, bg) <= 0.2
    assert cast_of(shadowed(bg, region, 0.8), bg) == 0.0
    assert cast_of(shadowed(flat_bg, region, 0.3), flat_bg) == 0.0


def tinted(img: np.ndarray, region: np.ndarray, tint) -> np.ndarray:
    """``region``'s linear radiance scaled per channel by ``tint`` (R, G, B): a see-through surface of that
    transmittance in front of the ground (the ground's texture kept in place), or a cast shadow when the three are
    equal (or bluer)."""
    from camo_base.imaging import linear_to_srgb, srgb_to_linear

    lin = srgb_to_linear(img)
    lin[region] *= np.asarray(tint, np.float32)
    return np.clip(linear_to_srgb(lin), 0, 1).astype(np.float32)


@pytest.mark.parametrize("tint", [(0.55, 0.30, 0.10), (0.60, 0.20, 0.20)])
def test_a_tinted_see_through_object_is_not_taken_for_a_shadow(tint):
    """An amber or red glass disc in front of the grass: darker than the ground there by a cast shadow's factor
    (its green channel keeps 20-30 % of the light) and showing the ground's texture in place, so the texture test
    alone (``cast_shadow="texture"``) reads it as ground in shadow and discounts it -- plainly coloured, it is never
    found (measured 0 %; the failure the chromaticity test is for). With ``cast_shadow="texture_chroma"`` the
    change of chromaticity towards red / yellow is no shadow's (:func:`shadow_chroma_kept`): the disc keeps its
    object evidence and is found."""
    from evaluation.observer import shadow_chroma_kept  # noqa: F401  (the cue under test)

    bg = grass(21)
    obj = disc(90, 150, 16)
    img = tinted(bg, obj, tint)
    out = {}
    for cast in ("texture", "texture_chroma"):
        cfg = ObserverConfig(cast_shadow=cast)
        m = evidence_maps(img, cfg, bg)
        fm = _feature_mask(obj, m.obj.shape)
        p = predict_stimulus(img, obj, n=200, seed=3, config=cfg, background=bg)
        out[cast] = (float(np.median(m.cast[fm])), p.p_found)
    assert out["texture"][0] >= 0.7 and out["texture"][1] <= 0.05, out  # the failure exists without the cue
    assert out["texture_chroma"][0] <= 0.05 and out["texture_chroma"][1] >= 0.95, out


@pytest.mark.parametrize("tint", [(0.35, 0.35, 0.35), (0.30, 0.35, 0.45)])
def test_chroma_test_keeps_a_grey_or_bluish_shadow_a_shadow(tint):
    """A cast shadow alone -- the ground's light scaled by 0.35, or bluer (daylight's sky-lit shade) -- is ground in
    shadow to the chromaticity test as to the texture test (the same cast-shadow map) and is not clicked as the
    object (clicks in it no more often than its share of the image gives); the same shadow beside a red-tinted
    object: the object is found and the shadow not clicked."""
    from evaluation.observer import _log_image, _resample, shadow_chroma_kept

    bg = grass(12)
    region = ellipse(100, 160, 40, 16)
    img = tinted(bg, region, tint)
    cfg = ObserverConfig(cast_shadow="texture_chroma")
    s = cfg.display_deg * cfg.feature_px_per_deg / N
    kept = shadow_chroma_kept(_log_image(_resample(img, s)), _log_image(_resample(bg, s)), 4.0, cfg.internal_noise)
    assert float(np.median(kept[_feature_mask(region, kept.shape)])) >= 0.95
    m_tex = evidence_maps(img, ObserverConfig(), bg)
    m_chr = evidence_maps(img, cfg, bg)
    np.testing.assert_allclose(m_chr.cast, m_tex.cast, atol=0.02)
    alone = simulate_search(img, n=300, seed=2, config=cfg, mask=region, background=bg)
    assert alone.found.mean() <= max(0.05, 3 * region.mean())
    obj = disc(150, 110, 14)
    shadow = ellipse(175, 128, 26, 10) & ~obj  # cast to the lower right, touching the object
    both = with_object(tinted(grass(13), shadow, tint), obj, 0.75)
    res = simulate_search(both, n=300, seed=4, config=cfg, mask=obj, background=grass(13))
    on_shadow = shadow[np.maximum(res.click_y, 0), np.maximum(res.click_x, 0)] & res.clicked
    assert res.found.mean() >= 0.9 and on_shadow.mean() <= 0.05


def fine_grass(seed: int = 0, n: int = N) -> np.ndarray:
    """A green texture with stationary statistics at the object's scale (spectrum 1/f^0.5: no object-sized
    blotches that would act as distractors of their own)."""
    t = 0.5 + 0.12 * unit_1f(np.random.default_rng(seed), n, power=0.5)
    return np.clip(np.stack([0.35 * t, 0.75 * t, 0.25 * t], -1), 0, 1).astype(np.float32)


@pytest.mark.parametrize("frame", ["none", "lines"])
@pytest.mark.parametrize("alpha, corners", [(0.8, True), (0.86, False)])
def test_no_position_bias(alpha, corners, frame):
    """The same object pasted on its own background at the centre, in each quadrant's centre and (for the more
    visible object) in two corners: found at rates within sampling error of the centre's (two-proportion z <
    2.5). (docs/observer.md: the fainter object 14 px from two borders is found 94 % vs 100 %.)"""
    bg = fine_grass(11)
    rates, n = [], 300
    places = ((128, 128), (64, 64), (192, 64), (64, 192), (192, 192)) + (((30, 30), (226, 226)) if corners else ())
    for cx, cy in places:
        mask = disc(cx, cy, 16)
        rates.append(predict_stimulus(with_object(bg, mask, alpha), mask, n=n, seed=3, background=bg,
                                      config=ObserverConfig(frame=frame)).p_found)
    for r in rates[1:]:
        pooled = (rates[0] + r) / 2
        se = math.sqrt(max(pooled * (1 - pooled), 1.0 / n) * 2 / n)
        assert abs(rates[0] - r) / se < 2.5, rates


def test_without_the_object_clicks_are_the_same_whatever_the_mask():
    bg = grass(4)
    rng = np.random.default_rng(0)
    rates, shares = [], []
    clicks = None
    cells = make_cells(bg, background=bg)
    for k in range(12):
        cx, cy = rng.uniform(30, N - 30, 2)
        mask = disc(cx, cy, 14)
        res = simulate_search(bg, n=100, seed=9, mask=mask, cells=cells)
        # same image and seed, another mask: the observer behaves identically (it never sees the mask)
        c = (res.click_x.copy(), res.click_y.copy(), res.rt_s.copy())
        if clicks is not None:
            for a, b in zip(clicks, c):
                np.testing.assert_array_equal(a, b)
        clicks = c
        rates.append(res.found.mean())
        shares.append(mask.mean())
    assert np.mean(rates) <= 3 * np.mean(shares) + 0.03  # found only by chance
    # an image without any object: the search runs long (timeouts or late false verifications)
    assert np.median(res.rt_s) > 5.0


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
    with pytest.raises(CamoError, match=">= 0"):
        simulate_search(img, config=ObserverConfig(shadow_gain=-1))
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
    # every method found (confusion ties): the mean time of finds orders them (found later = better hidden), as
    # Table I's second measure; equal times stay ties; a label never found ranks above every label found
    from evaluation.report import observer_rank

    found = views.assign(p_found=1.0, mean_time_found_s=[4.0, 2.5, 1.6])
    taus, dis = observer_agreement(df, found)
    by = {x["metric"]: x["tau"] for x in taus}
    assert by["psnr"] == pytest.approx(1.0) and by["lpips_proxy"] == pytest.approx(1 / 3)
    tied = views.assign(p_found=1.0, mean_time_found_s=2.0)
    assert {x["tau"] for x in observer_agreement(df, tied)[0]} == {0.0}
    two_runs = pd.DataFrame({"scene": ["s"] * 5, "run": ["a", "a", "b", "c", "c"], "label": list("AABCC"),
                             "p_found": [1.0, 1.0, 1.0, 0.0, 0.0], "mean_time_found_s": [3.0, 1.0, 2.5, np.nan, np.nan]})
    r = observer_rank(two_runs)
    assert r["C"] > r["B"] > r["A"]  # C never found; B (2.5 s) found later than A (mean of 3 and 1 s = 2 s)


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
    assert p.p_found >= 0.9
    assert "saliency_model_sha256" in cfg.to_dict() and len(cfg.to_dict()["saliency_model_sha256"]) == 64
    # random tiny weights run too (any TorchScript map); bad files are one-line errors
    rnd = ObserverConfig(saliency_model=str(_tiny_net(tmp_path / "rnd.pt", weight_red=False)))
    assert np.isfinite(discriminability_map(img, rnd)).all()
    (tmp_path / "bad.pt").write_bytes(b"not a model")
    with pytest.raises(CamoError, match="not a TorchScript file"):
        discriminability_map(img, ObserverConfig(saliency_model=str(tmp_path / "bad.pt")))
    with pytest.raises(CamoError, match="file not found"):
        simulate_search(img, config=ObserverConfig(saliency_model=str(tmp_path / "missing.pt")))
    # the frame cue reads the image's lines, which the learned map replaces: refused, not silently ignored
    with pytest.raises(CamoError, match="frame 'lines'.*saliency_model"):
        simulate_search(img, config=ObserverConfig(saliency_model=str(tmp_path / "red.pt"), frame="lines"))




def test_simulated_section_of_the_report_reads_the_stimulus_predictions(tmp_path):
    import json

    from evaluation.report import simulated_section

    stim = tmp_path / "stim"
    (stim / "predicted_power").mkdir(parents=True)
    rows, trials = [], []
    for sid, method, pf, med in (("a0", "ours", 0.2, 5.0), ("a1", "ours", 0.2, 5.0), ("b0", "mean", 1.0, 1.1),
                                 ("b1", "mean", 1.0, 1.1), ("p0", "practice", 0.0, 1.0)):
        rows.append({"id": sid, "run": f"s-{method}", "scene": "s", "method": method, "ablation": "", "view": sid[1],
                     "practice": method == "practice", "p_found": pf, "p_miss": 0.0, "p_timeout": 1 - pf,
                     "median_time_found_s": med, "mean_time_found_s": med, "mean_time_all_s": 30.0,
                     "median_time_all_s": 30.0})
        for k in range(10):
            found = k < 10 * pf
            trials.append({"id": sid, "trial": k, "found": found, "rt_s": med if found else 40.0})
    write_parquet(pd.DataFrame(rows), stim / "predicted.parquet")
    write_parquet(pd.DataFrame(trials), stim / "predicted_trials.parquet")
    (stim / "predicted_config.json").write_text(json.dumps({"observer": {"display_deg": 16.0, "time_limit_s": 40.0},
                                                            "trials_per_stimulus": 10}))
    from PIL import Image

    Image.new("RGB", (8, 8)).save(stim / "predicted_power" / "power.png")
    df = pd.DataFrame({"region": ["crop"] * 4, "scene": ["s"] * 4, "run": ["s-ours"] * 2 + ["s-mean"] * 2,
                       "label": ["Ours"] * 2 + ["Mean [6]"] * 2, "_order": [(5, 0, "")] * 2 + [(0, 1, "")] * 2,
                       "method": ["ours"] * 2 + ["mean"] * 2, "view": [0, 1, 0, 1],
                       "psnr": [20.0, 20.0, 30.0, 30.0]})  # PSNR prefers Mean, the observer Ours
    for m in ("ssim", "lpips", "lpips_proxy", "sifid", "sifid_proxy", "dreamsim"):
        df[m] = np.nan
    out = tmp_path / "report"
    out.mkdir()
    md, ht = simulated_section(df, [stim], out)
    text = "\n".join(md)
    assert "| Ours | 80.0% |" in text and "| Mean [6] | 0.0% |" in text  # predicted confusion = 1 - p found
    assert "| 54.1% | 8.02 / 9.41 |" in text  # the paper's human Ours row beside it
    assert "practice" not in text.split("Easy stimuli")[0]  # practice stimuli are not in Table I
    assert "| s | PSNR↑ | Mean [6] | Ours | 30.00 / 20.00 | 0.0% / 80.0% |" in text
    assert (out / "plots" / "power_predicted_0.png").is_file() and "power curve" in text
    assert simulated_section(df, [], out) == ([], [])
    with pytest.raises(CamoError, match="no observer predictions"):
        simulated_section(df, [tmp_path / "nothing"], out)


def sky_scene(seed: int = 20, n: int = N) -> np.ndarray:
    """A smooth sky (a blue gradient with a bright, compact sun glow at the upper left) over the grass texture."""
    img = grass(seed, n)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    hor = int(0.4 * n)
    glow = np.exp(-((xx - 0.2 * n) ** 2 + (yy - 0.15 * n) ** 2) / (2 * (0.12 * n) ** 2))
    sky = np.stack([0.35 + 0.2 * yy / hor, 0.5 + 0.2 * yy / hor, 0.8 + 0.1 * yy / hor], -1)
    sky = np.clip(sky + 0.4 * glow[..., None] * np.array([1.0, 0.9, 0.6]), 0, 1)
    img[:hor] = sky[:hor]
    return img.astype(np.float32)


def test_the_sky_and_its_glow_are_no_candidates():
    """Objects rest on the ground: the sky (smooth, at the top) and the sun's glow in it are never verified; a
    top-down view of ground alone has no sky; the object on the grass is found."""
    from evaluation.observer import sky_map

    bg = sky_scene()
    m = evidence_maps(bg, background=bg)
    hor = int(0.4 * N) * m.sky.shape[0] // N
    assert m.sky[: hor - 2].mean() > 0.97 and m.sky[hor + 2:].mean() < 0.01
    assert not evidence_maps(grass(21), background=grass(21)).sky.any()
    glow = disc(0.2 * N, 0.15 * N, 0.15 * N)
    res = simulate_search(bg, n=200, seed=6, mask=glow, background=bg)
    assert res.found.mean() == 0.0 and res.clicked.mean() <= 0.25  # never on the glow; an empty scene mostly times out
    mask = disc(180, 190, 14)
    p = predict_stimulus(with_object(bg, mask, 0.3), mask, n=200, seed=6, background=bg)
    assert p.p_found >= 0.95 and np.median(p.rt_found_s) < 3.0
    assert not sky_map(np.zeros((40, 40, 3))).any()  # smooth from top to bottom: no ground, so no sky either



def _feature_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``mask`` (image pixels) sampled at the centres of the feature map's pixels."""
    h, w = shape
    ys = ((np.arange(h) + 0.5) * mask.shape[0] / h).astype(int)
    xs = ((np.arange(w) + 0.5) * mask.shape[1] / w).astype(int)
    return mask[np.ix_(ys, xs)]


def test_shadow_discount_scales_what_a_cast_shadow_leaves_as_object_evidence():
    """``shadow_discount`` (the "surround" reference): the object evidence O inside a pasted cast shadow falls as the
    discount rises (0: the full difference D; 1: nothing of its shadow-like part), while D and the shadow evidence
    do not change, and an object of the same shape (red-tinted) keeps its evidence whatever the discount. Without
    the shape cue, which would discount this flat region fully whatever ``shadow_discount`` says (tested below), and
    without the cast-shadow texture test (``cast_shadow="none"``), which does the same for a shadow that keeps the
    ground's texture (tested below)."""
    bg = grass(12)
    region = ellipse(100, 160, 40, 16)
    img = shadowed(bg, region)
    core = None
    o, d, sh = [], [], []
    for k in (0.0, 0.6, 1.0):
        m = evidence_maps(img, ObserverConfig(shadow_discount=k, shadow_shape="none", cast_shadow="none"),
                          background=bg)
        core = _feature_mask(ellipse(100, 160, 24, 8), m.obj.shape) if core is None else core
        o.append(float(m.obj[core].mean()))
        d.append(float(m.d[core].mean()))
        sh.append(float(m.shadow[core].mean()))
    assert d[0] == d[1] == d[2] and sh[0] == sh[1] == sh[2] and sh[0] > 1.0
    assert o[0] > o[1] + 1.0 > o[2] + 2.0, o
    tinted = with_object(bg, region, 0.7)
    v = [float(evidence_maps(tinted, ObserverConfig(shadow_discount=k, shadow_shape="none"),
                            background=bg).verify.max())
         for k in (0.0, 1.0)]
    assert v[1] > 0.9 * v[0] and v[1] > 2 * ObserverConfig().criterion, v


def test_shadow_reference_background_tells_an_object_in_the_shade_from_a_cast_shadow():
    """The ratio image with the object-free view (``shadow_reference="background"``): a bluish-grey
    object standing in the scene's own shade (the left half, in the background too) is darker than its pooled
    surround, so "surround" takes it for shadow and discounts it; it is no darker than the shaded ground at its
    place, so "background" keeps its evidence. A cast shadow pasted on the lit half (not in the background) is
    discounted fully and not clicked as the object. The references are compared without the shape cue; with it
    (the default) "surround" discounts that flat cast shadow fully as well. Both without the cast-shadow texture
    test (``cast_shadow="none"``), which discounts a pasted shadow whatever the reference (tested above)."""
    bg = grass(21)
    shade = np.zeros((N, N), bool)
    shade[:, :110] = True
    bg_shade = shadowed(bg, shade)
    obj = ellipse(85, 150, 14, 22)
    img = bg_shade.copy()
    img[obj] = np.clip(bg_shade[shade].mean(0) * np.array([0.8, 0.9, 1.4], np.float32), 0, 1)
    m_sur = evidence_maps(img, ObserverConfig(shadow_reference="surround", shadow_shape="none", cast_shadow="none"),
                          bg_shade)
    m_ref = evidence_maps(img, ObserverConfig(shadow_reference="background", shadow_shape="none", cast_shadow="none"),
                          bg_shade)
    core = _feature_mask(ellipse(85, 150, 8, 14), m_sur.shadow.shape)
    assert float(m_sur.shadow[core].mean()) > 0.8  # "surround": taken for shadow (measured 1.08)
    assert float(m_ref.shadow[core].mean()) < 0.2  # "background": not a shadow of the ground there (0.10)
    assert float(m_ref.obj[core].mean()) > float(m_sur.obj[core].mean()) + 0.5  # 1.50 vs 0.80
    cast = ellipse(190, 170, 36, 14)
    img2 = shadowed(bg_shade, cast)
    c = _feature_mask(ellipse(190, 170, 20, 7), m_sur.shadow.shape)
    surround = ObserverConfig(shadow_reference="surround", shadow_shape="none", cast_shadow="none")
    o_sur = float(evidence_maps(img2, surround, bg_shade).obj[c].mean())
    ratio = ObserverConfig(shadow_reference="background", shadow_shape="none", cast_shadow="none")
    m2 = evidence_maps(img2, ratio, bg_shade)
    assert float(m2.obj[c].mean()) < o_sur and float(m2.verify[c].max()) < 1.0  # 0.12 vs 0.27; V 0.12
    res = simulate_search(img2, n=300, seed=3, config=ratio, mask=cast, background=bg_shade)
    assert res.found.mean() <= max(0.05, 3 * cast.mean())
    o_lying = float(evidence_maps(img2, ObserverConfig(cast_shadow="none"), bg_shade).obj[c].mean())
    assert o_lying < 0.1 < o_sur  # measured 0.06 vs 0.27
    assert float(evidence_maps(img2, ObserverConfig(), bg_shade).obj[c].mean()) < 0.1  # the default (-0.10)


def test_shadow_settings_are_checked():
    with pytest.raises(CamoError, match="shadow_discount"):
        ObserverConfig(shadow_discount=1.5).validate()
    with pytest.raises(CamoError, match="shadow_reference"):
        ObserverConfig(shadow_reference="sky").validate()
    from study_site.simulate import parse_observer

    cfg = parse_observer("shadow_reference=background,shadow_discount=1")
    assert (cfg.shadow_reference, cfg.shadow_discount) == ("background", 1.0)
    with pytest.raises(CamoError,
                       match=r"^observer shadow_shape must be 'scales' or 'lying' or 'none', not 'round'$"):
        ObserverConfig(shadow_shape="round").validate()
    assert parse_observer("shadow_shape=none").shadow_shape == "none"
    with pytest.raises(CamoError, match="shadow_shape") as e:
        parse_observer("shadow_shape=1")
    assert "\n" not in str(e.value)


def test_lying_shape_reads_the_region_s_outline():
    """The shape score of :func:`lying_shape` on synthetic regions: a flat (wide) or diagonal region lies (+1), a
    tall one stands (-1), a disc or a region filling the window is neither (0), and the straight edge of a region
    larger than the window (a half-plane: a large shade's border) is no upright thing (|score| <= 0.15, measured
    0.14; 1 without the boundedness condition of ``SHAPE_THIN``)."""
    from evaluation.observer import lying_shape

    n = 160
    yy, xx = np.mgrid[0:n, 0:n]
    diag = (np.abs((xx - 80) * 0.6 - (yy - 80) * 0.8) < 5) & (np.abs((xx - 80) * 0.8 + (yy - 80) * 0.6) < 25)
    for region, want in ((ellipse(80, 80, 30, 8, n), 1.0), (diag, 1.0), (ellipse(80, 80, 8, 20, n), -1.0),
                         (ellipse(80, 80, 15, 15, n), 0.0), (np.ones((n, n), bool), 0.0)):
        k = lying_shape(region.astype(np.float64), 10.0)
        assert k[80, 80] == pytest.approx(want, abs=0.02), (want, k[80, 80])
        assert np.all((k >= -1) & (k <= 1))
    for edge in (xx < 80, xx < 80 + 0.3 * (yy - 80)):
        k = lying_shape(edge.astype(np.float64), 10.0)
        assert abs(k[80, 80]) <= 0.15 and abs(k[80, 76]) <= 0.05, (k[80, 80], k[80, 76])


def test_lying_shape_does_not_take_the_frame_for_an_outline():
    """The image's frame is not a region's outline. The tip of a flat cast shadow (40 x 12 px lying ellipse) that
    runs out of the right side of the frame shows a stub taller than wide (9 x 15 px): read with zeros beyond the
    frame it was fully upright (-1, the former rule); continued across the frame it lies (measured 1.0). An upright
    region the frame cuts through its axis is neither (measured 0.0: no longer upright, but not taken for a lying
    shadow either), and regions that stop short of the frame read as they did (upright 2 px from it, lying 4 px
    from it)."""
    from evaluation.observer import lying_shape

    n = 160
    tip = ellipse(190, 80, 40, 12, n)
    ys, xs = np.nonzero(tip)
    assert xs.max() - xs.min() + 1 < ys.max() - ys.min() + 1  # the stub in the frame is taller than wide
    assert lying_shape(tip.astype(np.float64), 10.0)[80, 157] > 0.9
    tall = ellipse(159.5, 80, 8, 20, n)
    assert abs(lying_shape(tall.astype(np.float64), 10.0)[80, 157]) < 0.05
    for region, at, want in ((ellipse(150, 80, 8, 20, n), (80, 150), -1.0), (ellipse(80, 150, 40, 6, n), (150, 80), 1.0)):
        assert lying_shape(region.astype(np.float64), 10.0)[at] == pytest.approx(want, abs=0.02)


def test_a_shadow_cut_by_the_frame_is_not_clicked_as_the_object():
    """A flat cast shadow (20 % of the light) whose tip alone is in the frame, at its right side (panorama's Ours
    view 1: the box's shadow leaving the frame), with the shape cue alone (``cast_shadow="none"``: the texture
    test cannot read a shadow whose render noise is its own, as there -- its map 0.09 at the frame's edge) carries
    no more object evidence than the same shadow inside the frame, and is not clicked as the object. With zeros
    beyond the frame (the former rule) the stub read upright: object evidence 2.11 on it (0.55 inside),
    verification 6.15 (the criterion is 6; 4.73 inside) and 82 % of the trials clicked it."""
    bg = grass(51)
    cfg = ObserverConfig(cast_shadow="none")
    out = {}
    for name, region in (("inside", ellipse(128, 160, 40, 12)), ("cut", ellipse(276, 160, 40, 12))):
        m = evidence_maps(shadowed(bg, region, 0.2), cfg, bg)
        f = _feature_mask(region, m.obj.shape)
        out[name] = (float(m.obj[f].mean()), float(m.verify[f].max()))
    # measured: inside O 0.54, V 4.63; cut O -0.25, V -0.79
    assert out["cut"][0] <= out["inside"][0] + 0.2 and out["cut"][1] <= out["inside"][1] + 0.5, out
    cut = ellipse(276, 160, 40, 12)
    res = simulate_search(shadowed(bg, cut, 0.2), n=300, seed=2, config=cfg, mask=cut, background=bg)
    assert res.found.mean() <= max(0.05, 3 * cut.mean()), res.found.mean()  # measured 0.0 (0.82 before)


def test_shadow_shape_tells_a_cast_shadow_from_an_object_of_the_same_colour():
    """A pasted cast shadow (the grass texture darkened to 35 % of its light: its grain goes on) lying flat on the
    ground, and an upright object patch painted the shadow's mean colour (same mean luminance and chromaticity, so
    the photometric shadow test takes both for shadow). With ``shadow_shape="lying"`` the shadow's object
    evidence O and verification evidence V fall and the object's V doubles, so the object's V passes the
    shadow's (it did not without the cue), and the shadow is never clicked as the object."""
    bg = grass(31)
    cast = ellipse(80, 190, 40, 10)
    obj = ellipse(180, 150, 12, 26)
    img = shadowed(bg, cast)
    img[obj] = img[cast].mean(0)
    np.testing.assert_allclose(img[obj].mean(0), img[cast].mean(0), atol=1e-6)
    out = {}
    for shape in ("none", "lying"):  # the shape cue alone (the cast-shadow texture test would discount it anyway)
        m = evidence_maps(img, ObserverConfig(shadow_shape=shape, cast_shadow="none"), bg)
        cs = _feature_mask(ellipse(80, 190, 28, 6), m.obj.shape)
        co = _feature_mask(ellipse(180, 150, 7, 18), m.obj.shape)
        out[shape] = (float(m.obj[cs].mean()), float(m.obj[co].mean()), float(m.verify[cs].max()),
                      float(m.verify[co].max()))
    (os0, oo0, vs0, vo0), (os1, oo1, vs1, vo1) = out["none"], out["lying"]
    # measured on the display's grid (16 px/deg): none O 0.53 / 0.74, V 2.13 / 1.70; lying O 0.19 / 0.75,
    # V 0.74 / 3.25 (on the former 10 px/deg: none O 0.54 / 0.67, V 2.17 / 1.68; lying O 0.19 / 0.73, V 0.85 / 3.54)
    assert vo0 < vs0  # without the shape cue the shadow is the stronger candidate
    assert os1 < os0 - 0.25 and os1 < 0.3 and oo1 > os1 + 0.4 and oo0 < os0 + 0.25  # O alone barely separated them
    assert vs1 < 1.2 and vo1 > 3.0 and vo1 > vs1 + 2.0 and vo1 > vo0 + 1.5
    res = simulate_search(img, n=200, seed=1, config=ObserverConfig(shadow_shape="lying", cast_shadow="none"),
                          mask=obj, background=bg)
    assert not (res.clicked & cast[np.maximum(res.click_y, 0), np.maximum(res.click_x, 0)]).any()


def test_a_glass_box_at_the_start_of_its_shadow_is_found_fast():
    """A refracting, glassy object as the built-in scenes render one (gravel's glass box): the ground seen through
    it flipped and displaced, keeping 55 % of the light with a skylight-blue tint (photometrically a shadow: the
    path tracer leaves the ground behind the glass in the sun's shadow) and sparse glints, 3.1 x 4.6 deg -- larger
    than the 1 deg window of the shape cue -- standing at the start of its own cast shadow (45 % of the light,
    lying). It is found at once, fast, and its shadow is never clicked. The shape cue reads it as upright only at
    a window of the object sizes the study shows (``shadow_shape="scales"``): within 1 deg the inside of the box
    fills the window and reads neither way (so ``"lying"`` discounted it as shadow-like: object evidence 35 vs 40
    here, 3.6 vs 10.7 on gravel's view 1, where it was never found)."""
    from evaluation.observer import _resample, lying_shape

    rng = np.random.default_rng(44)
    g = 0.42 + 0.06 * rng.normal(size=(N, N)) + 0.03 * np.kron(rng.normal(size=(N // 4, N // 4)), np.ones((4, 4)))
    bg = np.clip(np.stack([g, 0.9 * g, 0.75 * g], -1), 0, 1).astype(np.float32)  # fine brown gravel
    yy, xx = np.mgrid[0:N, 0:N]
    box = (xx >= 70) & (xx < 120) & (yy >= 110) & (yy < 184)
    cast = ellipse(150, 178, 45, 9) & ~box
    img = shadowed(bg, cast, 0.45)
    seen = np.roll(bg[::-1], (17, -9), (0, 1))  # refraction: the ground behind, flipped and displaced
    glass = np.clip(shadowed(seen, box, 0.55) * np.array([0.9, 1.0, 1.2], np.float32), 0, 1)
    glints = box & (np.random.default_rng(5).random((N, N)) < 0.03)
    glass[glints] = np.clip(glass[glints] + 0.4, 0, 1)
    img[box] = glass[box]
    p = predict_stimulus(img, box, n=200, seed=1, background=bg)
    assert p.p_found >= 0.99 and p.p_timeout == 0, (p.p_found, p.p_miss)  # measured 1.00
    assert 1.4 <= float(p.rt_found_s.mean()) <= 3.0  # 1.48 s
    r = p.result
    assert not (r.clicked & cast[np.maximum(r.click_y, 0), np.maximum(r.click_x, 0)]).any()
    lying = predict_stimulus(img, box, n=200, seed=1, config=ObserverConfig(shadow_shape="lying"), background=bg)
    assert p.object_evidence > 1.1 * lying.object_evidence  # 40.1 vs 35.2
    # the box's outline read at 1 deg and at the largest object size (4.8 deg: sigma 2.04 deg = 20.4 px)
    m = _resample(np.repeat(box[..., None], 3, -1).astype(np.float32), 160 / N)[..., 0].astype(np.float64)
    assert abs(lying_shape(m, 10.0)[92, 59]) < 0.05 and lying_shape(m, 20.4)[92, 59] < -0.9


def two_grounds(seed: int = 0, n: int = N) -> tuple[np.ndarray, np.ndarray]:
    """A split-like scene (its view 2): a smooth sky over the top 30 %, a dark coarse-grained ground ("asphalt")
    below it and a light fine-grained one ("marble") below a slanted border from (0, 0.55 n) to (n, 0.9 n).
    Returns the sRGB image and the true label per pixel (0 marble, 1 asphalt, 2 sky)."""
    rng = np.random.default_rng(seed)
    img = np.empty((n, n, 3), np.float32)
    top = int(0.3 * n)
    ramp = np.linspace(0.0, 1.0, top)[:, None, None]
    img[:top] = (1 - ramp) * np.array([0.25, 0.35, 0.55]) + ramp * np.array([0.55, 0.6, 0.65])
    yy, xx = np.mgrid[0:n, 0:n]
    marble = yy > 0.55 * n + 0.35 * xx
    truth = np.where(yy < top, 2, np.where(marble, 0, 1))
    fine = 0.62 + 0.05 * rng.normal(size=(n, n))
    coarse = np.kron(rng.normal(size=(n // 4, n // 4)), np.ones((4, 4)))
    dark = 0.16 + 0.04 * coarse + 0.02 * rng.normal(size=(n, n))
    g = np.where(marble, fine, dark)
    img[top:] = np.stack([g, 0.97 * g, 0.92 * g], -1)[top:]
    return np.clip(img, 0, 1), truth


def test_ground_segments_tell_the_grounds_and_the_sky_apart():
    """Two grounds and a sky are told apart along their true borders (the grounds' labels at the feature
    resolution agree with the truth on >= 97 % of the ground); one ground whose brightness drifts across the frame
    (distance, light fall-off) stays one ground."""
    from evaluation.observer import _log_image, _resample

    cfg = ObserverConfig()
    img, truth = two_grounds()
    small = _resample(img, 160 / N)
    lab, lg = srgb_to_lab(small), _log_image(small)
    sky = sky_map(lg)
    seg = ground_segments(lab, sky, cfg)
    yy, xx = np.mgrid[0:160, 0:160]
    t = truth[(yy * N / 160).astype(int), (xx * N / 160).astype(int)]
    assert seg.max() == 2 and (seg[t == 2] == 2).mean() > 0.95  # the sky (sky_map) has its own, last label
    on = t < 2
    agree = max(((seg == 0) == (t == 0))[on].mean(), ((seg == 0) == (t == 1))[on].mean())
    assert agree >= 0.97, agree
    one = grass(30) * np.linspace(0.6, 1.3, N)[:, None, None].astype(np.float32)  # darker far, brighter near
    small = _resample(np.clip(one, 0, 1), 160 / N)
    seg1 = ground_segments(srgb_to_lab(small), np.zeros((160, 160), bool), cfg)
    assert seg1.max() == 0


def test_an_object_at_the_border_of_two_grounds_is_found():
    """split's case: a grey object on the dark ground, beside the light one. With the surround on its own
    ground (the default) it stands out from the dark ground and is found; with the pooled surround of both
    grounds ("all", the former default) a grey between light and dark is typical of the mixture there."""
    bg, _ = two_grounds(1)
    mask = ellipse(90, 140, 12, 22)  # upright, on the dark ground, its foot ~6 px above the border
    img = bg.copy()
    img[mask] = np.array([0.42, 0.41, 0.40], np.float32)
    ground = predict_stimulus(img, mask, n=300, seed=3, background=bg)
    pooled = predict_stimulus(img, mask, n=300, seed=3, background=bg, config=ObserverConfig(surround="all"))
    assert ground.p_found >= 0.95, (ground.p_found, pooled.p_found)
    assert pooled.p_found <= 0.05  # (measured: 100 % vs 0 %, the pooled surround's searches time out)
    assert ground.object_evidence > 3 * ObserverConfig().criterion > pooled.object_evidence


def test_decision_and_surround_settings_are_checked():
    from study_site.simulate import parse_observer

    with pytest.raises(CamoError, match=r"^observer decision must be 'diffusion' or 'threshold', not 'vote'$"):
        ObserverConfig(decision="vote").validate()
    with pytest.raises(CamoError, match=r"^observer surround must be 'ground' or 'all', not 'sky'$"):
        ObserverConfig(surround="sky").validate()
    with pytest.raises(CamoError, match="decision_time_s must be > 0"):
        ObserverConfig(decision_time_s=0).validate()
    with pytest.raises(CamoError, match=r"^observer props must be 'scene' or 'none', not 'all'$"):
        ObserverConfig(props="all").validate()
    with pytest.raises(CamoError, match=r"^observer click must be 'body' or 'thing' or 'core' or 'peak', not 'centre'$"):
        ObserverConfig(click="centre").validate()
    with pytest.raises(CamoError, match=r"^observer prop_test must be 'verify' or 'priority', not 'all'$"):
        ObserverConfig(prop_test="all").validate()
    cfg = parse_observer("decision=threshold, surround=all, decision_time_s=0.8, props=none, click=peak")
    assert (cfg.decision, cfg.surround, cfg.decision_time_s, cfg.props, cfg.click) == ("threshold", "all", 0.8,
                                                                                     "none", "peak")
    cfg = parse_observer("click=core, prop_test=priority")
    assert (cfg.click, cfg.prop_test) == ("core", "priority")


def crate(bg: np.ndarray, x0: int, y0: int, w: int = 40, h: int = 34) -> tuple[np.ndarray, np.ndarray]:
    """A scene prop painted into the object-free view: a smooth tan box with a darker side face (a crate), and its
    mask."""
    img = bg.copy()
    m = np.zeros(bg.shape[:2], bool)
    m[y0:y0 + h, x0:x0 + w] = True
    img[y0:y0 + h, x0:x0 + w] = [0.62, 0.48, 0.3]
    img[y0:y0 + h, x0 + 2 * w // 3:x0 + w] = [0.42, 0.32, 0.2]
    return img, m


def test_a_scene_prop_is_not_taken_for_the_object():
    """A crate that is part of the scene (in the object-free view, as in every stimulus of the scene) next to a
    plainly visible object: with the scene's props known (``props="scene"``, the default) the crate is neither
    clicked nor in the way; without (``props="none"``) it draws the search and is clicked as the object. The prop
    knowledge only takes evidence away: the crate's place with an invisible object is not found more often than
    without the prop, and an object standing right beside the crate is still found."""
    ground = fine_grass(31)
    bg, prop = crate(ground, 150, 60)
    obj = disc(70, 180, 14)
    img = with_object(bg, obj, 0.75)
    known = simulate_search(img, n=300, seed=6, mask=obj, background=bg)
    on_prop = prop[np.maximum(known.click_y, 0), np.maximum(known.click_x, 0)] & known.clicked
    assert known.found.mean() >= 0.95 and on_prop.mean() <= 0.01
    unknown = simulate_search(img, n=300, seed=6, mask=obj, background=bg, config=ObserverConfig(props="none"))
    on_prop_unknown = prop[np.maximum(unknown.click_y, 0), np.maximum(unknown.click_x, 0)] & unknown.clicked
    assert on_prop_unknown.mean() >= 0.3 and unknown.found.mean() <= 0.7  # the crate wins without the knowledge
    # beside the crate (its left face 3 px away), still found
    beside = disc(133, 80, 14)
    p = predict_stimulus(with_object(bg, beside, 0.75), beside, n=300, seed=6, background=bg)
    assert p.p_found >= 0.9
    # nothing to find: the prop's knowledge does not make the invisible object's place a candidate
    empty = simulate_search(bg, n=300, seed=6, mask=beside, background=bg)
    assert empty.found.mean() <= 0.03


def test_a_flat_prop_that_only_verification_would_take_is_known():
    """A large flat grey box standing on a blotchy floor in the object-free view: with the priority test alone
    (``prop_test="priority"``) part of it is no prop and the scene without the object gets clicked on it; with the
    default (``prop_test="verify"``) every place that the verification would accept in the object-free view is a
    prop, so no place of the object-free view reaches the criterion against its own null any more, and the box is
    clicked far less. A visible object beside it is still found."""
    from evaluation.observer import _null_evidence, _regional_null, scene_props

    g = grass(24)
    bg = np.clip(g[..., [1, 0, 2]] * np.array([0.72, 0.6, 0.44], np.float32), 0, 1).astype(np.float32)  # a floor
    box = np.zeros((N, N), bool)
    box[70:134, 150:230] = True
    bg[box] = (0.36 * (1 + 0.03 * np.random.default_rng(1).normal(size=(box.sum(), 1)))).astype(np.float32)
    bgm = evidence_maps(bg, regional=False)
    ground = ~bgm.sky

    def self_verification(cfg):
        props = scene_props(bgm, cfg)
        mu, scale = _regional_null(_null_evidence(bgm, props, cfg), bgm.sky, None, cfg)
        return float(((_null_evidence(bgm, props, cfg) - mu) / scale)[ground & ~props].max())

    # Before the frame fix (lying_shape reading the frame as an outline) the priority test alone also left one
    # place at the criterion (6.67, 7 map px below the top edge); with the frame continued both tests leave at most
    # 5.80 (at the top edge), so only the default's bound is asserted here and the clicks below carry the contrast.
    assert self_verification(ObserverConfig()) < 6.0
    clicks = {}
    for test in ("priority", "verify"):
        r = simulate_search(bg, n=300, seed=6, mask=box, background=bg, config=ObserverConfig(prop_test=test))
        clicks[test] = float(r.found.mean())
    assert clicks["priority"] >= 0.75 and clicks["verify"] <= 0.5, clicks  # measured 0.81 and 0.18 (0.94, 0.31 before the frame fix)
    obj = disc(70, 180, 14)
    assert predict_stimulus(with_object(bg, obj, 0.75), obj, n=200, seed=6, background=bg).p_found >= 0.95


def test_core_click_lands_inside_the_identified_thing():
    """``click="core"``: the centre of gravity of the connected object evidence at the verified place, kept in its
    core -- a ring is clicked on its body (its centre of gravity lies in the hole), a bar whose evidence peaks at
    one end in its middle; the start is returned where its evidence is below the level."""
    from evaluation.observer import core_click

    yy, xx = np.mgrid[0:60, 0:60]
    rr = np.hypot(yy - 30, xx - 30)
    ring = np.where((rr >= 10) & (rr <= 20), 4.0, 0.0)
    y, x = core_click(ring, np.array([30, 12]), np.array([49, 30]), 25.0)
    depth = np.minimum(rr - 10, 20 - rr)[y, x]
    assert (ring[y, x] > 0).all() and (depth >= 1.5).all(), (y, x)  # on the body, off both outlines
    bar = np.zeros((40, 40))
    bar[10:30, 5:35] = 3.0
    bar[10:30, 30:35] = 9.0
    y, x = core_click(bar, np.array([20]), np.array([33]), 30.0)
    assert abs(int(y[0]) - 19.5) <= 1 and abs(int(x[0]) - 19.5) <= 1
    y, x = core_click(bar, np.array([2]), np.array([2]), 30.0)
    assert (int(y[0]), int(x[0])) == (2, 2)


def dim_floor(seed: int = 0, n: int = N) -> np.ndarray:
    """A dim wooden floor (room's): brown, coarse 1/f mottling with a large luminance spread, pixel noise."""
    rng = np.random.default_rng(seed)
    t = 0.30 + 0.07 * unit_1f(rng, n) + 0.03 * rng.normal(size=(n, n))
    return np.clip(np.stack([t, 0.62 * t, 0.38 * t], -1), 0, 1).astype(np.float32)


def chair_outline(x0: int, y0: int, n: int = N, w: int = 2) -> np.ndarray:
    """A chair drawn in lines ``w`` px wide (26 x 46 px: 1.6 x 2.9 deg): two back posts running down into the back
    legs, two back rails, the seat's front edge and two front legs -- an outline, 14 % of its bounding box."""
    m = np.zeros((n, n), bool)
    for x, y, dx, dy in ((0, 0, w, 46), (24, 0, w, 46), (0, 2, 26, w), (0, 10, 26, w), (0, 20, 26, w + 1),
                         (4, 24, w, 22), (20, 24, w, 22)):
        m[y0 + y:y0 + y + dy, x0 + x:x0 + x + dx] = True
    return m


def test_a_thin_outlined_object_is_found_on_the_display_s_own_grid():
    """Room's chairs: a light wooden chair drawn in 2 px lines on a dim, coarsely mottled floor -- plain to see. Its
    outline is carried by the orientation energies of lines 2 image px (0.125 deg) wide. On the feature grid of the
    display itself (the default, 16 px/deg for a 256 px stimulus at 16 deg: no resampling) it is found at once;
    resampled to the former 10 px/deg first, the anti-aliasing blurs the lines into the floor's mottling, the
    chair's evidence never reaches the criterion and the search ends on the floor (found 0 %, misses ~90 %).
    With each energy's noise in its own units (``energy_gain=ENERGY_GAIN``) the former grid finds it as well."""
    from evaluation.observer import ENERGY_GAIN

    bg = dim_floor(3)
    mask = chair_outline(60, 150)
    img = bg.copy()
    img[mask] = (0.55, 0.4, 0.28)
    assert ObserverConfig().feature_px_per_deg * ObserverConfig().display_deg == N  # the display's own grid
    p = predict_stimulus(img, mask, n=200, seed=1, background=bg)
    assert p.p_found >= 0.95 and 1.5 <= float(p.rt_found_s.mean()) <= 3.0, (p.p_found, p.p_miss)
    assert p.object_evidence > ObserverConfig().criterion
    coarse = predict_stimulus(img, mask, n=200, seed=1, config=ObserverConfig(feature_px_per_deg=10.0),
                              background=bg)
    assert coarse.p_found <= 0.2, coarse.p_found
    gain = predict_stimulus(img, mask, n=200, seed=1, background=bg,
                            config=ObserverConfig(feature_px_per_deg=10.0, energy_gain=ENERGY_GAIN, prop_margin=2.0))
    assert gain.p_found >= 0.95, gain.p_found


def test_feature_noise_is_one_jnd_in_each_feature_s_units():
    """:data:`ENERGY_GAIN` is the energy channel's RMS response to a unit luminance grating at its preferred
    frequency (omega st = sqrt 2): measured on a grating through :func:`_features` itself."""
    from evaluation.observer import ENERGY_GAIN, _feature_noise, _features

    st = 1.5  # px: the centre sigma 3 px gives the derivative scale max(0.7, 3 / 2)
    omega = math.sqrt(2.0) / st
    x = np.arange(128)
    L = 50.0 + np.sin(omega * x)[None, :].repeat(128, 0)
    lab = np.stack([L, np.zeros_like(L), np.zeros_like(L)], -1)
    f = _features(lab, 3.0)
    assert abs(float(np.median(f[3, 32:96, 32:96])) - ENERGY_GAIN) < 0.02  # the 0-degree channel across the bars
    np.testing.assert_allclose(_feature_noise(2.3, 7), [2.3] * 3 + [2.3 * ENERGY_GAIN] * 4)


def test_click_thing_leaves_a_peak_that_is_more_shadow_than_object():
    """``click="thing"`` on hand-made maps (feature grid 160 x 160 of a 256 px image): a body of object evidence 3
    whose evidence peaks (6) on a rim just outside it, where the shadow evidence is 9 (an object's shaded side
    meeting its own cast shadow): ``click="body"`` lands on the rim, ``click="thing"`` inside the body. A dark body
    whose shadow evidence equals its object evidence everywhere (split's dark vases) is clicked at the same place by
    both rules."""
    from scipy import ndimage

    from evaluation.observer import Maps

    h = w = 160
    yy, xx = np.mgrid[0:h, 0:w]
    body = ((yy - 80) / 10.0) ** 2 + ((xx - 80) / 16.0) ** 2 < 1.0
    rim = ((yy - 80) / 10.0) ** 2 + ((xx - 99) / 3.0) ** 2 < 1.0
    obj = ndimage.gaussian_filter(np.where(body, 3.0, 0.0) + np.where(rim & ~body, 6.0, 0.0), 1.0)
    shadow = ndimage.gaussian_filter(np.where(rim & ~body, 9.0, 0.0), 1.0)
    img = np.full((256, 256, 3), 0.5, np.float32)

    def clicks(o, s, click):
        z = np.zeros((h, w), np.float32)
        maps = Maps(z, z, s.astype(np.float32), o.astype(np.float32), o.astype(np.float32), o.astype(np.float32),
                    np.zeros((h, w), bool))
        cells = make_cells(img, ObserverConfig(click=click), maps=maps)
        best = np.argsort(cells.v)[-5:]  # the cells nearest the evidence
        fx, fy = cells.click_px[best, 0] * w // 256, cells.click_px[best, 1] * h // 256
        return fy, fx

    by, bx = clicks(obj, shadow, "body")
    ty, tx = clicks(obj, shadow, "thing")
    assert not body[by, bx].any(), (by, bx)  # the former rule: on the rim
    assert body[ty, tx].all(), (ty, tx)
    dark = ndimage.gaussian_filter(np.where(body, 5.0, 0.0), 2.0)
    assert [a.tolist() for a in clicks(dark, dark, "body")] == [a.tolist() for a in clicks(dark, dark, "thing")]


def test_click_thing_stays_on_a_dark_object_that_shows_no_ground_texture():
    """``click="thing"`` on hand-made maps: a dark body (object evidence 5, shadow evidence 8 all over it: a grey vase
    darker than sunlit sand, a glass box) with a patch of object evidence just outside its outline (the blur of its
    own evidence). Without the cast-shadow test the rule leaves the body for that patch (split's Mean view 3 and
    panorama's Transparent view 0: 100 % missed); with the object-free view's cast-shadow map 0 on the body (no
    ground texture under it) the click stays on the body, while a rim peak on textured ground in shadow (map 0.3)
    is still left for the body."""
    from scipy import ndimage

    from evaluation.observer import CLICK_CAST_SHADOW, Maps

    h = w = 160
    yy, xx = np.mgrid[0:h, 0:w]
    body = ((yy - 80) / 10.0) ** 2 + ((xx - 80) / 16.0) ** 2 < 1.0
    patch = ((yy - 80) / 6.0) ** 2 + ((xx - 101) / 5.0) ** 2 < 1.0
    img = np.full((256, 256, 3), 0.5, np.float32)

    def clicks(o, s, cast):
        z = np.zeros((h, w), np.float32)
        maps = Maps(z, z, s.astype(np.float32), o.astype(np.float32), o.astype(np.float32), o.astype(np.float32),
                    np.zeros((h, w), bool), None if cast is None else cast.astype(np.float32))
        cells = make_cells(img, ObserverConfig(click="thing"), maps=maps)
        best = np.argsort(cells.v)[-5:]
        return cells.click_px[best, 1] * h // 256, cells.click_px[best, 0] * w // 256

    obj = ndimage.gaussian_filter(np.where(body, 5.0, 0.0) + np.where(patch & ~body, 4.0, 0.0), 1.0)
    shadow = ndimage.gaussian_filter(np.where(body, 8.0 - 0.15 * (xx - 80), 0.0), 1.0)  # shaded to the left
    fy, fx = clicks(obj, shadow, None)
    assert not body[fy, fx].any(), (fy, fx)  # the rule without the texture test: off the dark body
    fy, fx = clicks(obj, shadow, np.zeros((h, w)))
    assert body[fy, fx].all(), (fy, fx)
    # a rim peak whose shadow is textured ground (the cast-shadow map above the bar there) is still left for the body
    rim = ((yy - 80) / 10.0) ** 2 + ((xx - 99) / 3.0) ** 2 < 1.0
    obj = ndimage.gaussian_filter(np.where(body, 3.0, 0.0) + np.where(rim & ~body, 6.0, 0.0), 1.0)
    shadow = ndimage.gaussian_filter(np.where(rim & ~body, 9.0, 0.0), 1.0)
    cast = np.where(rim & ~body, 3 * CLICK_CAST_SHADOW, 0.0)
    fy, fx = clicks(obj, shadow, cast)
    assert body[fy, fx].all(), (fy, fx)


def test_background_maps_are_cached_by_content_and_configuration():
    """The object-free view's own maps are kept by content hash (``_background_maps``): a second image on the same
    background gives exactly what it gives with an empty cache; another configuration or another background is
    not served the first one's maps; the cached arrays are read-only."""
    import dataclasses

    import evaluation.observer as ob

    bg, mask = grass(21), disc(120, 120, 15)
    img = with_object(bg, mask, 0.8)
    # an 8-degree display: a quarter of the default's map pixels (the cache's logic does not depend on the size)
    cfg = ObserverConfig(display_deg=8.0)
    other_cfg = dataclasses.replace(cfg, shadow_reference="background")
    ob._BACKGROUND_CACHE.clear()
    fresh = [evidence_maps(img, c, bg).verify for c in (cfg, other_cfg)]
    assert len(ob._BACKGROUND_CACHE) == 2 and not np.array_equal(fresh[0], fresh[1])
    cached = [evidence_maps(img, c, bg).verify for c in (cfg, other_cfg)]
    assert len(ob._BACKGROUND_CACHE) == 2
    for a, b in zip(fresh, cached):
        np.testing.assert_array_equal(a, b)
    bg2 = bg.copy()
    bg2[0, 0, 0] += 0.01  # one value of one pixel: another background
    evidence_maps(with_object(bg2, mask, 0.8), cfg, bg2)
    assert len(ob._BACKGROUND_CACHE) == 3
    bgm, _ = next(iter(ob._BACKGROUND_CACHE.values()))
    with pytest.raises(ValueError):
        bgm.obj[0, 0] = 1.0


def floor_and_wall(seed: int = 0, n: int = N, wall_share: float = 0.45) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """room's case: a wall over the top ``wall_share`` of the frame and a floor below it, of one mean colour (so
    :func:`ground_segments` finds one ground), the floor finely textured, the wall in large dark and light blotches
    (room's brick walls in light and shade). Returns the sRGB scene, the same floor continued over the whole frame (the
    reference: an object compared with its own surface only) and the object-free view's normals (wall facing
    the camera, floor up)."""
    rng = np.random.default_rng(seed)
    top = int(wall_share * n)
    floor = 0.42 + 0.03 * unit_1f(rng, n) + 0.015 * rng.normal(size=(n, n))
    wall = 0.42 + 0.16 * np.kron(unit_1f(rng, n // 8, 0.5), np.ones((8, 8))) + 0.015 * rng.normal(size=(n, n))
    brown = lambda g: np.clip(np.stack([g, 0.72 * g, 0.48 * g], -1), 0, 1).astype(np.float32)  # noqa: E731
    scene = brown(np.where(np.arange(n)[:, None] < top, wall, floor))
    normals = np.zeros((n, n, 3), np.float32)
    normals[:top] = (0.0, -1.0, 0.0)
    normals[top:] = (0.0, 0.0, 1.0)
    return scene, brown(floor), normals


def test_surface_labels_split_a_floor_from_walls_by_their_normals():
    """Exact labels: a floor (up, tilted 20 deg: a slope stays floor), two walls at right angles and a ceiling
    are four surfaces; where no surface is seen (-1) stays apart; a strip under the minimum share joins the
    nearest surface. One colour ground split by them keeps the sky last."""
    from evaluation.observer import SEGMENT_MIN_SHARE, combine_segments, surface_labels

    n = 100
    nr = np.zeros((n, n, 3))
    t = math.radians(20)
    nr[60:] = (0.0, math.sin(t), math.cos(t))  # floor, 40 %
    nr[20:60, :50] = (1.0, 0.0, 0.0)  # left wall, 20 %
    nr[20:60, 50:] = (0.0, -1.0, 0.0)  # back wall, 20 %
    nr[10:20] = (0.0, 0.0, -1.0)  # ceiling, 10 %
    nr[8:10] = (0.0, 0.2, -0.98)  # a 2 % strip of a near-ceiling direction: joins the ceiling
    lab = surface_labels(nr)
    assert lab[:8].tolist() == np.full((8, n), -1).tolist()
    groups = [lab[60:], lab[20:60, :50], lab[20:60, 50:], lab[8:20]]
    assert all(len(np.unique(g)) == 1 for g in groups)
    assert len({int(g[0, 0]) for g in groups}) == 4 and lab.max() == 3
    sky = np.zeros((n, n), bool)
    sky[:8] = True  # the sky: where no surface is seen
    seg = combine_segments(None, lab, sky)
    assert seg.max() == 4 and (seg[:8] == 4).all()
    assert sorted(np.bincount(seg[8:].ravel()).tolist()) == [1200, 2000, 2000, 4000]
    assert 0.02 < SEGMENT_MIN_SHARE  # the strip is under the minimum share


def test_an_object_on_the_floor_is_compared_with_the_floor_not_the_wall():
    """A floor and a wall of one colour are one colour ground; with the object-free view's normals the
    surround of a place on the floor is the floor only: the object's discriminability D is what it is on a frame
    of floor alone (within 15 %), where the wall's blotches in its surround took ~half of it, and the faint
    object is found. Without normals (sets built before them), or with the default ``surfaces="colour"``, the
    observer is the former one, exactly."""
    cfg = ObserverConfig(surfaces="geometry")
    bg, floor, normals = floor_and_wall()
    mask = disc(128, 170, 14)  # on the floor, 55 px below the wall
    img, ref = bg.copy(), floor.copy()
    img[mask] = ref[mask] = 0.85 * bg[mask]
    import evaluation.observer as ob

    assert ground_segments(srgb_to_lab(bg), sky_map(ob._log_image(bg)), cfg).max() == 0  # one colour ground
    d_ref = evidence_maps(ref, cfg, floor).d[mask].max()
    ob._BACKGROUND_CACHE.clear()
    d_col = evidence_maps(img, cfg, bg).d[mask].max()
    d_surf = evidence_maps(img, cfg, bg, normals=normals).d[mask].max()
    assert len(ob._BACKGROUND_CACHE) == 2  # the object-free view's maps are keyed by its surfaces too
    assert abs(d_surf - d_ref) < 0.15 * d_ref, (d_surf, d_ref)
    assert d_col < 0.6 * d_ref, (d_col, d_ref)  # (measured: D 1.37 one ground, 2.46 floor, 2.75 floor only)
    found = predict_stimulus(img, mask, n=200, seed=0, config=cfg, background=bg, normals=normals).p_found
    former = predict_stimulus(img, mask, n=200, seed=0, config=cfg, background=bg).p_found
    assert found >= 0.95 and former <= 0.5, (found, former)
    off = predict_stimulus(img, mask, n=200, seed=0, config=ObserverConfig(), background=bg,
                           normals=normals).p_found
    assert ObserverConfig().surfaces == "colour" and off == former
    with pytest.raises(CamoError, match="normals"):
        evidence_maps(img, cfg, bg, normals=normals[:, :100])


def test_line_map_finds_thin_dark_lines_not_steps_or_specks():
    """:func:`line_map` (black top-hat with line elements, largest minus smallest over 4 orientations): a dark line
    2 px wide and 10 L* deep on a flat ground reads its depth, 10, along its length, in any of the 4 orientations;
    a step (a cast shadow's outline: 30 L* darker on one side) reads 0; a 2 x 2 px dark speck reads 0; a band as
    wide as the element (5 px) is no line (0)."""
    from evaluation.observer import line_map

    flat = np.full((40, 40), 50.0)
    for orient in range(4):
        img = flat.copy()
        yy, xx = np.mgrid[0:40, 0:40]
        dist = {0: np.abs(yy - 19.5), 1: np.abs(xx - 19.5), 2: np.abs(yy - xx) / math.sqrt(2),
                3: np.abs(yy + xx - 39) / math.sqrt(2)}[orient]
        img[dist < 1.0] -= 10.0
        lm = line_map(img, 5)
        assert np.allclose(lm[10:30, 10:30][dist[10:30, 10:30] < 0.5], 10.0), orient
    step = flat.copy()
    step[:, 20:] -= 30.0
    assert np.abs(line_map(step, 5)).max() == 0.0
    speck = flat.copy()
    speck[19:21, 19:21] -= 10.0
    assert np.abs(line_map(speck, 5)).max() == 0.0
    band = flat.copy()
    band[18:23] -= 10.0
    assert line_map(band, 5)[20, 20] == 0.0


def glass_chair(bg: np.ndarray, x0: int = 100, y0: int = 150) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Room's see-through chair on a floor under a wall of one colour (:func:`floor_and_wall`): a seat that keeps
    35 % of the floor's light with the floor's texture showing through it (photometrically ground in shadow) and a
    frame -- back posts, rails, the seat's edge, legs -- of 2 px lines that keep 35 % of the light too. Returns the
    stimulus, its mask and the seat."""
    lines = chair_outline(x0, y0, w=2)
    seat = np.zeros(bg.shape[:2], bool)
    seat[y0 + 20:y0 + 30, x0:x0 + 26] = True
    return shadowed(shadowed(bg, seat, 0.35), lines, 0.35), lines | seat, seat


def test_a_glass_chair_is_found_by_its_frame_on_a_floor_under_a_wall():
    """The glass chair of :func:`glass_chair` on a floor whose wall shares its colour: without the frame cue the
    seat is discounted as ground in shadow (cast-shadow map up to 1 on it, mean 0.63) and the chair is never found
    (0 %); with ``frame="lines"`` its lines -- darker than the ground on both sides, which a shadow's outline never
    is -- are object evidence and it is found >= 95 %; the seat they outline is only partly lifted out of ground in
    shadow (mean map at least 0.1 lower: measured 0.46; the former rule, which let any line within the fovea lift
    the discount, took it to <= 0.27, and lifted attached shadows beside objects' own lines too)."""
    import evaluation.observer as ob

    bg, _, _ = floor_and_wall(7)
    img, mask, seat = glass_chair(bg)
    out = {}
    for frame in ("none", "lines"):
        cfg = ObserverConfig(frame=frame)
        ob._BACKGROUND_CACHE.clear()
        p = predict_stimulus(img, mask, n=200, seed=0, config=cfg, background=bg)
        cast = evidence_maps(img, cfg, bg).cast
        out[frame] = (p.p_found, float(cast[_feature_mask(seat, cast.shape)].mean()))
    assert out["none"][0] <= 0.05 and out["none"][1] >= 0.5, out  # the failure exists without the cue
    assert out["lines"][0] >= 0.95 and out["lines"][1] <= out["none"][1] - 0.1, out  # (measured 99.5 %, 0.46)


@pytest.mark.parametrize("bg_kind", ["grass", "floor_and_wall"])
def test_with_the_frame_cue_a_shadow_alone_is_still_not_clicked(bg_kind):
    """A cast shadow (35 % of the light, soft-free outline: a step) with no object, on grass and on the floor of
    the floor-and-wall ground: with ``frame="lines"`` its clicks land in it no more often than chance, and its
    outline adds no frame evidence to speak of (``frame_evidence`` on its outline, 99th percentile, at most half the
    criterion and within one d' of the object-free view's own there -- measured 2.49 vs 1.86 on grass: the pixel
    noise along a step, not a line -- against the chair's 8-10 on room's stimuli). With lines read per pixel it was
    2.56 vs 2.23: the outline reads the same, the grass's own speckle no longer counts as lines (its 99th
    percentile fell; :func:`test_line_map_needs_a_line_to_hold_along_its_length`)."""
    from evaluation.observer import _log_image, frame_evidence, ground_segments

    if bg_kind == "grass":
        bg, region = grass(12), ellipse(100, 160, 40, 16)
    else:
        bg, region = floor_and_wall(7)[0], ellipse(128, 180, 34, 11)
    img = shadowed(bg, region)
    cfg = ObserverConfig(frame="lines")
    res = simulate_search(img, n=300, seed=2, mask=region, background=bg, config=cfg)
    assert res.found.mean() <= max(0.05, 3 * region.mean()), res.found.mean()
    lab, lab_bg = srgb_to_lab(img), srgb_to_lab(bg)
    seg = ground_segments(lab_bg, sky_map(_log_image(bg)), cfg)
    fe = frame_evidence(lab, cfg, lab_bg, seg)
    from scipy import ndimage

    rim = ndimage.binary_dilation(region, iterations=2) & ~ndimage.binary_erosion(region, iterations=2)
    own = frame_evidence(lab_bg, cfg, lab_bg, seg)  # the ground's own lines at the same places
    assert float(np.percentile(fe[rim], 99)) <= min(cfg.criterion / 2, float(np.percentile(own[rim], 99)) + 1.0), (
        float(np.percentile(fe[rim], 99)), float(np.percentile(own[rim], 99)))


def test_no_position_bias_for_a_framed_glass_object():
    """The glass chair of :func:`glass_chair` (found by its frame, ``frame="lines"``) pasted on a dim floor of
    floor of stationary texture (spectrum 1/f^0.5, as :func:`fine_grass`: no chair-sized blotches) at the centre
    and in each quadrant's centre: found at rates within sampling error of the centre's (two-proportion z < 2.5;
    measured 100 % at all five). On :func:`floor_and_wall`'s 1/f floor one quadrant's place (64, 192) gives 32 %
    against 100 % elsewhere: the texture's large blotches there, as docs/observer.md says of the disc on 1/f grass."""
    rng = np.random.default_rng(5)
    g = 0.42 + 0.03 * unit_1f(rng, N, 0.5) + 0.015 * rng.normal(size=(N, N))
    bg = np.clip(np.stack([g, 0.72 * g, 0.48 * g], -1), 0, 1).astype(np.float32)
    rates, n = [], 300
    for cx, cy in ((128, 128), (64, 64), (192, 64), (64, 192), (192, 192)):
        img, mask, _ = glass_chair(bg, cx - 13, cy - 23)
        rates.append(predict_stimulus(img, mask, n=n, seed=3, background=bg,
                                      config=ObserverConfig(frame="lines")).p_found)
    for r in rates[1:]:
        pooled = (rates[0] + r) / 2
        se = math.sqrt(max(pooled * (1 - pooled), 1.0 / n) * 2 / n)
        assert abs(rates[0] - r) / se < 2.5, rates
    assert min(rates) >= 0.9, rates


def _flank_case(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """L*a*b* ``(64, 64, 3)`` image and its object-free view (flat L* 50, pixel noise 0.5) with a dark line 2 px
    wide (L* 35) across columns 10-53 at rows 30-31: ``"frame"`` -- the same ground on both sides (a rail of a glass
    chair); ``"sliver"`` -- a light object (L* 80) above the line, the ground below (a cast shadow's sliver hugging
    its caster); ``"contact"`` -- a box (L* 65) above, its cast shadow (L* 24) below and the line L* 12 between
    (where a box's base meets its shadow)."""
    rng = np.random.default_rng(3)
    bg = np.zeros((64, 64, 3))
    bg[..., 0] = 50.0 + 0.5 * rng.normal(size=(64, 64))
    img = bg.copy()
    if kind == "sliver":
        img[8:30, 10:54, 0] = 80.0 + 0.5 * rng.normal(size=(22, 44))
    if kind == "contact":
        img[8:30, 10:54, 0] = 65.0 + 0.5 * rng.normal(size=(22, 44))
        img[32:52, 10:54, 0] = 24.0 + 0.5 * rng.normal(size=(20, 44))
    img[30:32, 10:54, 0] = 12.0 if kind == "contact" else 35.0
    return img, bg


@pytest.mark.parametrize("kind", ["frame", "sliver", "contact"])
def test_frame_evidence_counts_two_sided_lines_only(kind):
    """Step 2d's lines are two-sided (:func:`flank_contrast`): every case is a line to :func:`line_map` (depth
    >= 10 L* below both its sides; the element across it is not the one along it), but only the line with the same ground on both sides -- a frame's rail -- is
    frame evidence (>= 4 d' along its middle); a sliver between an object and the ground, and a contact line
    between a box and its shadow, are edges between two surfaces (measured flank contrast 24-44 L* against the
    frame's 2-5 and the flat ground's ~1: no weight) and give <= 0.5 (measured 6.1-6.7 for the frame, -0.3 for
    the other two)."""
    from evaluation.observer import _line_tophats, flank_contrast, frame_evidence

    img, bg = _flank_case(kind)
    li, across = _line_tophats(img[..., 0], 5)
    assert float(li[30:32, 20:44].min()) >= 10.0  # a line to the top-hat in every case
    assert (across[30:32, 20:44] != 0).all()  # the element across it: vertical or diagonal, never along it
    fc = flank_contrast(img, across, 3)
    fe = frame_evidence(img, ObserverConfig(frame="lines"), bg)
    if kind == "frame":
        assert float(fc[30:32, 20:44].max()) < 5.0
        assert float(fe[30:32, 20:44].min()) >= 4.0, float(fe[30:32, 20:44].min())
    else:
        assert float(fc[30:32, 20:44].min()) >= 20.0, float(fc[30:32, 20:44].min())
        assert float(fe[30:32, 20:44].max()) <= 0.5, float(fe[30:32, 20:44].max())


def test_with_the_frame_cue_an_attached_shadow_keeps_its_discount():
    """:func:`test_an_attached_shadow_does_not_pull_the_click_off_its_object`'s faint body with the dark shadow
    hugging its side (occluded's plain torus), with ``frame="lines"``: the body's own lines beside the shadow and
    the grass's own lines in it do not lift the shadow's cast-shadow discount (only lines on the darkening, and
    stronger than the ground's own by z 3-6, do): the cast-shadow map keeps a median >= 0.5 on the shadow
    (measured 0.89; 0.11 under the former rule, every line within the fovea, z 0-2) and no click lands on the
    shadow. The body is found in >= 50 % (measured 55 %, the rest timeouts: the grass's own lines raise the
    verification's null, V 5.7 against 7.0 without the cue -- the cue's cost on faint bodies, 99 % without it)."""
    bg = grass(41)
    obj = ellipse(120, 130, 13, 24)
    sh = (ellipse(134, 140, 10, 22) | ellipse(140, 154, 14, 9)) & ~obj
    img = shadowed(bg, sh, 0.2)
    img[obj] = 0.85 * bg[obj] + 0.15 * np.array([0.75, 0.7, 0.6], np.float32)
    cfg = ObserverConfig(frame="lines")
    cast = evidence_maps(img, cfg, bg).cast
    assert float(np.median(cast[_feature_mask(sh, cast.shape)])) >= 0.5
    res = simulate_search(img, n=300, seed=4, config=cfg, mask=obj, background=bg)
    on_sh = sh[np.maximum(res.click_y, 0), np.maximum(res.click_x, 0)] & res.clicked
    assert res.found.mean() >= 0.5 and on_sh.mean() <= 0.02, (res.found.mean(), on_sh.mean())


def test_line_map_needs_a_line_to_hold_along_its_length():
    """:func:`line_map` keeps a line's depth only where it holds for the element's length along the line (a
    directional opening, Soille & Talbot 2001). A dark shadow strewn with bright grains (20 % of the pixels, up to
    30 L* above it: a caustic's or a sparse render's speckle, panorama's Ours shadow) has dark gaps that one
    orientation's closing fills at one pixel and another's at the next; read per pixel they were lines (90th
    percentile 20.0, 99th 26.6); now most of the field reads 0 (90th percentile 0, 99th 13.9). On pixel noise of
    3 L* the 99th percentile nearly halves (7.6 -> 4.1) while a 2 px line 10 L* deep in that noise keeps 7.6 of its
    depth (10.1 before): the line stands out of the noise's own lines by 1.86x instead of 1.33x."""
    from evaluation.observer import line_map

    rng = np.random.default_rng(0)
    img = np.full((64, 64), 20.0)
    grains = rng.random((64, 64)) < 0.2
    img[grains] += 30.0 * rng.random(int(grains.sum()))
    lm = line_map(img, 5)[8:-8, 8:-8]
    assert np.percentile(lm, 90) <= 1.0 and np.percentile(lm, 99) <= 16.0, np.percentile(lm, [90, 99])
    noise = 20.0 + 3.0 * rng.normal(size=(64, 64))
    own = float(np.percentile(line_map(noise, 5)[8:-8, 8:-8], 99))
    lined = noise.copy()
    lined[31:33] -= 10.0
    on = float(np.median(line_map(lined, 5)[31:33, 8:-8]))
    assert own <= 4.5 and on >= 6.0 and on / own >= 1.6, (own, on)


def grainy_shadow_scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Panorama's Ours box (a plain grey see-through box on gravel) with a lying cast shadow beside its base whose
    dark ground is strewn with bright grains (20 % of its pixels, up to half the full linear radiance: the light
    sent through the box, rendered with few samples). Returns the stimulus, its object-free view, the box's mask and
    the shadow's."""
    from camo_base.imaging import linear_to_srgb, srgb_to_linear

    rng = np.random.default_rng(3)
    t = 0.45 + 0.08 * unit_1f(rng, N) + 0.08 * rng.normal(size=(N, N))
    bg = np.clip(np.stack([0.62 * t, 0.52 * t, 0.40 * t], -1) * 1.4, 0, 1).astype(np.float32)
    yy, xx = np.mgrid[0:N, 0:N]
    box = (xx >= 150) & (xx < 180) & (yy >= 100) & (yy < 150)
    shade = (((xx - 125) / 34.0) ** 2 + ((yy - 160) / 9.0) ** 2 < 1.0) & ~box
    lin = srgb_to_linear(bg)
    lin[shade] *= 0.25
    g = shade & (np.random.default_rng(5).random(shade.shape) < 0.2)
    lin[g] += 0.5 * np.random.default_rng(6).random(int(g.sum()))[:, None]
    lin[box] = 0.55 * lin[box] + 0.06
    return np.clip(linear_to_srgb(lin), 0, 1).astype(np.float32), bg, box, shade


def test_with_the_frame_cue_a_grainy_shadow_does_not_take_the_click_off_a_plain_box():
    """Panorama's Ours box with ``frame="lines"`` (:func:`grainy_shadow_scene`): the grains' gaps read as lines
    stronger than the box when lines were read per pixel (its clicks 100 % on the shadow, found 0 %: 93 % confused
    on panorama's four views); with lines that must hold along their length the box is found (measured 100 %) and
    its shadow never clicked -- as without the cue."""
    img, bg, box, shade = grainy_shadow_scene()
    for frame in ("none", "lines"):
        r = simulate_search(img, n=200, seed=1, mask=box, background=bg, config=ObserverConfig(frame=frame))
        on_shade = r.clicked & shade[np.maximum(r.click_y, 0), np.maximum(r.click_x, 0)]
        assert r.found.mean() >= 0.95 and on_shade.mean() <= 0.02, (frame, r.found.mean(), on_shade.mean())


def test_with_the_frame_cue_a_chair_on_a_noisy_floor_is_not_lost_in_the_floor_s_own_lines():
    """Room's Mean chair of view 0 with ``frame="lines"``: a chair drawn in 2 px lines, half-way between the floor
    and light wood, on a dim floor with strong pixel noise (5 % of full scale). Read per pixel, the noise's own
    lines raised the verification's null around it (its evidence 5.2, under the criterion 6) and the search timed
    out (found 13 %, 87 % timeouts; room's chair 19.5 %, 79.5 %); with lines that must hold along their length the
    floor's own lines are fewer, the chair's evidence clears the criterion (8.4) and it is found (measured 100 %)."""
    rng = np.random.default_rng(3)
    t = 0.30 + 0.07 * unit_1f(rng, N) + 0.05 * rng.normal(size=(N, N))
    bg = np.clip(np.stack([t, 0.62 * t, 0.38 * t], -1), 0, 1).astype(np.float32)
    mask = chair_outline(60, 150)
    img = bg.copy()
    img[mask] = np.clip(0.5 * bg[mask] + 0.5 * np.array([0.55, 0.4, 0.28]), 0, 1)
    cfg = ObserverConfig(frame="lines")
    maps = evidence_maps(img, cfg, bg)
    assert float(maps.verify[mask].max()) >= cfg.criterion + 0.5, float(maps.verify[mask].max())
    r = simulate_search(img, n=200, seed=1, mask=mask, background=bg, config=cfg)
    assert r.found.mean() >= 0.9 and r.timed_out.mean() <= 0.1, (r.found.mean(), r.timed_out.mean())


def _lstar(y: np.ndarray) -> np.ndarray:
    """CIE L* of relative luminance ``y`` (above the linear toe)."""
    return 116.0 * np.cbrt(y) - 16.0


def test_a_rail_that_darkens_its_ground_by_a_factor_reads_one_depth_as_a_ratio():
    from evaluation.observer import RATIO_REF_L, line_map

    # a dark floor (Y 0.05, left) and a light one (Y 0.4, right), a vertical rail 2 px wide over both that passes
    # half the light (a see-through rail): in L* it is 8.8 deep on the dark floor and 17.6 on the light one; as a
    # contrast ratio, (RATIO_REF_L + 16) / 3 x ln 2 on both
    y = np.full((48, 48), 0.05)
    y[:, 24:] = 0.4
    y = y.T.copy()  # the floors top (dark) and bottom (light); the rail runs down across both
    y[:, 20:22] *= 0.5
    lum = _lstar(y)
    diff, ratio = line_map(lum, 7), line_map(lum, 7, contrast="ratio")
    top, bottom = (slice(4, 18), slice(20, 22)), (slice(30, 44), slice(20, 22))
    assert diff[top].max() == pytest.approx(_lstar(0.05) - _lstar(0.025), rel=0.01)
    assert diff[bottom].max() == pytest.approx(_lstar(0.4) - _lstar(0.2), rel=0.01)
    want = (RATIO_REF_L + 16.0) / 3.0 * np.log(2.0)
    assert ratio[top].min() == pytest.approx(want, rel=0.01)
    assert ratio[bottom].min() == pytest.approx(want, rel=0.01)
    # off the rail, flat floors: no line either way
    assert diff[top[0], 30:44].max() == pytest.approx(0.0, abs=1e-9)
    assert ratio[top[0], 30:44].max() == pytest.approx(0.0, abs=1e-9)


def test_frame_lines_ratio_is_a_setting_and_a_bad_frame_is_refused():
    from evaluation.observer import line_map

    ObserverConfig(frame="lines_ratio").validate()
    with pytest.raises(CamoError, match="frame"):
        ObserverConfig(frame="ratio").validate()
    with pytest.raises(ValueError, match="line contrast"):
        line_map(np.zeros((8, 8)), 3, contrast="log")
