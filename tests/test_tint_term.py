"""The mean-colour term of Stage 1 (``--tint-match W``, optimizer/optimise/tint.py): its value on known image pairs,
its gradient against central differences and through the Dr.Jit surrogate (per view and on the batch film), that it
is the mean-colour part of the squared error at W = 1, its option errors, and that a real Stage 1 adds it."""

from __future__ import annotations

import numpy as np
import pytest

from camo_base.errors import CamoError
from fixture_stage1 import tiny_gravel_stage1
from optimizer.optimise import tint


def test_value_on_known_pairs():
    bg = np.full((6, 5, 3), 0.3)
    c = np.zeros((6, 5))
    c[1:4, 1:4] = 1.0
    assert tint.term_np(bg.copy(), bg, c, 0.5, 8.0) == 0.0  # no object colour error: no term
    img = bg.copy()
    img[1:4, 1:4] += (0.0, 0.2, -0.1)  # a green cast on the mask, none outside
    assert tint.term_np(img, bg, c, 0.5, 8.0) == pytest.approx(8.0 * 0.5 * (0.04 + 0.01) / 3)
    img[0, 0] += 5.0  # outside the mask: no change
    assert tint.term_np(img, bg, c, 0.5, 8.0) == pytest.approx(8.0 * 0.5 * 0.05 / 3)
    # texture with a zero mean on the mask is not a tint: +0.2 and -0.2 on two of its pixels
    tex = bg.copy()
    tex[1, 1] += 0.2
    tex[1, 2] -= 0.2
    assert tint.term_np(tex, bg, c, 1.0, 1.0) == pytest.approx(0.0, abs=1e-15)
    # a half-covered pixel counts half
    c2 = np.zeros((1, 2))
    c2[0] = (1.0, 0.5)
    assert tint.mean_colour(np.array([[[0.0] * 3, [0.3] * 3]]), c2) == pytest.approx([0.1] * 3)
    # no mask: no term, a zero gradient
    assert tint.term_np(img, bg, np.zeros((6, 5)), 1.0, 1.0) == 0.0
    assert not tint.grad_np(img, bg, np.zeros((6, 5)), 1.0, 1.0).any()


def test_at_weight_one_it_is_the_mean_colour_part_of_the_squared_error():
    """On a fully covered mask that is the loss domain, mean((I - B)^2) = the term at W = 1, s = 1 plus the variance
    of the per-pixel error about its mean (the bias-variance split of the squared error)."""
    rng = np.random.default_rng(0)
    bg = rng.random((8, 8, 3))
    img = bg + 0.05 + 0.1 * rng.standard_normal((8, 8, 3))
    c = np.ones((8, 8))
    err = img - bg
    mse = float(np.mean(err**2))
    variance = float(np.mean((err - err.mean((0, 1))) ** 2))
    assert tint.term_np(img, bg, c, 1.0, 1.0) == pytest.approx(mse - variance, rel=1e-12)


def test_gradient_against_central_differences():
    rng = np.random.default_rng(1)
    h, w = 5, 6
    img, bg = rng.random((h, w, 3)), rng.random((h, w, 3)) * 1.5
    c = rng.random((h, w)) * (rng.random((h, w)) > 0.3)
    g = tint.grad_np(img, bg, c, 0.4, 16.0)
    num = np.zeros_like(img)
    for idx in np.ndindex(*img.shape):
        up, dn = img.copy(), img.copy()
        up[idx] += 1e-6
        dn[idx] -= 1e-6
        num[idx] = (tint.term_np(up, bg, c, 0.4, 16.0) - tint.term_np(dn, bg, c, 0.4, 16.0)) / 2e-6
    assert np.abs(num).max() > 1e-3
    np.testing.assert_allclose(g, num, rtol=1e-6, atol=1e-9)
    assert not g[c == 0].any()  # uncovered pixels get no gradient


def test_surrogate_gradient_per_view_and_on_the_film(mi_backend):
    """The surrogate's Dr.Jit gradient is :func:`grad_np` / V for each view, and the batch film (two views side by
    side) gives the same gradients in the same columns; ``last`` holds the mean of the views' terms."""
    mi, dr = mi_backend
    rng = np.random.default_rng(3)
    h, w = 6, 7
    imgs = [rng.random((h, w, 3)).astype(np.float32) for _ in range(2)]
    bgs = [rng.random((h, w, 3)).astype(np.float32) for _ in range(2)]
    cs = [(rng.random((h, w)) > 0.4).astype(np.float64) for _ in range(2)]
    shares = [0.3, 0.6]
    term = tint.TintTerm(bgs, cs, shares, 4.0)
    xs = [mi.TensorXf(i) for i in imgs]
    for x in xs:
        dr.enable_grad(x)
    dr.backward(term.surrogate(xs, [(0, 0), (1, 1)]))
    expect = [tint.grad_np(imgs[v].astype(np.float64), bgs[v], cs[v], shares[v], 4.0) / 2 for v in range(2)]
    for v in range(2):
        np.testing.assert_allclose(np.asarray(dr.grad(xs[v]), np.float64), expect[v], rtol=1e-5, atol=1e-9)
    value = sum(tint.term_np(imgs[v].astype(np.float64), bgs[v], cs[v], shares[v], 4.0) for v in range(2)) / 2
    assert term.last["value"] == pytest.approx(value, rel=1e-6) and value > 0

    film_term = tint.TintTerm(bgs, cs, shares, 4.0, film=(h, w, 2))
    film = mi.TensorXf(np.concatenate(imgs, axis=1))
    dr.enable_grad(film)
    dr.backward(film_term.surrogate([film], [(0, 0), (1, 0)]))
    np.testing.assert_allclose(np.asarray(dr.grad(film), np.float64), np.concatenate(expect, axis=1),
                               rtol=1e-5, atol=1e-9)
    assert film_term.last["value"] == pytest.approx(value, rel=1e-6)
    # no mask in any view: no surrogate
    empty = tint.TintTerm(bgs, [np.zeros((h, w))] * 2, shares, 4.0)
    assert empty.surrogate(xs, [(0, 0), (1, 1)]) is None


@pytest.mark.parametrize("batched", [False, True], ids=["per-view", "batch-film"])
def test_stage1_adds_the_term_linearly_in_its_weight(mi_backend, batched):
    """A real Stage 1 on gravel (2 views, 24 px), one thread and the same seeds (the same renders): the albedo's
    gradient with the term at W and 2 W differs from the one without by d and 2 d (the surrogate is linear in W),
    d is not negligible, and the logged photometric loss is the squared error's alone."""
    _, dr = mi_backend
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        runs = {}
        for weight in (0.0, 20.0, 40.0):
            s1 = tiny_gravel_stage1(batched, tint_match=weight)
            assert (s1._tint is not None) == (weight > 0) and s1._batched == batched
            runs[weight] = (*s1.gradient(), s1._tint.last if s1._tint is not None else None)
    finally:
        dr.set_thread_count(threads)
    base = runs[0.0][1]["albedo"]
    d1 = runs[20.0][1]["albedo"] - base
    d2 = runs[40.0][1]["albedo"] - base
    assert runs[20.0][0] == pytest.approx(runs[0.0][0], rel=1e-5)  # the photometric loss is logged without the term
    assert np.abs(d1).max() > 1e-3 * np.abs(base).max()
    np.testing.assert_allclose(d2, 2 * d1, rtol=2e-2, atol=2e-3 * np.abs(d1).max())
    last20, last40 = runs[20.0][2], runs[40.0][2]
    assert last20["value"] > 0 and last40["value"] == pytest.approx(2 * last20["value"], rel=1e-4)
    assert last20["error"] == pytest.approx(last40["error"], rel=1e-4)


def test_local_form_gradient_and_its_wide_limit():
    """The local form (``--tint-scale S``): its gradient against central differences (the zero-padded Gaussian is its
    own transpose), and a uniform cast far from the window's edges costs what the mean form charges."""
    rng = np.random.default_rng(4)
    h, w = 9, 8
    bg = rng.random((h, w, 3))
    img = bg + (0.3, -0.1, 0.2) + 0.2 * rng.random((h, w, 3))  # a cast and texture
    c = rng.random((h, w)) * (rng.random((h, w)) > 0.5)
    g = tint.lowpass_grad_np(img, bg, c, 0.3, 4.0, 1.5)
    num = np.zeros_like(img)
    for idx in np.ndindex(*img.shape):
        up, dn = img.copy(), img.copy()
        up[idx] += 1e-6
        dn[idx] -= 1e-6
        num[idx] = (tint.lowpass_term_np(up, bg, c, 0.3, 4.0, 1.5) - tint.lowpass_term_np(dn, bg, c, 0.3, 4.0, 1.5)) / 2e-6
    assert np.abs(num).max() > 1e-3
    np.testing.assert_allclose(g, num, rtol=1e-6, atol=1e-9)
    big = np.zeros((40, 40, 3))
    cast = big + (0.1, -0.2, 0.05)
    mask = np.zeros((40, 40))
    mask[17:23, 17:23] = 1.0
    assert tint.lowpass_term_np(cast, big, mask, 0.2, 3.0, 2.0) == pytest.approx(
        tint.term_np(cast, big, mask, 0.2, 3.0), rel=1e-9)
    # texture of zero mean is damped by the low-pass (a checkerboard of +-0.2): far below its squared error
    checker = big + 0.2 * np.where(np.indices((40, 40)).sum(0) % 2 == 0, 1.0, -1.0)[..., None]
    assert tint.lowpass_term_np(checker, big, mask, 1.0, 1.0, 2.0) < 1e-3 * 0.04


def test_scale_needs_the_weight():
    from optimizer.optimise.spec import RunSpec

    assert RunSpec.from_options({"scene": "meadow", "tint_match": 4, "tint_scale": 2}).validate().stage1.tint_scale == 2
    with pytest.raises(CamoError, match="tint.scale") as e:
        RunSpec.from_options({"scene": "meadow", "tint_scale": 2}).validate()
    assert "\n" not in str(e.value)
    with pytest.raises(CamoError, match="tint.scale"):
        RunSpec.from_options({"scene": "meadow", "tint_match": 4, "tint_scale": -1}).validate()
