"""The warm start's joint albedo and transmittance solve (``--warm-transmittance``, ``--warm-transmittance-low``,
``--warm-transmittance-sun``, optimizer/optimise/warmstart.py, issue 29): where the albedo alone would have to exceed 1 to match the ground, the
transmittance per texel moves so that the required radiance is reachable. Checked against an analytic radiance model
and on a tiny rendered scene whose target the albedo alone cannot reach."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.optimise.warmstart import joint_albedo_transmittance, least_squares_albedo, sun_facing


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


def test_a_floor_keeps_the_sun_facing_texels_from_going_down():
    """Four texels whose target (a bright, nearly opaque body: albedo 1, t = 0.1) needs a lower transmittance than the start 0.5. With a
    per-texel floor at the start on texels 0 and 2 (they face the sun) those keep exactly the start and its clipped
    least-squares albedo; texels 1 and 3 (floor 0) go down to 0.1 as without a floor, and reproduce the target."""
    V, N = 3, 4
    D = np.full((V, N, 3), 1.2)
    G = np.full((V, N, 3), 0.1)
    E = np.full((V, N, 3), 0.01)
    want_a, want_t = 1.0, 0.1  # albedo 1: no higher transmittance reaches it (a unique solution)
    B = _model(want_a, want_t, D, G, E)
    w = np.ones((V, N))
    levels = [0.0, 0.5, 1.0]
    black, white = _renders(levels, D, G, E)
    _, t_free, _, _ = joint_albedo_transmittance(B, black, white, levels, w, start=0.5, steps=41)
    np.testing.assert_allclose(t_free, want_t, atol=1e-6)
    floor = np.array([0.5, 0.0, 0.5, 0.0])
    a, t, ok, raw = joint_albedo_transmittance(B, black, white, levels, w, start=0.5, steps=41, floor=floor)
    assert ok.all()
    np.testing.assert_allclose(t, [0.5, 0.1, 0.5, 0.1], atol=1e-6)
    np.testing.assert_allclose(a[[1, 3]], want_a, atol=1e-4)
    # at the start the model is 0.01 + a (0.6 + 0.025): the target 0.01 + (1.08 + 0.001) needs a = 1.081 / 0.625
    np.testing.assert_allclose(raw[[0, 2]], 1.081 / 0.625, rtol=1e-4)
    assert (a[[0, 2]] == 1.0).all()
    # a floor above a candidate never rejects the start itself (floor 0.9 > start 0.5: the start is kept)
    _, t9, ok9, _ = joint_albedo_transmittance(B, black, white, levels, w, start=0.5, steps=41,
                                               floor=np.full(N, 0.9))
    assert ok9.all() and (t9 >= 0.5 - 1e-7).all()


def test_sun_facing_and_the_scenes_sun(mi_backend):
    """The sun-facing test is the sign of n . s (a cube's six faces, sun from above at 45 degrees in x: the top and
    +x face it, the other four do not); meadow's sun is its sunsky's direction (42 degrees up, azimuth 35), the room
    (an area light) has none."""
    from optimizer.scenes.environments import ENVIRONMENTS, Environment, sun_direction, sun_of

    n = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], float)
    s = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    assert sun_facing(n, s).tolist() == [True, False, True, False, False, False]

    def env(name):
        desc, build, kinds, near, occl = ENVIRONMENTS[name]
        return Environment(name, desc, build, kinds, near, occl)

    np.testing.assert_allclose(sun_of(env("meadow")), sun_direction(42.0, 35.0), atol=1e-12)
    np.testing.assert_allclose(sun_of(env("gravel")), sun_direction(22.0, -60.0), atol=1e-12)
    assert sun_of(env("room")) is None
    assert sun_of(Environment("d", "d", lambda: {"sun": {"type": "directional", "direction": [0, 0, -2]}},
                              ("sun",))).tolist() == [0.0, 0.0, 1.0]


def test_shadow_points_and_which_views_see_them(mi_backend):
    """A unit cube standing on the ground (x, y in [-0.5, 0.5], z in [0, 1]), the sun 45 degrees up from +x. The top
    centre's shadow falls at (-1, 0, 0): a camera on the shadow side (-x) sees it, one on the sun side (+x) does not (the
    cube is in the way), both together do. A point low on the sun-side face casts its shadow under the cube: no view
    sees it; one low on the shadow side, just beside the cube: the shadow-side camera does."""
    import trimesh

    from optimizer.optimise.warmstart import shadow_points, shadow_seen
    from optimizer.rendering import projection
    from optimizer.scenes.cameras import Camera
    from optimizer.scenes.environments import ENVIRONMENTS, Environment

    s = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    p = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 0.01], [-0.5, 0.0, 0.01]])
    np.testing.assert_allclose(shadow_points(p, s), [[-1.0, 0.0, 0.0], [0.49, 0.0, 0.0], [-0.51, 0.0, 0.0]], atol=1e-12)
    with pytest.raises(ValueError, match="horizon"):
        shadow_points(p, np.array([1.0, 0.0, 0.0]))
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    pos = np.asarray(box.vertices) + [0.0, 0.0, 0.5]
    desc, build, kinds, near, occl = ENVIRONMENTS["gravel"]
    sc, shape = projection.object_scene(Environment("gravel", desc, build, kinds, near, occl), pos,
                                        np.asarray(box.faces), np.zeros((len(pos), 2)))
    shade = Camera((-5.0, 0.0, 3.0), (0.0, 0.0, 0.3), 40.0, 32, 32)
    sunny = Camera((5.0, 0.0, 3.0), (0.0, 0.0, 0.3), 40.0, 32, 32)
    assert shadow_seen(sc, shape, [shade], p, s, 0.01).tolist() == [True, False, True]
    assert shadow_seen(sc, shape, [sunny], p, s, 0.01).tolist() == [False, False, False]
    assert shadow_seen(sc, shape, [sunny, shade], p, s, 0.01).tolist() == [True, False, True]


def test_a_scene_without_a_sun_is_refused_where_the_choice_is_read(mi_backend):
    """``warm_transmittance_sun`` on the room (an area light): a one-line library error naming no CLI flag; off, or
    without a floor below the start, the sun is not looked up at all."""
    from types import SimpleNamespace

    from camo_base.errors import CamoError
    from optimizer.optimise.stage1 import Stage1
    from optimizer.scenes.environments import ENVIRONMENTS, Environment

    desc, build, kinds, near, occl = ENVIRONMENTS["room"]
    room = Environment("room", desc, build, kinds, near, occl)
    me = SimpleNamespace(cfg=SimpleNamespace(warm_transmittance_sun="facing"), env=room,
                         _warm_transmittance=lambda: (0.0, 1.0))
    with pytest.raises(CamoError, match="has no sun") as e:
        Stage1._warm_sun(me)
    assert "--" not in str(e.value)
    assert Stage1._warm_sun(SimpleNamespace(**(vars(me) | {"_warm_transmittance": lambda: (None, 1.0)}))) is None
    assert Stage1._warm_sun(SimpleNamespace(**(vars(me) | {"cfg": SimpleNamespace(warm_transmittance_sun="off")}))) \
        is None


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
    # lowered only away from the sun (gravel's low sun): the texels whose outward normal faces it keep >= 0.75, most
    # of the others still go down; the restriction binds: the opaque target is matched worse than by the free solve
    # (here about as badly as by the albedo alone: rms 0.116 against 0.109 and the free solve's < 0.055)
    from optimizer.optimise.warmstart import texel_views
    from optimizer.rendering.appearance import world_normals
    from optimizer.scenes.environments import sun_of

    sun = sun_of(env)
    sunny, info2 = warm_start_albedo(start, g, app, env, s1.cams, integ, target, cov, 16, 3,
                                     transmittance_max=1.0, transmittance_min=0.0, sun=(sun, "facing"))
    tv = texel_views(world_positions(g, start, app), g, t.shape[0], env, s1.cams, target, cov,
                     world_normals(g, start))
    facing = sun_facing(tv.surface.normals[tv.seen], sun)
    assert 0.1 < info2.sun_kept < 0.9 and info2.sun_kept == pytest.approx(facing.mean())
    ts = sunny["transmittance"][..., 0].reshape(-1)[tv.surface.index[tv.seen]]
    assert (ts[facing] >= 0.75 - 1e-6).all()
    assert (ts[~facing] < 0.75 - 1e-6).mean() > 0.5
    assert info1.lowered > info2.lowered > 0.0
    rms2 = float(np.sqrt(np.mean((render(sunny) - target)[full] ** 2)))
    assert rms1 < 0.75 * rms2, (rms1, rms2)
    # lowered only where no view sees the texel's shadow on the ground: exactly those texels may go below 0.75
    from optimizer.optimise.warmstart import shadow_seen
    from optimizer.rendering import projection

    pos = world_positions(g, start, app)
    shaded, info3 = warm_start_albedo(start, g, app, env, s1.cams, integ, target, cov, 16, 3,
                                      transmittance_max=1.0, transmittance_min=0.0, sun=(sun, "shadow"))
    sc, shape = projection.object_scene(env, pos, g.faces, g.uvs)
    kept = shadow_seen(sc, shape, s1.cams, tv.surface.points[tv.seen], sun, 0.01 * float(g.size))
    assert 0.0 < kept.mean() < 1.0 and info3.sun_kept == pytest.approx(kept.mean())
    t3 = shaded["transmittance"][..., 0].reshape(-1)[tv.surface.index[tv.seen]]
    assert (t3[kept] >= 0.75 - 1e-6).all() and (t3[~kept] < 0.75 - 1e-6).any()


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
    # the sun switch: refused where it does nothing (no warm start; no floor below the start), in setting names
    on = {"scene": "meadow", "warm_transmittance": 1.0, "warm_transmittance_low": 0.0, "warm_transmittance_sun": "shadow"}
    assert RunSpec.from_options(on).validate().stage1.warm_transmittance_sun == "shadow"
    assert d.warm_transmittance_sun == "off"
    with pytest.raises(SettingError, match="must be one of off, facing, shadow"):
        RunSpec.from_options(dict(on, warm_transmittance_sun="sunny")).validate()
    with pytest.raises(SettingError, match="stage1.warm_transmittance_low below 1") as e:
        RunSpec.from_options(dict(on, warm_transmittance_low=1.0)).validate()
    assert "--" not in str(e.value)
    with pytest.raises(SettingError, match="warm"):
        RunSpec.from_options(dict(on, preset="paper")).validate()
