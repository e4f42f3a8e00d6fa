"""The detail term of Stage 1 (``--detail-match``, optimizer/optimise/detail.py, issue 29): the interior taps, the
texture energy against kornia's Laplacian and hand-computed cases, the cross-product estimate's noise immunity, the
surrogate's image gradient against central differences of the term, the option's parsing and range, and Stage 1's
use of it through a real Mitsuba render (no term on the first step, the term's gradient on the next, the previous
render in the checkpoint)."""

from __future__ import annotations

import numpy as np
import pytest

from fixture_stage1 import tiny_gravel_stage1
from optimizer.optimise import detail


def test_interior_taps_of_a_mask_with_a_hole():
    covered = np.ones((5, 6), bool)
    covered[2, 3] = False  # a hole: every pixel whose 3x3 neighbourhood holds (2, 3) leaves the interior
    taps = detail.interior_taps(covered)
    centres = sorted((int(i) // 6, int(i) % 6) for i in taps[0])
    assert centres == [(1, 1), (2, 1), (3, 1)]  # column 1 only: columns 2-4 touch the hole, row 0/4 the border
    assert taps[1:, 0].tolist() == [0, 1, 2, 6, 8, 12, 13, 14]  # (1, 1)'s neighbours in a 6-wide image
    film = detail.interior_taps(covered, column_offset=12, width=24)  # third view of a 4-view film
    assert film[0].tolist() == [25 + 12, 49 + 12, 73 + 12]
    assert detail.interior_taps(np.ones((2, 9), bool)).shape == (9, 0)  # too thin for a 3x3 neighbourhood


def test_energy_is_kornias_laplacian_squared_on_the_interior():
    import kornia
    import torch

    rng = np.random.default_rng(0)
    img = rng.random((12, 10, 3))
    covered = np.zeros((12, 10), bool)
    covered[2:11, 1:8] = True
    taps = detail.interior_taps(covered)
    y = torch.tensor(detail.luma_np(img))[None, None]
    lap = kornia.filters.laplacian(y, 3, border_type="reflect", normalized=False)[0, 0].numpy()
    inner = np.zeros_like(covered)
    inner[3:10, 2:7] = True
    assert detail.energy_np(img, img, taps) == pytest.approx(float(np.mean(lap[inner] ** 2)), rel=1e-12)
    # a uniform image (and an affine ramp) has none
    ramp = np.broadcast_to((np.arange(10) * 0.1)[None, :, None], (12, 10, 3))
    assert detail.energy_np(ramp, ramp, taps) == pytest.approx(0.0, abs=1e-24)
    assert np.isnan(detail.energy_np(img, img, np.zeros((9, 0), np.int64)))


def test_the_cross_product_does_not_count_render_noise():
    """Two renders of one flat body with independent noise of sigma 0.1: each alone has energy G sigma^2 = 0.72; their
    product has ~0 (the standard error of the mean of n products of independent ~N(0, 0.72) values)."""
    rng = np.random.default_rng(1)
    taps = detail.interior_taps(np.ones((130, 130), bool))
    a, b = (0.5 + 0.1 * rng.standard_normal((130, 130, 1)) * np.ones(3) for _ in range(2))
    scale = 1.0 / float(np.sum(detail.REC709_LUMA))  # unit luma per unit channel
    a, b = 0.5 + (a - 0.5) * scale, 0.5 + (b - 0.5) * scale
    assert detail.energy_np(a, a, taps) == pytest.approx(detail.GAIN * 0.01, rel=0.05)
    assert abs(detail.energy_np(a, b, taps)) < 4 * detail.GAIN * 0.01 / np.sqrt(taps.shape[1]) * 2


def test_term_value_and_floor():
    # matched energy: 0; no grain against a target of rms 0.01 per pixel (E* = G 1e-4) at share 1, W = 4:
    # W / (4 G E*) E*^2 = E* / G = 1e-4 (the squared error the missing grain costs)
    assert detail.term_np(3.0, 3.0, 0.7, 8.0) == 0.0
    assert detail.term_np(0.0, detail.GAIN * 1e-4, 1.0, 4.0) == pytest.approx(1e-4)
    # a flat ground (E* = 0) uses the floor G 1e-6: 1 / (4 G^2 1e-6) x E^2 at W = 1, s = 1
    assert detail.coefficient(0.0, 1.0, 1.0) == pytest.approx(1.0 / (4 * detail.GAIN**2 * 1e-6))


def test_surrogate_gradient_is_the_terms_gradient(mi_backend):
    """With the previous render equal to this one, the surrogate's gradient with respect to the image is the gradient
    of ``coef (E(x, x) - E*)^2`` (central differences on a float64 copy); its value is logged in ``last``."""
    mi, dr = mi_backend
    rng = np.random.default_rng(2)
    h, w = 7, 8
    img = rng.random((h, w, 3)).astype(np.float32)
    target = rng.random((h, w, 3)).astype(np.float32) * 2.0
    covered = np.ones((h, w), bool)
    covered[0, 0] = False
    term = detail.DetailTerm([target], [covered], [0.6], 8.0)
    x = mi.TensorXf(img)
    assert term.surrogate([x], [(0, 0)]) is None  # the first step: no previous render
    assert term.last == {"value": 0.0, "ratio": None}
    dr.enable_grad(x)
    s = term.surrogate([x], [(0, 0)])
    dr.backward(s)
    grad = np.asarray(dr.grad(x), np.float64)
    taps = term.taps[0]

    def value(im):
        return detail.term_np(detail.energy_np(im, im, taps), term.target[0], 0.6, 8.0)

    assert term.last["value"] == pytest.approx(value(img.astype(np.float64)), rel=1e-5)
    e = detail.energy_np(img, img, taps)
    assert term.last["ratio"] == pytest.approx(np.sqrt(e / term.target[0]), rel=1e-6)
    num = np.zeros_like(grad)
    base = img.astype(np.float64)
    for idx in np.ndindex(*base.shape):
        up, dn = base.copy(), base.copy()
        up[idx] += 1e-5
        dn[idx] -= 1e-5
        num[idx] = (value(up) - value(dn)) / 2e-5
    assert np.abs(num).max() > 0
    np.testing.assert_allclose(grad, num, rtol=1e-3, atol=1e-4 * np.abs(num).max())


@pytest.mark.parametrize("batched", [False, True], ids=["per-view", "batch-film"])
def test_stage1_adds_the_term_from_its_second_render(mi_backend, batched):
    """A real Stage 1 on gravel (2 views, 24 px): the first ``gradient()`` has no previous render, so its gradient is
    the photometric loss's; the second (same seeds, one thread: the same renders) adds the term, whose value is
    ``term_np`` of the renders' own energy; the previous render travels in the checkpoint."""
    _, dr = mi_backend
    s1 = tiny_gravel_stage1(batched, detail_match=50.0)
    assert s1._detail is not None and s1._batched == batched
    assert sum(t.shape[1] for t in s1._detail.taps) > 0
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        loss0, first = s1.gradient()
        assert s1._detail.last == {"value": 0.0, "ratio": None}
        loss1, second = s1.gradient()
    finally:
        dr.set_thread_count(threads)
    assert loss1 == pytest.approx(loss0)  # the same renders: the photometric loss alone is logged as before
    value, ratio = s1._detail.last["value"], s1._detail.last["ratio"]
    assert value > 0 and ratio is not None and ratio >= 0
    diff = np.abs(second["albedo"] - first["albedo"]).max()
    assert diff > 1e-3 * np.abs(first["albedo"]).max()  # the term moved the albedo's gradient
    state = s1.checkpoint_state()
    keys = sorted(k for k in state if k.startswith("detail_prev/"))
    assert keys == (["detail_prev/0"] if batched else ["detail_prev/0", "detail_prev/1"])
    s1._detail.previous = {}
    s1.load_checkpoint_state(state)
    for k in keys:
        np.testing.assert_array_equal(s1._detail.previous[int(k.split("/")[1])], state[k])
