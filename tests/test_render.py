"""Rendering core: masks are the object's visible projection, depth is in scene units,
and the background render equals the full render away from the object and its shadow."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.rendering import scene as scn
from optimizer.scenes.cameras import Camera
from optimizer.scenes.environments import ENVIRONMENTS
from optimizer.rendering.render import coverage_and_depth, render_shaded, render_views, split_batch


def _box_obj():
    import trimesh

    m = trimesh.creation.box([0.8, 0.6, 1.0])
    m.apply_translation([0.0, 0.0, 0.5])
    return m


def _obj_fn(m, bsdf):
    return lambda: scn.object_mesh(m.vertices, m.faces, None, bsdf)


CAMS = [Camera((4.0, 0.0, 1.8), (0.0, 0.0, 0.4), 30.0, 40, 32), Camera((0.0, -4.0, 1.6), (0.0, 0.0, 0.4), 30.0, 40, 32)]


def test_split_batch_layout():
    img = np.arange(2 * 6 * 1, dtype=np.float32).reshape(2, 6, 1)  # H=2, 3 views of W=2
    out = split_batch(img, 3)
    assert out.shape == (3, 2, 2, 1)
    np.testing.assert_array_equal(out[1, :, :, 0], [[2, 3], [8, 9]])


def test_mask_equals_emitter_render_with_occluders(mi_backend):
    """Coverage from ray casting == a render where only the object emits (occluders kept, all else black)."""
    m = _box_obj()
    elements = {k: v for k, v in ENVIRONMENTS["occluded"][1]().items() if k != "sky"}
    for v in elements.values():
        v["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    emitter_obj = scn.object_mesh(m.vertices, m.faces, None, {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}})
    mi, dr = mi_backend
    # An emitting copy: same geometry with an area emitter.
    emitting = mi.load_dict({"type": "ply", "filename": _ply(m), "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}},
                             "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}}})
    cam = Camera((4.0, 0.3, 1.0), (0.0, 0.0, 0.4), 30.0, 48, 40)  # the low wall hides the box's lower part
    emit = render_shaded(elements, emitting, [cam], {"type": "path", "max_depth": 1}, spp=256, seed=3)[0, ..., 0]
    sc = scn.build_scene(elements, emitter_obj)
    cov, _ = coverage_and_depth(sc, cam, emitter_obj, ss=8)
    assert 0.05 < cov.mean() < 0.5
    full = (cov > 0.999).sum()
    assert full > 50
    # partly occluded: the wall hides part of the box's lower half
    assert (cov[-10:] > 0.5).sum() < (cov[:25] > 0.5).sum()
    np.testing.assert_allclose(cov, emit, atol=0.13)
    assert np.abs(cov - emit).mean() < 0.01


_PLY = {}


def _ply(m):
    import tempfile

    if id(m) not in _PLY:
        path = tempfile.NamedTemporaryFile(suffix=".ply", delete=False).name
        m.export(path)
        _PLY[id(m)] = path
    return _PLY[id(m)]


def test_depth_is_distance_in_scene_units(mi_backend):
    elements = {"ground": {"type": "rectangle", "to_world": __import__("mitsuba").ScalarTransform4f().scale([10, 10, 1])}}
    cam = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), 40.0, 33, 33, up=(0.0, 1.0, 0.0))
    _, depth = coverage_and_depth(scn.build_scene(elements), cam, ss=1)
    assert depth[16, 16] == pytest.approx(3.0, rel=1e-4)
    # a pixel off-centre: distance = 3 / cos(angle to the axis)
    assert depth[16, 0] > depth[16, 16] and depth[16, 0] == pytest.approx(depth[16, -1], rel=1e-4)
    sky_cam = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 6.0), 40.0, 8, 8, up=(0.0, 1.0, 0.0))
    _, sky = coverage_and_depth(scn.build_scene(elements), sky_cam, ss=1)
    assert np.all(sky == 0)


def test_background_equals_full_render_away_from_object(mi_backend):
    m = _box_obj()
    build = ENVIRONMENTS["gravel"][1]
    bsdf = scn.principled({"albedo": (0.5, 0.5, 0.5), "metallic": 0.0, "roughness": 0.0, "transmittance": 0.0})
    vr = render_views(build, _obj_fn(m, bsdf), CAMS, {"type": "path", "max_depth": 3}, spp=16, seed=5)
    assert vr.background.shape == (2, 32, 40, 3) and vr.mask.shape == (2, 32, 40)
    from optimizer.optimise.stage1 import influence_domain

    for v in range(2):
        dom = influence_domain(vr.background[v], vr.with_object[v], vr.coverage[v], 0.05, 3) > 0
        outside = ~dom
        diff = np.abs(vr.background[v] - vr.with_object[v])[outside]
        # same seed: paths that never meet the object are identical
        assert np.median(diff) == 0.0
        assert diff.mean() < 0.02 * vr.background[v].mean()  # indirect light off the object
        # inside the mask the object changes the image
        assert np.abs(vr.background[v] - vr.with_object[v])[vr.mask[v]].mean() > 0.05 * vr.background[v].mean()
        # its shadow is darker than the background there (the sun is at 22 degrees elevation)
        shadow = dom & ~vr.mask[v]
        assert (vr.with_object[v][shadow].mean() < vr.background[v][shadow].mean())
    assert np.all(vr.depth > 0)  # the ground is everywhere below the horizon


def test_a_views_coverage_does_not_depend_on_the_other_views_in_its_launch(mi_backend):
    """coverage_and_depth_views traces every view in one launch (coverage_and_depth is its one-view case): each
    view's coverage is bit for bit and its depth to float rounding what it is when traced alone, whatever the other
    views and their order, with and without the object (a wrong offset into the wavefront fails)."""
    from optimizer.rendering.render import coverage_and_depth_views

    build = ENVIRONMENTS["meadow"][1]
    obj = _obj_fn(_box_obj(), scn.principled({"albedo": (0.5, 0.5, 0.5), "metallic": 0.0, "roughness": 0.5,
                                               "transmittance": 0.0}))()
    cams = CAMS + [Camera((2.0, 3.0, 1.0), (0.0, 0.0, 0.4), 40.0, 40, 32)]
    for sc, target in ((scn.build_scene(build(), obj), obj), (scn.build_scene(build()), None)):
        for order in (cams, cams[::-1]):
            cov, depth = coverage_and_depth_views(sc, order, target, ss=3)
            for v, c in enumerate(order):
                cv, d = coverage_and_depth(sc, c, target, ss=3)
                assert cv.shape == (c.height, c.width)
                np.testing.assert_array_equal(cov[v], cv)
                np.testing.assert_allclose(depth[v], d, rtol=1e-6, atol=1e-6)
        assert (cov.max() > 0.5) == (target is not None)


def test_the_objects_coverage_traced_on_its_box_only_is_the_full_pass(mi_backend):
    """object_coverage_views (the evaluation's with-object renders) traces only the pixels whose rays can meet the
    object's box: its coverage is bit for bit the full pass's, the object covers some pixels and not all, and a
    camera with the box behind it (no bound) traces every pixel and still agrees."""
    from optimizer.rendering.region import box_pixels
    from optimizer.rendering.render import coverage_and_depth_views, object_coverage_views

    build = ENVIRONMENTS["meadow"][1]
    obj = _obj_fn(_box_obj(), scn.principled({"albedo": (0.5, 0.5, 0.5), "metallic": 0.0, "roughness": 0.5,
                                               "transmittance": 0.0}))()
    inside = Camera((0.0, 0.0, 0.4), (1.0, 0.0, 0.4), 60.0, 40, 32)  # in the box: corners behind it
    cams = CAMS + [Camera((2.0, 3.0, 1.0), (0.0, 0.0, 0.4), 40.0, 40, 32), inside]
    sc = scn.build_scene(build(), obj)
    full = coverage_and_depth_views(sc, cams, obj, ss=3)[0]
    box = object_coverage_views(sc, cams, obj, ss=3)
    for v in range(len(cams)):
        np.testing.assert_array_equal(box[v], full[v])
    assert 0 < (full[0] > 0).mean() < 1
    px = box_pixels(obj, cams)
    assert px[-1] is None and all(p.size < c.width * c.height for p, c in zip(px[:-1], cams[:-1]))


def test_surface_normals_are_the_room_s_planes_facing_the_camera(mi_backend):
    """surface_normals_views (the observer's surfaces): inside the built-in room, looking at its north wall from
    1.2 m up, the lowest rows see the floor (normal +z), the middle rows the north wall (its normal, -y, towards
    the camera), the top row the ceiling (-z: each rectangle is turned towards the camera whatever its own
    orientation); the depth is the ray's hit distance, as coverage_and_depth_views' at one ray a pixel."""
    from optimizer.rendering.render import coverage_and_depth_views, surface_normals_views

    sc = scn.build_scene(ENVIRONMENTS["room"][1]())
    cams = [Camera((0.0, 0.0, 1.2), (0.0, 6.5, 1.2), 100.0, 48, 40),
            Camera((0.0, -3.0, 2.0), (0.0, 0.0, 0.0), 50.0, 48, 40)]
    normals, depth = surface_normals_views(sc, cams)
    assert normals.shape == (2, 40, 48, 3) and depth.shape == (2, 40, 48) and normals.dtype == np.float32
    n = normals[0]
    np.testing.assert_allclose(n[-1, 24], (0.0, 0.0, 1.0), atol=1e-4)  # floor
    np.testing.assert_allclose(n[20, 24], (0.0, -1.0, 0.0), atol=1e-4)  # north wall, towards the camera
    np.testing.assert_allclose(n[0, 24], (0.0, 0.0, -1.0), atol=1e-4)  # ceiling
    assert (depth[0] > 0).all()  # the room is closed: every ray hits a surface
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    assert depth[0, 20, 24] == pytest.approx(6.5, abs=0.05)  # the wall at y = 6.5, straight ahead
    np.testing.assert_allclose(depth[0], coverage_and_depth_views(sc, cams[:1], None, ss=1)[1][0], rtol=1e-5)
    down = normals[1][10:, :]  # the second view looks down at the floor
    assert (down[..., 2] > 0.9999).all()


def test_the_built_in_room_is_closed_walls_meet_at_its_corners(mi_backend):
    """The room's four walls are 13 m wide and 4 m high and meet at the corners: a wide view into each corner
    from the middle of the room hits a surface at every pixel, the east wall's normal is -x at eye height,
    and no wall reaches above the ceiling (a ray just under the ceiling towards a corner ends within the
    corner's distance, 6.5 * sqrt(2) ~ 9.19 m)."""
    from optimizer.rendering.render import surface_normals_views

    sc = scn.build_scene(ENVIRONMENTS["room"][1]())
    corners = [(6.5, 6.5), (-6.5, 6.5), (6.5, -6.5), (-6.5, -6.5)]
    cams = [Camera((0.0, 0.0, 2.0), (x, y, 2.0), 90.0, 32, 32) for x, y in corners]
    cams.append(Camera((0.0, 0.0, 1.2), (6.5, 0.0, 1.2), 30.0, 32, 32))
    cams.append(Camera((0.0, 0.0, 3.9), (6.5, 6.5, 3.9), 1.0, 32, 32))
    normals, depth = surface_normals_views(sc, cams)
    assert (depth > 0).all(), [float((d > 0).mean()) for d in depth]
    np.testing.assert_allclose(normals[4][16, 16], (-1.0, 0.0, 0.0), atol=1e-4)  # east wall, facing in
    assert depth[4][16, 16] == pytest.approx(6.5, abs=0.05)
    assert depth[5].max() <= 6.5 * np.sqrt(2) + 0.05
