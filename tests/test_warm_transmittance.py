"""The warm start's joint albedo and transmittance solve (``--warm-transmittance``, ``--warm-transmittance-low``,
optimizer/optimise/warmstart.py, issue 29): where the albedo alone would have to exceed 1 to match the ground, the
transmittance per texel moves so that the required radiance is reachable. Checked against an analytic radiance model
and on a tiny rendered scene whose target the albedo alone cannot reach."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.optimise.warmstart import joint_albedo_transmittance, least_squares_albedo


def _model(a, t, D, G, E):
    """Radiance of a texel at albedo ``a`` and transmittance ``t``: a diffuse part ``(1 - t) D``, light through the
    body crossing two interfaces ``t^2 G`` (both tinted by the albedo) and an albedo-free part ``E`` (reflection)."""
    return E + a * ((1.0 - t) * D + t * t * G)


def _renders(levels, D, G, E):
    return ([_model(0.0, t, D, G, E) for t in levels], [_model(1.0, t, D, G, E) for t in levels])


def test_joint_solve_reproduces_a_radiance_the_albedo_alone_cannot_reach():
    """Three texels in two views, start transmittance 0.5, quadratic model (the solve's interpolation is exact):
    texel 0 needs light through the body (bright ground behind, dim diffuse): at t = 0.5 it would need albedo 1.6;
    texel 1 needs a more diffuse body (sunlit top, dark ground behind): albedo alone clips too; texel 2 is matched at
    the start and keeps it. The solved (albedo, transmittance) reproduce every target radiance."""
    V, N = 2, 3
    D = np.array([[0.2, 1.2, 0.4]] * V)[..., None] * np.ones(3)  # (V, N, 3)
    G = np.array([[1.0, 0.1, 0.4]] * V)[..., None] * np.ones(3)
    E = np.full((V, N, 3), 0.01)
    want_a = np.array([[0.7, 0.6, 0.5], [0.9, 0.8, 0.7], [0.3, 0.5, 0.4]])
    want_t = np.array([0.95, 0.1, 0.5])
    B = _model(want_a[None], want_t[None, :, None], D, G, E)
    w = np.ones((V, N))
    levels = [0.0, 0.5, 1.0]
    black, white = _renders(levels, D, G, E)
    # the albedo alone at the start (t = 0.5) clips above 1 on texels 0 and 1
    _, _, raw0 = least_squares_albedo(B, black[1], white[1], w)
    assert (raw0[0] > 1.0).any() and (raw0[1] > 1.0).any() and (raw0[2] <= 1.0).all()
    a, t, ok, raw = joint_albedo_transmittance(B, black, white, levels, w, start=0.5, steps=41)
    assert ok.all() and np.isfinite(a).all() and (a >= 0).all() and (a <= 1).all()
    assert t[0] > 0.5 and t[1] < 0.5 and t[2] == pytest.approx(0.5)
    np.testing.assert_allclose(a[2], want_a[2], atol=1e-5)  # the start matched: kept, albedo exact
    got = _model(a[None].astype(np.float64), t[None, :, None].astype(np.float64), D, G, E)
    # every target reproduced to within the grid's step (0.025 in t)
    np.testing.assert_allclose(got, B, atol=0.02)
    assert np.abs(got - B).max() < 0.1 * np.abs(_model(np.clip(raw0, 0, 1)[None], 0.5, D, G, E) - B).max()


def test_joint_solve_ignores_nonfinite_and_unseen_and_keeps_the_start_without_a_range():
    """A NaN target view carries no weight, an unseen texel is unassigned and keeps the start, and a range of one
    level (nothing to choose) gives the plain least-squares albedo."""
    V, N = 2, 2
    D, G, E = np.full((V, N, 3), 0.5), np.full((V, N, 3), 0.5), np.zeros((V, N, 3))
    B = _model(0.4, 0.5, D, G, E)
    B[0, 0] = np.nan
    w = np.ones((V, N))
    w[:, 1] = 0.0
    levels = [0.25, 0.5, 0.75]
    black, white = _renders(levels, D, G, E)
    a, t, ok, _ = joint_albedo_transmittance(B, black, white, levels, w, start=0.5)
    assert ok.tolist() == [True, False] and t[1] == pytest.approx(0.5)
    assert np.isfinite(a).all()
    # at t = 0.5 the model gives 0.4 * 0.375 = 0.15 exactly: the start is an exact fit, kept
    assert t[0] == pytest.approx(0.5) and a[0] == pytest.approx(0.4, abs=1e-5)
    plain, ok1, _ = least_squares_albedo(B, black[1], white[1], w)
    a1, t1, ok2, _ = joint_albedo_transmittance(B, [black[1]], [white[1]], [0.5], w)
    np.testing.assert_allclose(a1, plain)
    np.testing.assert_array_equal(ok1, ok2)
    assert (t1 == 0.5).all()


@pytest.mark.slow
def test_warm_start_reaches_an_opaque_target_the_transmissive_start_cannot(mi_backend):
    """A tiny rendered scene (gravel's box at 24 px): the target is the box itself, opaque (transmittance 0) with
    albedo 0.8. From the fast preset's transmittance start 0.75 the albedo alone cannot reach it (it would need an
    albedo above 1 on most texels); the joint solve over [0, 1] lowers the transmittance and the box rendered with
    the solved maps reproduces the target radiance on the pixels it covers fully, far closer than the albedo alone."""
    mi, dr = mi_backend
    from test_convergence import tiny_box_stage

    from optimizer.rendering import scene as scn
    from optimizer.rendering.appearance import object_bsdf, world_positions
    from optimizer.rendering.render import render_shaded
    from optimizer.optimise.warmstart import warm_start_albedo

    dr.set_thread_count(1)
    s1, app, env = tiny_box_stage(views=3)
    g, integ, cov = s1.geometry, s1.shading_integrator(), s1.targets.coverage

    def render(vals, spp=64):
        pos = world_positions(g, vals, app)
        return render_shaded(env.build(), scn.object_mesh(pos, g.faces, g.uvs, object_bsdf(vals, app)), s1.cams,
                             integ, spp, 5)

    base = dict(s1.values)
    target = render(dict(base, albedo=np.full_like(base["albedo"], 0.8),
                         transmittance=np.zeros_like(base["transmittance"])))
    start = dict(base, transmittance=np.full_like(base["transmittance"], 0.75))
    full = cov >= 0.999
    alone, info0 = warm_start_albedo(start, g, app, env, s1.cams, integ, target, cov, 16, 3)
    joint, info1 = warm_start_albedo(start, g, app, env, s1.cams, integ, target, cov, 16, 3,
                                     transmittance_max=1.0, transmittance_min=0.0)
    rms0 = float(np.sqrt(np.mean((render(alone) - target)[full] ** 2)))
    rms1 = float(np.sqrt(np.mean((render(joint) - target)[full] ** 2)))
    assert info0.clipped_high > 0.7 and info0.clipped_high_after is None
    assert info1.clipped_high_after < 0.4 and info1.lowered > 0.5
    assert info1.mean_transmittance < 0.5
    np.testing.assert_array_equal(alone["transmittance"], start["transmittance"])  # the albedo alone: map untouched
    t = joint["transmittance"]
    assert t.shape == start["transmittance"].shape and t.min() >= 0.0 and t.max() <= 1.0
    assert rms1 < 0.5 * rms0, (rms0, rms1)


def test_warm_transmittance_needs_the_warm_start():
    from camo_base.errors import SettingError
    from optimizer.optimise.spec import RunSpec

    s = RunSpec.from_options({"scene": "meadow", "warm_transmittance": 1.0, "warm_transmittance_low": 0.0}).validate()
    assert (s.stage1.warm_transmittance, s.stage1.warm_transmittance_low) == (1.0, 0.0)
    d = RunSpec.from_options({"scene": "meadow"}).validate().stage1
    assert (d.warm_transmittance, d.warm_transmittance_low) == (0.0, 1.0)  # off by default
    with pytest.raises(SettingError, match="warm"):
        RunSpec.from_options({"scene": "meadow", "preset": "paper", "warm_transmittance": 1.0}).validate()
    with pytest.raises(SettingError):
        RunSpec.from_options({"scene": "meadow", "warm_transmittance": 1.5}).validate()
