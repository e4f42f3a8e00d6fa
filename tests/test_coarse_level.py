"""The coarse level under the albedo and transmittance maps (``--coarse-grid K``, optimizer/optimise/coarse.py): its
interpolation against scikit-image's bilinear resize, the Dr.Jit value and gradient against NumPy (``U^T`` of the
fine gradient where the clip is inactive), and in a real Stage 1: the level's gradient is the sum of the map's, it
steps at its own rate, and what the stage hands on is the folded map."""

from __future__ import annotations

import numpy as np
import pytest

from camo_base.errors import CamoError
from fixture_stage1 import tiny_gravel_stage1
from optimizer.optimise import coarse


@pytest.mark.parametrize(("fine", "grid"), [(8, 1), (8, 2), (16, 3), (32, 4), (5, 5)])
def test_upsampling_is_bilinear_resize(fine, grid):
    from skimage.transform import resize

    c = np.random.default_rng(grid).random((grid, grid, 3))
    ref = resize(c, (fine, fine, 3), order=1, mode="edge", anti_aliasing=False)
    np.testing.assert_allclose(coarse.upsample_np(c, fine), ref, atol=1e-12)
    u = coarse.interpolation_matrix(fine, grid)
    np.testing.assert_allclose(u.sum(1), 1.0)  # a constant offset stays constant


def test_fold_clips_to_the_maps_range():
    values = {"albedo": np.full((4, 4, 3), 0.9, np.float32), "rotation": np.zeros(1, np.float32)}
    out = coarse.fold(values, {"albedo": np.array([[[0.3, -0.5, 0.0]]])}, {"albedo": 1e-3})
    assert out["albedo"][0, 0].tolist() == pytest.approx([1.0, 0.4, 0.9])
    assert out["rotation"] is values["rotation"] and values["albedo"][0, 0, 0] == pytest.approx(0.9)


def test_dr_value_and_gradient_against_numpy(mi_backend):
    mi, dr = mi_backend
    rng = np.random.default_rng(3)
    R, K, low = 12, 3, 1e-3
    fine = rng.random((R, R, 3)).astype(np.float32)
    c = (0.4 * rng.standard_normal((K, K, 3))).astype(np.float32)  # large enough that some texels clip
    G = rng.standard_normal((R, R, 3)).astype(np.float32)
    level = coarse.CoarseLevel(R, K, {"albedo": 3})
    f_dr, c_dr = mi.TensorXf(fine), mi.TensorXf(c)
    dr.enable_grad(f_dr, c_dr)
    out = level.add(f_dr, c_dr, low)
    raw = fine + coarse.upsample_np(c, R)
    np.testing.assert_allclose(np.asarray(out), np.clip(raw, low, 1.0), atol=1e-6)
    dr.backward(dr.sum(out.array * mi.Float(G.ravel())))
    inside = (raw > low) & (raw < 1.0)
    assert 0.05 < 1 - inside.mean() < 0.95  # the clip matters in this test
    u = coarse.interpolation_matrix(R, K)
    want = np.einsum("ik,ijc,jl->klc", u, G * inside, u)  # U^T (G where the clip is inactive)
    np.testing.assert_allclose(np.asarray(dr.grad(c_dr)), want, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(np.asarray(dr.grad(f_dr)), G * inside, atol=1e-6)


def test_grid_bounds():
    with pytest.raises(ValueError, match="1 to 8"):
        coarse.CoarseLevel(8, 9, {"albedo": 3})
    with pytest.raises(ValueError):
        coarse.interpolation_taps(4, 0)


def test_stage1_level_gradient_rate_and_fold(mi_backend):
    """A real Stage 1 on gravel (2 views, 24 px, one thread): with one cell the level's gradient is the sum of its
    map's texel gradients (the chain rule through the constant offset), its first Adam step is its own rate, the
    rendered map is the folded one and the stage's result has no level left in it."""
    mi, dr = mi_backend
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        s1 = tiny_gravel_stage1(False, coarse_grid=1, coarse_lr=0.05)
        assert set(s1._coarse.channels) == {"albedo", "transmittance"}
        _, grads = s1.gradient()
        for name in ("albedo", "transmittance"):
            g = grads[f"{name}_coarse"].reshape(-1)
            assert np.abs(g).max() > 0
            np.testing.assert_allclose(g, grads[name].reshape(-1, g.size).sum(0), rtol=1e-3,
                                       atol=1e-4 * np.abs(g).max())
        rec = s1.step()
        for name in ("albedo", "transmittance"):
            step = np.abs(np.asarray(rec["coarse_offset"][name]))
            np.testing.assert_allclose(step[step > 0], 0.05, rtol=5e-4)  # Adam's first step: the rate (logged to 5 digits)
        before = s1.current_values()
        assert not any(k.endswith("_coarse") for k in before)
        s1.opt.values["albedo_coarse"] = mi.TensorXf(np.array([[[0.2, -0.3, 0.0]]], np.float32))
        folded = s1.current_values()["albedo"]
        fine = np.asarray(s1.opt["albedo"]).reshape(folded.shape)
        np.testing.assert_allclose(folded, np.clip(fine + [0.2, -0.3, 0.0], 1e-3, 1.0), atol=1e-6)
        rendered = np.asarray(s1._mapped()[s1._keys["albedo"]]).reshape(folded.shape)
        np.testing.assert_allclose(rendered, folded, atol=1e-6)
        # off: no level, the map renders as it is
        s0 = tiny_gravel_stage1(False)
        assert s0._coarse is None and "albedo_coarse" not in s0.opt
    finally:
        dr.set_thread_count(threads)


def test_options_and_errors():
    from optimizer.optimise.spec import RunSpec

    spec = RunSpec.from_options({"scene": "meadow", "coarse_grid": 4, "coarse_lr": 0.03}).validate()
    assert (spec.stage1.coarse_grid, spec.stage1.coarse_lr) == (4, 0.03)
    # the fast preset (the default) has one offset per channel; the paper preset and --coarse-grid 0 have none
    assert RunSpec.from_options({"scene": "meadow"}).validate().stage1.coarse_grid == 1
    assert RunSpec.from_options({"scene": "meadow", "preset": "fast"}).validate().stage1.coarse_grid == 1
    assert RunSpec.from_options({"scene": "meadow", "preset": "paper"}).validate().stage1.coarse_grid == 0
    assert RunSpec.from_options({"scene": "meadow", "coarse_grid": 0}).validate().stage1.coarse_grid == 0
    # a rate for the default level is accepted; a rate without a level is not
    assert RunSpec.from_options({"scene": "meadow", "coarse_lr": 0.03}).validate().stage1.coarse_lr == 0.03
    for off in ({"coarse_grid": 0}, {"preset": "paper"}):
        with pytest.raises(CamoError, match="coarse.lr") as e:
            RunSpec.from_options({"scene": "meadow", "coarse_lr": 0.03, **off}).validate()
        assert "\n" not in str(e.value)
    with pytest.raises(CamoError, match="coarse.grid") as e:
        RunSpec.from_options({"scene": "meadow", "coarse_grid": 64, "map_resolution": 32}).validate()
    assert "\n" not in str(e.value)
