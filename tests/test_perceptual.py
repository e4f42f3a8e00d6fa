"""The perceptual term of Stage 1 (``--perceptual``, optimizer/optimise/perceptual.py, issue 29): the LPIPS gradient
with respect to a linear render (against central differences), the padding of small windows, the option's
parsing and range, and the surrogate's parameter gradient through a real Mitsuba render (against the squared
error's, with a provider whose gradient is the squared error's)."""

from __future__ import annotations

import numpy as np
import pytest

from camo_base.errors import CamoError
from fixture_stage1 import tiny_gravel_stage1


def test_lpips_gradient_matches_central_differences(installed_lpips):
    import camo  # noqa: F401  (registers the LPIPS provider)
    from optimizer.optimise.perceptual import network, perceptual_grad

    rng = np.random.default_rng(0)
    x = (rng.random((2, 20, 40, 3)) * 0.6).astype(np.float32)  # smaller than 32 px: padded
    y = (rng.random((2, 20, 40, 3)) * 0.6).astype(np.float32)
    fn = network("alex")
    v, g = perceptual_grad(fn, x, y)
    assert g.shape == x.shape and v.shape == (2,) and np.all(v > 0.01)
    vs, gs = perceptual_grad(fn, y, y)
    assert np.allclose(vs, 0.0, atol=1e-6) and np.abs(gs).max() < 1e-4  # identical images: 0 and no push
    for idx in [(0, 5, 7, 1), (1, 12, 30, 0), (0, 19, 39, 2)]:
        e = 1e-2
        xp, xm = x.copy(), x.copy()
        xp[idx] += e
        xm[idx] -= e
        fd = (perceptual_grad(fn, xp, y)[0][idx[0]] - perceptual_grad(fn, xm, y)[0][idx[0]]) / (2 * e)
        assert fd == pytest.approx(float(g[idx]), rel=0.05, abs=2e-5)
    over = x.copy()
    over[0, 3, 3] = 5.0  # above 1 the sRGB encoding is clipped: no gradient there
    assert np.all(perceptual_grad(fn, over, y)[1][0, 3, 3] == 0)


def test_padding_adds_no_distance():
    from optimizer.optimise.perceptual import pad_to_min

    x = np.zeros((1, 10, 50, 3), np.float32)
    y = np.ones((1, 10, 50, 3), np.float32)
    xp, yp, hw = pad_to_min(x, y)
    assert xp.shape == yp.shape == (1, 32, 50, 3) and hw == (10, 50)
    np.testing.assert_array_equal(xp[:, 10:], yp[:, 10:])
    np.testing.assert_array_equal(xp[:, :10], x)


def test_option_parsing_and_errors():
    from optimizer.optimise import perceptual
    from optimizer.optimise.spec import RunSpec

    s = RunSpec.from_options({"scene": "meadow", "perceptual": 1e-3, "perceptual_net": "vgg"})
    assert (s.stage1.perceptual, s.stage1.perceptual_net) == (1e-3, "vgg")
    assert RunSpec.from_options({"scene": "meadow"}).stage1.perceptual == 0.0  # off by default
    with pytest.raises(CamoError, match="perceptual"):
        RunSpec.from_options({"scene": "meadow", "perceptual": -1})
    with pytest.raises(CamoError, match="perceptual_net must be one of"):
        perceptual.network("resnet")


def test_missing_provider_is_a_clear_error(monkeypatch):
    from optimizer.optimise import perceptual

    monkeypatch.setattr(perceptual, "_factory", None)
    with pytest.raises(CamoError, match="import camo"):
        perceptual.network("alex")


@pytest.mark.parametrize("batched", [False, True], ids=["per-view", "batch-film"])
def test_surrogate_gradient_is_the_terms_gradient(mi_backend, monkeypatch, batched):
    """With a provider whose distance is the sum of squared differences, ``W = 1 / (H W 3)`` makes the perceptual
    term the frame's squared error again: the parameter gradient of Stage 1 (loss mse, domain frame) doubles. Both
    training paths: one render per view (projective integrator), and one batch film of all views (prb: no geometry
    trains)."""
    import drjit as dr

    from optimizer.optimise import perceptual

    def squared(x, y):
        return ((x - y) ** 2).sum(axis=(1, 2, 3)), 2.0 * (x - y)

    monkeypatch.setattr(perceptual, "_factory", lambda net: squared)
    s1 = tiny_gravel_stage1(batched, perceptual=1.0 / (24 * 24 * 3))
    assert s1._perceptual is squared and s1._batched == batched
    threads = dr.thread_count()
    dr.set_thread_count(1)  # same seeds, one thread: the same renders in both calls
    try:
        loss1, with_term = s1.gradient()
        term = s1._last_perceptual
        s1._perceptual = None
        loss0, without = s1.gradient()
    finally:
        dr.set_thread_count(threads)
    assert loss1 == pytest.approx(loss0)  # the logged photometric loss is the photometric loss alone
    assert term == pytest.approx(loss0, rel=1e-3)  # W x sum of squares / V = the frame's MSE
    for name in ("albedo", "roughness") if batched else ("albedo", "roughness", "translation"):
        scale = np.abs(without[name]).max()
        assert scale > 0, name
        np.testing.assert_allclose(with_term[name], 2.0 * without[name], rtol=0, atol=2e-3 * scale, err_msg=name)
