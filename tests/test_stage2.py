"""Stage 2 (Eq. 12-14): pseudo ground truths change only the object's pixels, depth is aligned with the
render and in scene units, refinement lowers the MSE to the pseudo ground truth, and bad weights fail early."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from camo.cli import main


@pytest.fixture(scope="module")
def stage2(mi_backend, tmp_path_factory):
    from optimizer.scenes import builtin_scenes
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment
    from optimizer.optimise.inpaint import get_inpainter
    from optimizer.rendering.placement import prepare_object
    from optimizer.rendering.planner import plan
    from optimizer.optimise.stage1 import Stage1Config
    from optimizer.optimise.stage2 import Stage2, Stage2Config

    pack = builtin_scenes.get("gravel")
    pack.cameras = dataclasses.replace(pack.cameras, views=3)
    pack.render = dataclasses.replace(pack.render, resolution=(48, 48))
    env = get_environment(pack.environment)
    prepared = prepare_object(pack, target_vertices=1500)
    app = AppearanceConfig(map_resolution=64, displacement_resolution=32, pose=False)
    s2 = Stage2(pack, env, prepared, cameras(pack), plan(pack, env, app.planner_params()),
                Stage1Config(spp=8, target_spp=16, seed=3), app,
                stage2=Stage2Config(strength=0.8, preview_spp=16), inpainter=get_inpainter("patch")).prepare()
    for v in range(3):
        s2.make_pseudo_gt(v)
    return s2


def test_pseudo_gt_changes_only_masked_pixels(stage2):
    for v in range(3):
        mask = stage2.targets.coverage[v] >= 0.5
        assert mask.sum() > 20
        same = stage2.pseudo_np[v][~mask] == stage2.inputs_np[v][~mask]
        assert same.all()
        assert np.abs(stage2.pseudo_np[v][mask] - stage2.inputs_np[v][mask]).mean() > 1e-3


def test_depth_is_aligned_and_in_scene_units(stage2, mi_backend):
    """Behind the object's pixels lies the ground, farther than the object itself; elsewhere depth is the
    distance to the ground plane z = 0 along the pixel's ray."""
    from optimizer.rendering import scene as scn
    from optimizer.rendering.render import coverage_and_depth

    cam = stage2.cams[0]
    obj = stage2._object()
    sc = scn.build_scene(stage2.env.build(), obj)
    _, depth_obj = coverage_and_depth(sc, cam, obj)
    bg_depth = stage2.targets.depth[0]
    mask = stage2.targets.coverage[0] >= 1.0
    assert np.all(bg_depth[mask] > depth_obj[mask])
    # the camera is `radius` from the object's centre: ground depth near the image centre ~ 4 / cos(...)
    cz = cam.origin[2]
    assert bg_depth.max() > cz and np.all(bg_depth > 0)
    np.testing.assert_allclose(depth_obj[~(stage2.targets.coverage[0] > 0)], bg_depth[~(stage2.targets.coverage[0] > 0)],
                               rtol=1e-5)


def test_refinement_lowers_mse_to_pseudo_gt(stage2, mi_backend):
    from optimizer import backend
    from optimizer.assets.result import Result, render_result
    from optimizer.optimise.stage1 import Stage1
    from optimizer.optimise.stage2 import gamma_encode_np

    def mse():
        res = Result(stage2.pack, stage2.env, stage2.cams, stage2.geometry, stage2.current_values(), stage2.app,
                     stage2.shading_integrator(), 64, None)
        imgs = render_result(res, seed=5)
        # inside the silhouette (outside it the pseudo-GT is the noisy render it came from)
        return np.mean([((gamma_encode_np(imgs[v]) - stage2.pseudo_np[v]) ** 2)[stage2.targets.coverage[v] >= 1].mean()
                        for v in range(3)])

    backend.set_threads(1)  # bit-exact: multi-threaded atomic adds reorder sums, and Adam amplifies the difference
    before = mse()
    for _ in range(12):
        Stage1.step(stage2)  # gradient steps on the fixed pseudo ground truths (Eq. 14)
    after = mse()
    assert after < 0.8 * before, (before, after)


def test_missing_weights_fail_before_stage1(tmp_path, capsys):
    code = main(["optimize", "gravel", "--out", str(tmp_path / "run"), "--stage2-backend", "diffusers",
                 "--sdxl-path", str(tmp_path / "nope"), "--controlnet-path", str(tmp_path / "nope2"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("camo: error:")
    assert not (tmp_path / "run" / "log.jsonl").exists()


def test_gamma_encoding_keeps_the_gradient_of_overexposed_pixels(mi_backend):
    """A glint brighter than 1 (linear) must still be pulled toward a pseudo ground truth in [0, 1]."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.optimise.stage2 import gamma_encode_dr

    x = mi.Float([0.0, 0.25, 1.0, 4.0])
    dr.enable_grad(x)
    y = gamma_encode_dr(x)
    np.testing.assert_allclose(np.array(y), [1e-4 ** (1 / 2.2), 0.25 ** (1 / 2.2), 1.0, 1.0], rtol=1e-5)  # clipped
    dr.backward(dr.sum(dr.square(y - 0.7)))  # pseudo ground truth 0.7 everywhere
    g = np.array(dr.grad(x))
    assert g[0] == 0.0  # below the 1e-4 clamp: no slope
    assert g[1] < 0.0 and g[2] > 0.0  # pulled up / down toward 0.7
    # the glint at 4.0: straight-through slope of x^(1/2.2) at 4, times 2 * (1 - 0.7)
    np.testing.assert_allclose(g[3], 2 * 0.3 * (1 / 2.2) * 4.0 ** (1 / 2.2 - 1), rtol=1e-5)


def test_fixed_displacement_keeps_stage1_geometry_and_drops_projective_sampling(mi_backend):
    """--stage2-fixed-displacement: Stage 2 trains the BSDF maps only; Stage 1's displacement stays applied
    (the mesh is displaced, not the base mesh) and unchanged, and with no geometry moving the planner
    switches to prb with one batch sensor."""
    from optimizer.scenes import builtin_scenes
    from optimizer.rendering.appearance import AppearanceConfig, initial_values, world_positions
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment
    from optimizer.optimise.inpaint import get_inpainter
    from optimizer.rendering.placement import prepare_object
    from optimizer.rendering.planner import plan
    from optimizer.optimise.stage1 import Stage1Config
    from optimizer.optimise.stage2 import Stage2, Stage2Config

    pack = builtin_scenes.get("gravel")
    pack.cameras = dataclasses.replace(pack.cameras, views=2)
    pack.render = dataclasses.replace(pack.render, resolution=(32, 32))
    env = get_environment(pack.environment)
    app = AppearanceConfig(map_resolution=32, displacement_resolution=16, pose=False, freeze_displacement=True)
    assert "displacement" not in app.trainable() and "displacement" not in app.planner_params()
    pl = plan(pack, env, app.planner_params())
    assert pl.integrator["type"] == "prb" and pl.batch
    values = initial_values(app, pack.material)
    rng = np.random.default_rng(0)
    values["displacement"] = rng.uniform(-0.5, 0.5, values["displacement"].shape).astype(np.float32)
    s2 = Stage2(pack, env, prepare_object(pack, target_vertices=800), cameras(pack), pl,
                Stage1Config(spp=2, target_spp=8, seed=1), app, initial=values,
                stage2=Stage2Config(strength=0.8, preview_spp=4, displacement=False),
                inpainter=get_inpainter("patch")).prepare()
    displaced = world_positions(s2.geometry, values, app)
    flat = world_positions(s2.geometry, dict(values, displacement=np.zeros_like(values["displacement"])), app)
    assert np.abs(displaced - flat).max() > 1e-4  # the fixed map really displaces the mesh
    for _ in range(2):
        s2.step()
    out = s2.current_values()
    np.testing.assert_array_equal(out["displacement"], values["displacement"])
    assert np.abs(out["albedo"] - values["albedo"]).max() > 0  # the maps did train
    in_scene = np.asarray(s2.params[s2._keys["positions"]]).reshape(-1, 3)  # what was rendered
    np.testing.assert_allclose(in_scene, displaced, atol=1e-5)
