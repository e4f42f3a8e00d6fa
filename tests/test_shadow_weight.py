"""The shadow's weight in Stage 1's loss (``--shadow-weight W``, optimizer/optimise/stage1.py ``shadow_weighted``,
issue 29): the weights on hand-made masks, a real tiny Stage 1's per-view loss against the NumPy reference with those
weights, and the one-line option errors."""

from __future__ import annotations

import numpy as np
import pytest

from camo.cli import main
from optimizer.optimise.stage1 import shadow_weighted


def test_shadow_weighted_scales_only_the_pixels_away_from_the_object():
    domain = np.zeros((7, 9), np.float32)
    domain[1:6, 1:8] = 1.0
    coverage = np.zeros((7, 9), np.float32)
    coverage[3, 2] = 0.3  # one partly covered pixel: the object
    w = shadow_weighted(domain, coverage, 4.0)
    ring = {(3, 2), (2, 2), (4, 2), (3, 1), (3, 3)}  # the object's pixel and its 1-px (4-connected) ring
    for y in range(7):
        for x in range(9):
            want = 0.0 if domain[y, x] == 0 else (1.0 if (y, x) in ring else 4.0)
            assert w[y, x] == want, (y, x)
    assert w.dtype == np.float32 and domain[1, 1] == 1.0  # the input is not changed
    np.testing.assert_array_equal(shadow_weighted(domain, coverage, 1.0), domain)
    zero = shadow_weighted(domain, coverage, 0.0)
    assert zero.sum() == 5.0  # the object alone


def test_stage1_loss_weighs_the_shadow(mi_backend):
    """A real tiny Stage 1 (the frame domain): its per-view loss of a known image is the NumPy squared error with
    weight 3 outside the object and its ring and 1 on it (and the plain mean with the default weight)."""
    import mitsuba as mi

    from fixture_stage1 import tiny_gravel_stage1
    from optimizer.optimise.loss import mse_loss_np

    s1 = tiny_gravel_stage1(False, shadow_weight=3.0)
    plain = tiny_gravel_stage1(False)
    v = 0
    bg = np.asarray(s1.targets.background[v], np.float64)
    cov = s1.targets.coverage[v]
    assert (cov > 0).any() and (cov == 0).any()
    rng = np.random.default_rng(1)
    img = (bg + rng.uniform(0.0, 0.2, bg.shape)).astype(np.float32)
    weights = np.where(shadow_weighted(np.ones(cov.shape, np.float32), cov, 1.0) > 0, 1.0, 0.0)
    near = shadow_weighted(np.ones(cov.shape, np.float32), cov, 0.0)  # 1 on the object and its ring, 0 elsewhere
    weights = np.where(near > 0, 1.0, 3.0) * weights
    got = float(s1._view_loss(mi.TensorXf(img), v)[0][0])
    want = mse_loss_np(img, bg, weights)
    assert got == pytest.approx(want, rel=1e-5)
    got_plain = float(plain._view_loss(mi.TensorXf(img), v)[0][0])
    assert got_plain == pytest.approx(mse_loss_np(img, bg, None), rel=1e-5)
    assert abs(got - got_plain) > 1e-3 * got_plain  # the weight changed the loss


@pytest.mark.parametrize("value", ["-1", "nan", "2000", "x"])
def test_shadow_weight_bad_values_are_one_line_errors(tmp_path, capsys, value):
    assert main(["optimize", "meadow", "--out", str(tmp_path / "run"), "--shadow-weight", value]) == 2
    err = capsys.readouterr().err.strip()
    assert "--shadow-weight" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run").exists()
