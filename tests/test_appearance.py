"""Appearance model: pose composition (Eq. 3), clipping, displacement along normals (Eq. 4), Adam hygiene."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optimizer.rendering.appearance import (AppearanceConfig, Geometry, bilinear_taps, displacement_per_uv_vertex,
                                            initial_values, world_normals)
from optimizer.scenes.pose import clip_offset, euler_xyz_deg, model_matrix, rot_z, scaling, translation
from optimizer.scenes.scenepack import MaterialSpec, ObjectSpec


def test_model_matrix_is_eq3():
    size, rot, t, dt, th = 1.7, (10.0, -20.0, 35.0), (0.3, -0.2, 0.0), (0.01, 0.02, 0.0), 0.4
    expected = translation(dt) @ translation(t) @ rot_z(th) @ euler_xyz_deg(rot) @ scaling(size)
    np.testing.assert_allclose(model_matrix(size, rot, t, dt, th), expected)
    # rotating about z by theta then by the fixed R_z(35 deg) equals one rotation by the sum
    np.testing.assert_allclose(model_matrix(1, (0, 0, 35), (0, 0, 0), theta_z=0.1)[:3, :3],
                               rot_z(math.radians(35) + 0.1)[:3, :3], atol=1e-12)


def test_translation_offset_clipped_to_five_percent_and_dz_zero():
    out = clip_offset([0.5, -0.01, 0.3], size=2.0)
    np.testing.assert_allclose(out, [0.1, -0.01, 0.0])
    np.testing.assert_allclose(clip_offset([0.5, -0.5, 0.3], size=2.0, allow_z=True), [0.1, -0.1, 0.1])


def test_initial_values_follow_the_paper():
    v = initial_values(AppearanceConfig(map_resolution=8, displacement_resolution=4), MaterialSpec())
    assert v["albedo"].shape == (8, 8, 3) and np.all(v["albedo"] == 0.5)
    assert np.all(v["metallic"] == 0) and np.all(v["roughness"] == 0) and np.all(v["transmittance"] == 0.5)
    no_t = initial_values(AppearanceConfig(map_resolution=8, transmittance=False), MaterialSpec())
    assert np.all(no_t["transmittance"] == 0)


def test_bilinear_taps_match_hand_values():
    # 2x2 map, uv at the centre -> the mean of all four texels
    idx, w = bilinear_taps(np.array([[0.5, 0.5], [0.25, 0.25], [0.75, 0.25]]), 2, 2)
    m = np.array([1.0, 2.0, 3.0, 4.0])
    vals = (m[idx] * w).sum(1)
    np.testing.assert_allclose(vals, [2.5, 1.0, 2.0])


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    from optimizer.scenes.mesh import prepare_mesh
    from optimizer.scenes.primitives import make_primitive

    return prepare_mesh(make_primitive("vase"), target_vertices=600, cache_dir=tmp_path_factory.mktemp("cache"))


def test_constant_displacement_moves_vertices_along_normals(prepared):
    app = AppearanceConfig(displacement_resolution=16, displacement_bound=0.05)
    obj = ObjectSpec(primitive="vase", size=2.0, rotation=(0, 0, 30), translation=(1.0, 2.0, 0.0))
    g = Geometry.build(prepared, obj, app)
    p0 = g.positions_np()
    p1 = g.positions_np(np.full((16, 16), 0.6, np.float32))
    moved = p1 - p0
    np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 0.6 * 0.05 * 2.0, rtol=1e-4)
    np.testing.assert_allclose(moved / np.linalg.norm(moved, axis=1, keepdims=True), g.normal, atol=1e-4)


@pytest.mark.parametrize("theta", [0.0, 1.0, math.pi, -2.75])
def test_world_normals_turn_with_the_positions(prepared, theta):
    """Displacing along ``normals_np(theta)`` in the turned frame moves the vertices exactly as displacing along
    ``normal`` before the turn (the normals are in the frame of ``positions_np(.., theta)``); at a turn of pi the
    unturned ``normal`` points the other way in x and y (issue 29: the warm start oriented faces with it)."""
    app = AppearanceConfig(displacement_resolution=16, displacement_bound=0.05)
    g = Geometry.build(prepared, ObjectSpec(primitive="vase", rotation=(0, 0, 30), translation=(1.0, 2.0, 0.0)), app)
    p0 = g.positions_np(None, (0.0, 0.0, 0.0), theta)
    p1 = g.positions_np(np.full((16, 16), 0.6, np.float32), (0.0, 0.0, 0.0), theta)
    n = g.normals_np(theta)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(p1 - p0, 0.6 * 0.05 * n, atol=1e-5)
    np.testing.assert_allclose(world_normals(g, {"rotation": np.array([theta], np.float32)}), n, atol=1e-6)
    if theta == math.pi:
        np.testing.assert_allclose(n[:, :2], -g.normal[:, :2], atol=1e-5)


def test_seam_copies_move_together(prepared):
    app = AppearanceConfig(displacement_resolution=32)
    g = Geometry.build(prepared, ObjectSpec(primitive="vase"), app)
    rng = np.random.default_rng(0)
    d = displacement_per_uv_vertex(rng.uniform(-1, 1, (32, 32)), g.taps, g.uv_to_welded)
    w2u = g.uv_to_welded
    assert len(np.unique(w2u)) < len(w2u), "the test mesh must have seams"
    for w in np.unique(w2u)[:200]:
        copies = np.flatnonzero(w2u == w)
        assert np.ptp(d[copies]) < 1e-12


def test_dr_positions_match_numpy_and_have_pose_gradients(prepared, mi_backend):
    mi, dr = mi_backend
    app = AppearanceConfig(displacement_resolution=16)
    g = Geometry.build(prepared, ObjectSpec(primitive="vase", rotation=(0, 0, 20), translation=(0.5, 0, 0)), app)
    rng = np.random.default_rng(1)
    dmap = rng.uniform(-1, 1, (16, 16, 1)).astype(np.float32)
    dt, th = np.array([0.01, -0.02, 0.0], np.float32), np.array([0.3], np.float32)
    D, DT, TH = mi.TensorXf(dmap), mi.Float(dt), mi.Float(th)
    dr.enable_grad(D, DT, TH)
    pos = g.positions_dr(D, DT, TH)
    np.testing.assert_allclose(np.asarray(pos).reshape(-1, 3), g.positions_np(dmap[..., 0], dt, float(th[0])), atol=1e-5)
    # d(sum of x) / d(dx) = number of vertices; the rotation gradient is finite and non-zero
    xs = dr.gather(mi.Float, pos, dr.arange(mi.UInt32, len(g.base)) * 3)
    dr.backward(dr.sum(xs))
    assert np.asarray(dr.grad(DT))[0] == pytest.approx(len(g.base), rel=1e-5)
    assert np.isfinite(np.asarray(dr.grad(TH))).all() and abs(np.asarray(dr.grad(TH))[0]) > 0
    assert np.abs(np.asarray(dr.grad(D))).sum() > 0


def test_adam_drops_and_counts_nonfinite_gradients(mi_backend):
    mi, dr = mi_backend
    from optimizer.optimise.adam import Adam

    opt = Adam({"x": 0.1})
    opt.add("x", mi.Float([0.5, 0.5, 0.5]))
    dr.set_grad(opt["x"], mi.Float([1.0, float("nan"), float("inf")]))
    assert opt.sanitise_grads() == 2
    opt.step({"x": lambda v: dr.clip(v, 0.0, 1.0)})
    x = np.asarray(opt["x"])
    assert np.isfinite(x).all()
    np.testing.assert_allclose(x, [0.4, 0.5, 0.5], atol=1e-6)


def test_adam_state_round_trip(mi_backend):
    mi, dr = mi_backend
    from optimizer.optimise.adam import Adam

    def run(n, resume_at=None):
        opt = Adam({"x": 0.05})
        opt.add("x", mi.Float([0.2, 0.8]))
        for i in range(n):
            if resume_at == i:
                st = opt.state()
                opt = Adam({"x": 0.05})
                opt.add("x", mi.Float([0.0, 0.0]))
                opt.load_state(st)
            dr.set_grad(opt["x"], mi.Float([1.0 + i, -0.5]))
            opt.step()
        return np.asarray(opt["x"])

    np.testing.assert_array_equal(run(6), run(6, resume_at=3))


def test_adam_iterate_average_is_the_bias_corrected_ema_of_the_projected_iterates(mi_backend):
    """a_t = b a_{t-1} + (1 - b) x_t from 0, read as a_t / (1 - b^t): at t = 1 the iterate itself, and in general
    the weighted mean sum_k (1 - b) b^(t-k) x_k / (1 - b^t) of the clamped iterates; off (0) it is the iterate."""
    mi, dr = mi_backend
    from optimizer.optimise.adam import Adam

    b = 0.8
    opt, plain = Adam({"x": 0.3}, average=b), Adam({"x": 0.3})
    for o in (opt, plain):
        o.add("x", mi.Float([0.5, 0.9]))
    iterates = []
    rng = np.random.default_rng(0)
    for t in range(1, 8):
        g = rng.normal(0.0, 1.0, 2).astype(np.float32) - np.float32(1.0)
        for o in (opt, plain):
            dr.set_grad(o["x"], mi.Float(g))
            o.step({"x": lambda v: dr.clip(v, 0.0, 1.0)})
        x = np.asarray(opt["x"], np.float64)
        np.testing.assert_array_equal(x, np.asarray(plain["x"]))  # the average never feeds back into the descent
        iterates.append(x)
        w = np.array([(1 - b) * b ** (t - k) for k in range(1, t + 1)]) / (1 - b**t)
        want = (w[:, None] * np.array(iterates)).sum(0)
        np.testing.assert_allclose(np.asarray(opt.averaged("x")), want, atol=1e-6)
        np.testing.assert_array_equal(np.asarray(plain.averaged("x")), x)
        assert np.asarray(opt.averaged("x")).max() <= 1.0  # a convex combination stays in the box
    np.testing.assert_allclose(iterates[0], np.asarray(iterates[0]))
    assert not np.allclose(np.asarray(opt.averaged("x")), iterates[-1])


def test_adam_iterate_average_is_nearer_the_optimum_under_noisy_gradients(mi_backend):
    """A quadratic with Monte Carlo-like gradient noise at a constant rate: the iterate jitters by about one rate
    around the optimum with a correlation time of ~sigma / lr = 25 steps; the average of the last ~1 / (1 - b) = 100
    iterates sits several times closer (Polyak-Ruppert). A window shorter than the correlation time helps little."""
    mi, dr = mi_backend
    from optimizer.optimise.adam import Adam

    rng = np.random.default_rng(1)
    opt = Adam({"x": 0.02}, average=0.99)
    opt.add("x", mi.Float(np.zeros(4096, np.float32)))
    target = rng.uniform(0.3, 0.7, 4096).astype(np.float32)
    for _ in range(800):
        x = np.asarray(opt["x"])
        dr.set_grad(opt["x"], mi.Float((x - target + rng.normal(0.0, 0.5, 4096)).astype(np.float32)))
        opt.step()
    err_iterate = np.sqrt(np.mean((np.asarray(opt["x"]) - target) ** 2))
    err_average = np.sqrt(np.mean((np.asarray(opt.averaged("x")) - target) ** 2))
    assert err_average < 0.5 * err_iterate, (err_average, err_iterate)


def test_adam_iterate_average_survives_a_checkpoint_and_rejects_a_bad_decay(mi_backend):
    mi, dr = mi_backend
    from camo_base.errors import CamoError
    from optimizer.optimise.adam import Adam

    def run(n, resume_at=None):
        opt = Adam({"x": 0.05}, average=0.9)
        opt.add("x", mi.Float([0.2, 0.8]))
        for i in range(n):
            if resume_at == i:
                st = opt.state()
                assert set(st) == {"adam_t", "value/x", "m/x", "v/x", "avg/x"}
                opt = Adam({"x": 0.05}, average=0.9)
                opt.add("x", mi.Float([0.0, 0.0]))
                opt.load_state(st)
            dr.set_grad(opt["x"], mi.Float([1.0 + i, -0.5]))
            opt.step()
        return np.asarray(opt.averaged("x"))

    np.testing.assert_array_equal(run(6), run(6, resume_at=3))
    opt = Adam({"x": 0.05}, average=0.9)
    opt.add("x", mi.Float([0.2, 0.8]))
    st = Adam({"x": 0.05}).state()  # a checkpoint of a run without averaging
    st.update({"adam_t": np.array(1), "value/x": np.zeros(2, np.float32), "m/x": np.zeros(2, np.float32),
               "v/x": np.zeros(2, np.float32)})
    with pytest.raises(CamoError, match="no avg/x"):
        opt.load_state(st)
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="decay"):
            Adam({"x": 0.05}, average=bad)
