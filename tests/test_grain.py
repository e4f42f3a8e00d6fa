"""The albedo's grain layer (``--grain G``, optimizer/optimise/grain.py, issue 29): the best-view residual against
hand-computed values, the 1 / sqrt(V) smoothing it undoes, the option's validation, and in a real Stage 1 on gravel:
the layer is the warm start's, fixed, rendered and folded as ``clip(fine + G grain)``."""

from __future__ import annotations

import numpy as np
import pytest

from camo_base.errors import CamoError
from fixture_stage1 import tiny_gravel_stage1
from optimizer.optimise import grain
from optimizer.optimise.warmstart import grain_residual


def test_residual_is_best_view_minus_weighted_mean():
    # black renders 0, white 1: the albedo that matches a view is its background itself
    B = np.array([[[0.2] * 3, [0.3] * 3], [[0.6] * 3, [0.3] * 3], [[0.4] * 3, [0.3] * 3]])  # (V=3, N=2, 3)
    w = np.array([[0.2, 0.0], [0.9, 0.0], [0.5, 0.0]])  # texel 1 seen by no view
    g, ok = grain_residual(B, np.zeros_like(B), np.ones_like(B), w)
    mean = (0.2 * 0.2 + 0.9 * 0.6 + 0.5 * 0.4) / 1.6  # 0.4875
    np.testing.assert_allclose(g[0], 0.6 - mean, atol=1e-6)  # 0.1125
    assert ok.tolist() == [True, False] and g[1].tolist() == [0.0, 0.0, 0.0]


def test_residual_divides_out_the_materials_slope():
    # a transmissive start: L(a) = L0 + a (L1 - L0) with L0 = 0.3, L1 = 0.5; best view's target 0.42 -> a = 0.6
    B = np.array([[[0.42, 0.42, 0.42]], [[0.34, 0.34, 0.34]]])
    L0, L1 = np.full_like(B, 0.3), np.full_like(B, 0.5)
    g, ok = grain_residual(B, L0, L1, np.array([[1.0], [0.5]]))
    # mean: (1 * 0.6 + 0.5 * 0.2) / 1.5 = 0.4667 (the slopes are equal); best 0.6
    np.testing.assert_allclose(g[0], 0.6 - 0.7 / 1.5, atol=1e-6)
    assert ok.all()


def test_mean_plus_grain_restores_the_best_views_texture():
    """V views of unrelated grain with equal weights: the warm start's mean keeps ~1 / sqrt(V) of the grain's
    amplitude (the smooth body); mean + grain is each texel's best view exactly."""
    rng = np.random.default_rng(0)
    V, N = 4, 20_000
    B = 0.5 + 0.1 * rng.standard_normal((V, N, 1)).repeat(3, -1)
    w = 0.5 + 0.01 * rng.random((V, N))  # near-equal weights, one best view per texel
    from optimizer.optimise.warmstart import least_squares_albedo

    mean, _, _ = least_squares_albedo(B, np.zeros_like(B), np.ones_like(B), w)
    g, ok = grain_residual(B, np.zeros_like(B), np.ones_like(B), w)
    assert ok.all()
    assert np.std(mean[:, 0]) == pytest.approx(0.1 / np.sqrt(V), rel=0.05)
    best = B[np.argmax(w, 0), np.arange(N)]
    np.testing.assert_allclose(mean + g, best, atol=1e-5)
    assert np.std((mean + g)[:, 0]) == pytest.approx(0.1, rel=0.05)


def test_grain_map_places_texels_and_zeroes_the_rest():
    class Surface:
        resolution = 2
        index = np.array([0, 3, 2])

    m = grain.grain_map(Surface(), np.array([[0.1] * 3, [-0.2] * 3, [0.5] * 3]), np.array([True, True, False]))
    assert m.shape == (2, 2, 3)
    np.testing.assert_allclose(m[..., 0], [[0.1, 0.0], [0.0, -0.2]])


def test_options_and_errors():
    from optimizer.optimise.spec import RunSpec

    assert RunSpec.from_options({"scene": "meadow", "grain": 1.0}).validate().stage1.grain == 1.0
    assert RunSpec.from_options({"scene": "meadow"}).validate().stage1.grain == 0.0  # off by default
    for bad, field in (({"grain": 1.0, "warm_start": "off"}, "warm.start"), ({"grain": 3.0}, "grain"),
                       ({"grain": -1.0}, "grain"), ({"grain": 1.0, "method": "mean"}, "grain")):
        with pytest.raises(CamoError, match=field) as e:
            RunSpec.from_options({"scene": "meadow", **bad}).validate()
        assert "\n" not in str(e.value)


def test_stage1_grain_layer_is_rendered_and_folded(mi_backend):
    """A real Stage 1 on gravel (4 views: texels seen twice; 24 px, one thread): the warm start projects a grain layer of the ground's
    texture (non-zero, texels both ways), the rendered albedo is ``clip(fine + G grain)``, a step leaves the layer as
    it was, and the stage's result is the folded map; without the option there is no layer."""
    mi, dr = mi_backend
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        s1 = tiny_gravel_stage1(False, views=4, warm_start=True, grain=0.8, grain_sharpen=2.0)
        g, g_dr = s1._grain
        assert g.shape == s1.values["albedo"].shape
        seen = np.abs(g).sum(-1) > 0
        assert seen.mean() > 0.02 and (g < -0.01).any() and (g > 0.01).any()
        assert s1.warm_start_info.grain_rms > 0.01 and "grain" not in s1.warm_start_info.to_dict()
        before = g.copy()
        s1.step()
        fine = np.asarray(s1.opt["albedo"]).reshape(g.shape)
        want = np.clip(fine + 0.8 * g, 1e-3, 1.0)
        rendered = np.asarray(s1._mapped()[s1._keys["albedo"]]).reshape(g.shape)
        if s1._coarse is None:
            np.testing.assert_allclose(rendered, want, atol=1e-6)
        np.testing.assert_array_equal(s1._grain[0], before)  # fixed: not a parameter
        assert "albedo_grain" not in s1.opt.values
        out = s1.current_values()["albedo"]
        np.testing.assert_allclose(out, want, atol=1e-6)
        np.testing.assert_allclose(rendered, out, atol=1e-6)
        s0 = tiny_gravel_stage1(False, views=4, warm_start=True)
        assert s0._grain is None and s0.warm_start_info.grain is None
    finally:
        dr.set_thread_count(threads)


def test_sharpen_is_an_unsharp_mask_against_scipy():
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(1)
    x = rng.random((2, 9, 7, 3))
    want = x + 2.0 * (x - np.stack([gaussian_filter(v, (0.7, 0.7, 0), mode="reflect") for v in x]))
    np.testing.assert_allclose(grain.sharpen(x, 2.0), want, atol=1e-6)
    np.testing.assert_allclose(grain.sharpen(np.full((1, 4, 4, 3), 0.3), 2.0), 0.3, atol=1e-6)  # flat stays flat
    assert np.std(grain.sharpen(x, 2.0)) > 1.5 * np.std(x - x.mean())  # the pixel-scale grain is amplified


def test_best_view_reads_the_sharpened_observations():
    B = np.array([[[0.2] * 3], [[0.6] * 3]])  # (V=2, N=1, 3), L0 = 0, L1 = 1: albedo = the observation
    Bs = np.array([[[0.1] * 3], [[0.7] * 3]])
    w = np.array([[0.5], [1.0]])
    g, ok = grain_residual(B, np.zeros_like(B), np.ones_like(B), w, best_background=Bs)
    np.testing.assert_allclose(g[0], 0.7 - (0.5 * 0.2 + 1.0 * 0.6) / 1.5, atol=1e-6)  # best (sharpened) - mean (not)
