"""The fast preset's parts: the least-squares albedo warm start, the learning-rate schedule, the time budget,
snapshots and the presets, each checked against analytic values or end to end through the CLI on a tiny scene."""

from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest

from camo.cli import main
from optimizer.optimise.presets import PRESETS
from optimizer.optimise.schedule import lr_scale, progress
from optimizer.optimise.warmstart import least_squares_albedo

TINY = ["--views", "3", "--resolution", "32", "--map-resolution", "48", "--displacement-resolution", "16",
        "--target-vertices", "800", "--spp", "2", "--target-spp", "16", "--quiet", "--threads", "1"]


# --- least squares, analytic ---------------------------------------------------------------------------------

def test_least_squares_recovers_a_known_albedo_from_noisy_affine_views():
    """B = L0 + a (L1 - L0) in every view (different lighting per view): the solve returns a exactly; with
    zero-mean noise on B it returns the weighted least-squares estimate sum(w s r) / sum(w s^2)."""
    rng = np.random.default_rng(0)
    V, N = 5, 200
    a = rng.uniform(0.05, 0.95, (N, 3))
    L0 = rng.uniform(0.0, 0.2, (V, N, 3))
    s = rng.uniform(0.3, 2.0, (V, N, 3))
    B = L0 + a * s
    w = rng.uniform(0.1, 1.0, (V, N))
    got, assigned, raw = least_squares_albedo(B, L0, L0 + s, w)
    assert assigned.all()
    np.testing.assert_allclose(got, a, atol=1e-5)
    noise = rng.normal(0, 0.05, B.shape)
    got, _, raw = least_squares_albedo(B + noise, L0, L0 + s, w)
    want = (w[..., None] * s * (B + noise - L0)).sum(0) / (w[..., None] * s * s).sum(0)
    np.testing.assert_allclose(raw, want, rtol=1e-5)
    np.testing.assert_allclose(got, np.clip(want, 0, 1), atol=1e-6)


def test_least_squares_clips_ignores_nonfinite_and_unseen():
    """Too dark a background -> 0, too bright -> 1 (raw keeps the sign); a NaN/Inf observation carries no
    weight; a texel seen by no view, or with zero slope (black even at albedo 1), is unassigned."""
    V, N = 2, 5
    L0 = np.zeros((V, N, 3))
    L1 = np.ones((V, N, 3))
    B = np.full((V, N, 3), 0.25)
    B[:, 0] = -1.0  # needs a < 0
    B[:, 1] = 3.0  # needs a > 1
    B[0, 2] = np.nan  # view 0 poisoned, view 1 says 0.25
    L1[0, 2, 1] = np.inf
    w = np.ones((V, N))
    w[:, 3] = 0.0  # never seen
    L1[:, 4] = 0.0  # no slope
    got, assigned, raw = least_squares_albedo(B, L0, L1, w)
    assert np.isfinite(got).all() and np.isfinite(raw).all()
    assert assigned.tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(got[0], 0.0)
    np.testing.assert_allclose(got[1], 1.0)
    assert raw[0, 0] == pytest.approx(-1.0) and raw[1, 0] == pytest.approx(3.0)
    np.testing.assert_allclose(got[2], 0.25, atol=1e-6)


# --- schedule ------------------------------------------------------------------------------------------------

def test_cosine_schedule_values_and_extremes():
    assert lr_scale(0.0) == pytest.approx(1.0)
    assert lr_scale(0.5, floor=0.1) == pytest.approx(0.55)
    assert lr_scale(1.0, floor=0.1) == pytest.approx(0.1)
    assert lr_scale(7.0, floor=0.0) == 0.0 and lr_scale(-3.0) == pytest.approx(1.0)  # clamped
    assert lr_scale(math.nan) == pytest.approx(0.1)  # a broken clock ends on small steps, never NaN
    assert lr_scale(0.3, "constant") == 1.0
    with pytest.raises(ValueError):
        lr_scale(0.3, "linear")
    assert progress(5, 20) == 0.25
    assert progress(5, 20, seconds=9.0, budget=10.0) == 0.9  # the budget runs out first
    assert progress(30, 20) == 1.0 and progress(0, 0) == 0.0


def test_adam_scale_multiplies_the_step(mi_backend):
    """One Adam step moves by lr * scale (the first bias-corrected step is lr * sign(g)); scale 0 keeps the
    value; a non-finite scale is refused."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.optimise.adam import Adam

    for scale in (1.0, 0.25, 0.0):
        opt = Adam({"x": 0.1})
        opt.add("x", mi.Float([0.5, 0.5]))
        dr.backward(dr.sum(opt["x"] * mi.Float([2.0, -3.0])))
        opt.step(scale=scale)
        np.testing.assert_allclose(np.asarray(opt["x"]), [0.5 - 0.1 * scale, 0.5 + 0.1 * scale], atol=1e-6)
    with pytest.raises(ValueError):
        opt.step(scale=float("nan"))


def test_soft_threshold_is_the_l1_proximal_step(mi_backend):
    import mitsuba as mi

    from optimizer.optimise.schedule import soft_threshold

    out = soft_threshold(mi.TensorXf(np.array([[0.3], [-0.02], [0.0], [-0.7]], np.float32)), 0.05)
    np.testing.assert_allclose(np.asarray(out).ravel(), [0.25, 0.0, 0.0, -0.65], atol=1e-7)


def test_displacement_regulariser_settles_with_the_proximal_step(tmp_path):
    """The issue's case: gravel from metallic 1, roughness 0, transmittance 1. Under the paper's schedule L_disp
    rises every step (Adam turns gradient noise into full steps; the regulariser's gradient is 1/N per texel);
    with the fast preset's proximal step it falls back after the first steps and ends far below."""
    final = {}
    for preset in ("paper", "fast"):
        out = tmp_path / preset
        assert main(["optimize", "gravel", "--out", str(out), *TINY, "--preset", preset, "--stages", "1",
                     "--iterations", "10", "--init", "metallic=1,roughness=0,transmittance=1",
                     "--displacement-resolution", "32"]) == 0
        disp = [json.loads(x)["loss_disp"] for x in (out / "log.jsonl").read_text().splitlines()]
        assert all(math.isfinite(d) and d >= 0 for d in disp)
        final[preset] = disp
    paper, fast = final["paper"], final["fast"]
    assert paper[-1] > paper[2] > 0  # the drift the issue measured
    assert fast[-1] < max(fast) and fast[-1] < 0.25 * paper[-1]


def test_blur_texels_averages_noise_and_keeps_constants():
    """The gradient blur of --grad-blur: white noise loses variance by ~1/(4 pi sigma^2), a constant and a linear
    ramp (away from the edges) pass unchanged, channels stay apart, sigma 0 is the identity."""
    from optimizer.optimise.adam import blur_texels

    rng = np.random.default_rng(0)
    noise = rng.normal(size=(256, 256, 2)).astype(np.float32)
    for sigma in (1.0, 2.0):
        ratio = blur_texels(noise, sigma).var() / noise.var()
        assert 0.6 / (4 * np.pi * sigma**2) < ratio < 1.6 / (4 * np.pi * sigma**2), (sigma, ratio)
    const = np.full((32, 32, 3), 0.25, np.float32)
    np.testing.assert_allclose(blur_texels(const, 2.0), const, atol=1e-7)
    ramp = np.tile(np.linspace(0, 1, 64, dtype=np.float32), (64, 1))
    np.testing.assert_allclose(blur_texels(ramp, 2.0)[:, 8:-8], ramp[:, 8:-8], atol=1e-6)
    two = np.zeros((16, 16, 2), np.float32)
    two[8, 8, 0] = 1.0
    out = blur_texels(two, 1.5)
    assert out[..., 1].max() == 0.0 and abs(out[..., 0].sum() - 1.0) < 1e-5
    np.testing.assert_array_equal(blur_texels(noise, 0.0), noise)


def test_smooth_texels_inverts_the_screened_laplacian_and_keeps_constants():
    """(I + lambda L)^-p by the DCT: applying (I + lambda L) p times to the output (L the 5-point Laplacian with
    reflecting edges, built by hand) gives the input back; constants are unchanged; white noise loses far more
    than a smooth ramp; lambda 0 is a copy and a negative lambda is refused."""
    from optimizer.optimise.adam import smooth_texels

    def apply(u, lam):  # (I + lam L) u, L = 4-neighbour graph Laplacian, Neumann edges
        p = np.pad(u, ((1, 1), (1, 1)) + ((0, 0),) * (u.ndim - 2), mode="edge")
        lap = 4 * u - p[:-2, 1:-1] - p[2:, 1:-1] - p[1:-1, :-2] - p[1:-1, 2:]
        return u + lam * lap

    rng = np.random.default_rng(0)
    g = rng.standard_normal((24, 20, 3)).astype(np.float32)
    for power in (1, 2):
        u = smooth_texels(g, 5.0, power).astype(np.float64)
        for _ in range(power):
            u = apply(u, 5.0)
        np.testing.assert_allclose(u, g, atol=1e-4)
    np.testing.assert_allclose(smooth_texels(np.full((16, 16), 0.3, np.float32), 16.0), 0.3, atol=1e-6)
    noise = rng.standard_normal((64, 64)).astype(np.float32)
    ramp = np.tile(np.linspace(-1, 1, 64, dtype=np.float32), (64, 1))
    assert smooth_texels(noise, 16.0).std() < 0.05 * noise.std()
    assert smooth_texels(ramp, 16.0)[:, 24:40].std() > 0.2 * ramp[:, 24:40].std()
    np.testing.assert_array_equal(smooth_texels(noise, 0.0), noise)
    with pytest.raises(ValueError):
        smooth_texels(noise, -1.0)


def test_uniform_adam_keeps_the_gradient_direction(mi_backend):
    """Uniform Adam (Nicolet et al.): the first step is lr * g / max|g| for every entry, so a small entry moves
    little; per-entry Adam moves every entry by lr."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.optimise.adam import Adam

    for uniform, want in (((), [0.4, 0.6, 0.4]), (("x",), [0.4, 0.55, 0.49])):
        opt = Adam({"x": 0.1}, uniform=uniform)
        opt.add("x", mi.TensorXf(np.full((1, 3, 1), 0.5, np.float32)))
        dr.backward(dr.sum(opt["x"] * mi.TensorXf(np.array([2.0, -1.0, 0.2], np.float32).reshape(1, 3, 1))))
        opt.step()
        np.testing.assert_allclose(np.asarray(opt["x"]).ravel(), want, atol=1e-5)


def test_large_steps_makes_the_noise_driven_maps_smooth(tmp_path):
    """End to end: --map-update large_steps (no gradient blur) leaves the metallic and transmittance maps far
    smoother than per-texel Adam from the same start and seed, and the config records it."""
    rough = {}
    for arm, flags in (("adam", ["--grad-blur", "0"]), ("ls", ["--grad-blur", "0", "--map-update", "large_steps"])):
        out = tmp_path / arm
        assert main(["optimize", "gravel", "--out", str(out), *TINY, "--stages", "1", "--iterations", "6",
                     *flags]) == 0
        rough[arm] = {}
        for name in ("metallic", "transmittance"):
            m = np.load(out / "maps" / f"{name}.npy")[..., 0]
            rough[arm][name] = float(np.abs(np.diff(m, axis=0)).mean() + np.abs(np.diff(m, axis=1)).mean())
    assert 'map_update = "large_steps"' in (tmp_path / "ls" / "config.toml").read_text()
    for name in ("metallic", "transmittance"):
        assert rough["adam"][name] > 0
        assert rough["ls"][name] < 0.2 * rough["adam"][name], (name, rough)


def test_grad_blur_makes_the_noise_driven_maps_smooth(tmp_path):
    """End to end: from the same start and seed, --grad-blur 2 leaves the metallic and transmittance maps (whose
    gradients are mostly Monte Carlo noise at 2 spp) with far less texel-to-texel variation than per-texel Adam
    steps, and the config records it."""
    rough = {}
    for blur in ("0", "2"):
        out = tmp_path / f"b{blur}"
        assert main(["optimize", "gravel", "--out", str(out), *TINY, "--stages", "1", "--iterations", "6",
                     "--grad-blur", blur]) == 0
        assert f"grad_blur = {float(blur)}" in (out / "config.toml").read_text()
        rough[blur] = {}
        for name in ("metallic", "transmittance"):
            m = np.load(out / "maps" / f"{name}.npy")[..., 0]
            rough[blur][name] = float(np.abs(np.diff(m, axis=0)).mean() + np.abs(np.diff(m, axis=1)).mean())
    for name in ("metallic", "transmittance"):
        assert rough["0"][name] > 0
        assert rough["2"][name] < 0.5 * rough["0"][name], (name, rough)


# --- end to end --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("conv")
    out = {}
    for name, extra in (("fast", ["--iterations", "3", "--stage2-iterations", "1", "--snapshot-every", "1"]),
                        ("paper", ["--preset", "paper", "--iterations", "3", "--stages", "1"])):
        assert main(["optimize", "meadow", "--out", str(base / name), *TINY, *extra]) == 0
        out[name] = base / name
    return out


def _config(run):
    return tomllib.loads((run / "config.toml").read_text())


def test_presets_are_recorded(runs):
    fast, paper = _config(runs["fast"]), _config(runs["paper"])
    assert fast["preset"] == "fast" and paper["preset"] == "paper"
    assert fast["stage1"]["warm_start"] is True and fast["stage1"]["lr_schedule"] == PRESETS["fast"].stage1["lr_schedule"]
    assert paper["stage1"]["warm_start"] is False and paper["stage1"]["lr_schedule"] == "constant"
    assert paper["stage1"]["silhouette_every"] == 1 and paper["stage2"]["iterations"] == 20
    assert paper["appearance"]["lr_maps"] == 0.01 and paper["appearance"]["lr_displacement"] == 0.1
    assert fast["appearance"]["lr_displacement"] == PRESETS["fast"].appearance["lr_displacement"]


def test_warm_start_matches_the_background_better_than_grey(runs):
    """Iteration 0 of the fast run (the warm-started albedo) already has a lower loss than the grey start at
    the same high spp, and the summary records the warm start and the seconds per part."""
    s = json.loads((runs["fast"] / "summary.json").read_text())
    ws = s["warm_start"]
    assert 0 < ws["texels_seen"] <= ws["texels"] and ws["seconds"] > 0
    assert all(0.0 <= x <= 1.0 for x in ws["mean_albedo"])
    # Stage 1's seconds: the turn search, the start search, the warm start, its steps and their held-out checks
    assert s["seconds_stage1"] == pytest.approx(s["seconds_pose_search"] + s["seconds_start_search"] +
                                                s["seconds_warm_start"] + sum(
        r.get("seconds_total", r["seconds"]) + r.get("seconds_holdout", 0.0)
        for r in map(json.loads, (runs["fast"] / "log.jsonl").read_text().splitlines()) if r["stage"] == 1), rel=1e-6)
    assert s["seconds_optimisation"] == pytest.approx(s["seconds_stage1"] + s["seconds_stage2"])
    first = json.loads((runs["fast"] / "log.jsonl").read_text().splitlines()[0])
    paper_first = json.loads((runs["paper"] / "log.jsonl").read_text().splitlines()[0])
    assert first["loss_photo"] < 0.8 * paper_first["loss_photo"]
    assert s["final_loss_high_spp"] < s["initial_loss_high_spp"]


def test_snapshots_have_increasing_seconds_and_the_final_values(runs):
    snaps = sorted((runs["fast"] / "snapshots").glob("s*_*.npz"))
    assert [p.name for p in snaps] == ["s1_0000.npz", "s1_0001.npz", "s1_0002.npz", "s1_0003.npz", "s2_0000.npz",
                                       "s2_0001.npz"]
    secs = [float(np.load(p)["seconds"]) for p in snaps]
    assert all(b >= a for a, b in zip(secs, secs[1:])) and secs[0] > 0  # s1_0000 already paid the warm start
    # the result (the held-out views' chosen iterate) is one of the snapshots, saved again as result.npz at the end
    res = np.load(runs["fast"] / "snapshots" / "result.npz")
    chosen = np.load(runs["fast"] / "snapshots" / f"s{int(res['stage'])}_{int(res['iteration']):04d}.npz")
    albedo = np.load(runs["fast"] / "maps" / "albedo.npy")
    np.testing.assert_allclose(chosen["albedo"], albedo, atol=1e-6)
    np.testing.assert_array_equal(res["albedo"], chosen["albedo"])
    assert float(res["seconds"]) >= secs[-1]
    log = [json.loads(x) for x in (runs["fast"] / "log.jsonl").read_text().splitlines()]
    sched = _config(runs["fast"])["stage1"]["lr_schedule"]
    planned = {1: 3, 2: 1}
    for r in log:  # the step's multiplier is the schedule at the stage's progress before the step
        assert r["lr_scale"] == pytest.approx(lr_scale(progress(r["iteration"] - 1, planned[r["stage"]]), sched))


def test_time_budget_ends_the_run(tmp_path):
    """A budget far below one iteration's cost: Stage 1 takes one step, Stage 2 one step, and the run is a
    complete run directory whose config records the budget."""
    out = tmp_path / "budget"
    assert main(["optimize", "meadow", "--out", str(out), *TINY, "--time-budget", "0.01", "--lr-schedule", "cosine"]) == 0
    log = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    assert [(r["stage"], r["iteration"]) for r in log] == [(1, 1), (2, 1)]
    assert all(r["lr_scale"] == pytest.approx(1.0) for r in log)  # each stage's first step is at progress 0
    assert _config(out)["time_budget"] == 0.01
    assert (out / "result.glb").is_file()


@pytest.mark.parametrize("flags, message", [
    (["--time-budget", "0"], "--time-budget: must be a number > 0"),
    (["--time-budget", "nan"], "--time-budget: must be a number > 0"),
    (["--lr-maps", "-1"], "--lr-maps: must be a number in (0, 10]"),
    (["--snapshot-every", "-2"], "--snapshot-every: must be an integer in [0, "),
])
def test_bad_schedule_flags_are_one_line_errors(tmp_path, capsys, flags, message):
    out = tmp_path / "bad"
    assert main(["optimize", "meadow", "--out", str(out), *TINY, *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not out.exists() or not any(out.iterdir())


def test_user_pack_under_the_sun_starts_rough_in_the_fast_preset(tmp_path, capsys):
    """A user pack (paper material, roughness 0) around the sunlit meadow: the fast preset starts at the
    planner's glint-safe roughness and says so; --init roughness=0 and --preset paper keep 0. config.toml records the
    spec (the pack as given, rough_start) and the roughness the run started from ([plan] start_roughness)."""
    pack = tmp_path / "user.toml"
    pack.write_text('name = "user"\n[object]\nprimitive = "vase"\n[environment]\nbuiltin = "meadow"\n')
    common = [*TINY, "--iterations", "1", "--stages", "1"]
    assert main(["optimize", str(pack), "--out", str(tmp_path / "a"), *common]) == 0
    a = _config(tmp_path / "a")
    assert a["pack"]["material"]["roughness"] == 0.0 and a["rough_start"] is True
    assert a["plan"]["start_roughness"] == 0.5
    assert np.load(tmp_path / "a" / "maps" / "roughness.npy").min() > 0.035 + 0.965 * 0.5 - 0.011  # one step from 0.5
    assert main(["optimize", str(pack), "--out", str(tmp_path / "b"), *common, "--init", "roughness=0"]) == 0
    b = _config(tmp_path / "b")
    assert b["pack"]["material"]["roughness"] == 0.0 and b["rough_start"] is False and "start_roughness" not in b["plan"]
    assert main(["optimize", str(pack), "--out", str(tmp_path / "c"), *common, "--preset", "paper"]) == 0
    c = _config(tmp_path / "c")
    assert c["pack"]["material"]["roughness"] == 0.0 and c["rough_start"] is False and "start_roughness" not in c["plan"]


# --- numerics: poisoned and degenerate inputs ----------------------------------------------------------------

def tiny_box_stage(views: int, mesh: str | None = None):
    """A Stage 1 on gravel's box (or the ``mesh`` file) at 24 px, 32 px maps and 8-spp targets: ``(stage, appearance,
    environment)``."""
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.rendering.placement import prepare_object
    from optimizer.rendering.planner import plan
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment
    from optimizer.scenes.scenepack import parse_pack
    from optimizer.optimise.stage1 import Stage1, Stage1Config

    pack = parse_pack({"object": {"primitive": "utility_box", "target_vertices": 400} if mesh is None else
                       {"mesh": mesh, "target_vertices": 400, "rotation": [0.0, 0.0, 30.0]},
                       "environment": {"builtin": "gravel"}, "cameras": {"views": views},
                       "render": {"resolution": 24}, "material": {"roughness": 0.5}})
    env = get_environment(pack.environment)
    app = AppearanceConfig(map_resolution=32, displacement_resolution=16)
    s1 = Stage1(pack, env, prepare_object(pack), cameras(pack), plan(pack, env, app.planner_params()),
                Stage1Config(iterations=1, target_spp=8), app).prepare()
    return s1, app, env


def test_warm_start_from_black_and_nan_targets_stays_finite_and_in_range(mi_backend):
    """Hard case: background targets that are black in one view and NaN/Inf in another (a corrupt render).
    The warm-started albedo is finite and in [0, 1] everywhere; black targets pull the albedo to 0 where only
    they see the surface; nothing seen at all (every target poisoned) leaves the initial albedo."""
    from optimizer.optimise.warmstart import warm_start_albedo

    s1, app, env = tiny_box_stage(views=2)
    bg = s1.targets.background.copy()
    bg[0] = 0.0
    bg[1, ::2] = np.nan
    bg[1, 1::2] = np.inf
    vals, info = warm_start_albedo(s1.values, s1.geometry, app, env, s1.cams, s1.shading_integrator(), bg,
                                   s1.targets.coverage, 8, 1)
    a = vals["albedo"]
    assert np.isfinite(a).all() and a.min() >= 0.0 and a.max() <= 1.0
    assert info.texels_seen > 0 and max(info.mean_albedo) < 0.05  # only the black view counts
    poisoned = np.full_like(bg, np.nan)
    vals, info = warm_start_albedo(s1.values, s1.geometry, app, env, s1.cams, s1.shading_integrator(), poisoned,
                                   s1.targets.coverage, 8, 1)
    assert info.texels_seen == 0
    np.testing.assert_allclose(vals["albedo"], 0.5)


def test_one_view_and_schedule_extremes_run_finite(tmp_path):
    """One training view, a zero learning-rate floor reached at once (a tiny time budget) and the largest
    map rate: the run completes with finite, in-range maps."""
    out = tmp_path / "one"
    assert main(["optimize", "gravel", "--out", str(out), *TINY, "--views", "1", "--lr-maps", "10",
                 "--time-budget", "0.05", "--stages", "1"]) == 0
    log = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    assert all(math.isfinite(r["loss"]) and r["nonfinite_grads"] == 0 for r in log)
    for k in ("albedo", "metallic", "roughness", "transmittance"):
        m = np.load(out / "maps" / f"{k}.npy")
        assert np.isfinite(m).all() and m.min() >= 0.0 and m.max() <= 1.0


@pytest.mark.parametrize("theta", [0.0, math.pi / 2, math.pi, -2.7488935])
def test_warm_start_solves_every_front_facing_texel_of_a_turned_box(mi_backend, tmp_path, theta):
    """The right answer is known for a convex box (a cube): a texel is seen in a view where its outward face normal points
    towards the camera (and the ground does not hide it). The warm start must use every such texel whose pixel the
    box covers fully, at any turn. Before issue 29's fix the faces were oriented by the unturned vertex normals: at a
    turn of pi (or meadow's -2.75 rad) the front faces read as back faces and about a tenth of the texels were solved
    (meadow: 741 of 7,771, now 6,294)."""
    from optimizer.rendering import projection
    from optimizer.rendering.appearance import world_positions
    from optimizer.rendering.render import coverage_and_depth_views
    from optimizer.optimise.warmstart import warm_start_albedo

    import trimesh

    cube = trimesh.creation.box((0.8, 0.8, 0.8))
    cube.apply_translation((0.0, 0.0, 0.4))
    cube.export(tmp_path / "cube.obj")
    s1, app, env = tiny_box_stage(views=3, mesh=str(tmp_path / "cube.obj"))
    g = s1.geometry
    values = dict(s1.values, rotation=np.array([theta], np.float32))
    pos = world_positions(g, values, app).astype(np.float64)
    sc, shape = projection.object_scene(env, pos, g.faces, g.uvs)
    cov = coverage_and_depth_views(sc, s1.cams, shape)[0]  # the turned box's own coverage
    cache: dict = {}
    _, info = warm_start_albedo(values, g, app, env, s1.cams, s1.shading_integrator(), s1.targets.background, cov,
                                8, 3, cache=cache)
    tv = next(iter(cache.values()))
    surface = tv.surface
    # outward normals from the geometry alone: the winding normal turned away from the box's centre
    tri = pos[g.faces[surface.face]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n *= np.sign(np.einsum("ij,ij->i", n, tri.mean(1) - pos.mean(0)))[:, None]
    want = np.zeros((len(s1.cams), len(surface)), bool)
    for k, cam in enumerate(s1.cams):
        to_cam = np.asarray(cam.origin, np.float64) - surface.points
        cos = np.einsum("ij,ij->i", n, to_cam) / np.linalg.norm(to_cam, axis=1)
        x, y, _ = projection.project(surface.points, cam)
        full = projection.sample_bilinear(cov[k][..., None], x, y)[:, 0] >= 0.999
        want[k] = (cos > 0.05) & (n[:, 2] > -0.5) & full  # clearly front-facing, not the bottom on the ground
    got = np.zeros_like(want)
    got[:, tv.seen] = tv.weight > 0
    assert want.any(0).sum() > 0.3 * len(surface)
    # every clearly front-facing, fully covered texel is used in its view; nothing facing away is
    assert (got & want).sum() >= 0.99 * want.sum()
    facing_away = np.stack([np.einsum("ij,ij->i", n, np.asarray(c.origin, np.float64) - surface.points) < 0
                            for c in s1.cams])
    assert not (got & facing_away).any()
    assert info.texels_seen >= 0.99 * want.any(0).sum()


def test_warm_start_cache_and_seen_texels_match_the_whole_atlas_solve(mi_backend):
    """The warm start solves only texels some view sees and can share that geometry-only work across starts (the
    start search): one thread, same seed -> the albedo is bit-identical to solving every texel of the atlas
    (weight 0 elsewhere) and to a call without the cache; the cache holds one entry per placement."""
    mi, dr = mi_backend
    from optimizer.rendering import projection
    from optimizer.rendering import scene as scn
    from optimizer.rendering.appearance import object_bsdf, world_normals, world_positions
    from optimizer.rendering.render import render_shaded
    from optimizer.optimise.warmstart import least_squares_albedo, warm_start_albedo

    dr.set_thread_count(1)
    s1, app, env = tiny_box_stage(views=3)
    bg, cov, integ = s1.targets.background, s1.targets.coverage, s1.shading_integrator()
    cache: dict = {}
    rough = dict(s1.values, roughness=np.full_like(s1.values["roughness"], 0.8))
    for values in (s1.values, rough):
        got, _ = warm_start_albedo(values, s1.geometry, app, env, s1.cams, integ, bg, cov, 8, 3, cache=cache)
        plain, _ = warm_start_albedo(values, s1.geometry, app, env, s1.cams, integ, bg, cov, 8, 3)
        np.testing.assert_array_equal(got["albedo"], plain["albedo"])
    assert len(cache) == 1
    # the whole atlas, every texel solved (the warm start before it skipped unseen ones)
    pos = world_positions(s1.geometry, rough, app)
    surface = projection.rasterise_texels(pos, s1.geometry.faces, s1.geometry.uvs, 32, world_normals(s1.geometry, rough))
    sc, shape = projection.object_scene(env, pos, s1.geometry.faces, s1.geometry.uvs)
    obs = projection.observe(sc, shape, s1.cams, surface, 0.01 * float(s1.geometry.size))
    imgs = []
    for grey in (0.0, 1.0):
        v = dict(rough, albedo=np.full_like(rough["albedo"], grey))
        imgs.append(render_shaded(env.build(), scn.object_mesh(pos, s1.geometry.faces, s1.geometry.uvs,
                                                               object_bsdf(v, app)), s1.cams, integ, 8, 3))
    full = np.stack([projection.sample_bilinear(cov[k][..., None], obs.x[k], obs.y[k])[:, 0]
                     for k in range(len(s1.cams))]) >= 0.999
    albedo, assigned, _ = least_squares_albedo(obs.sample(bg), obs.sample(imgs[0]), obs.sample(imgs[1]),
                                               obs.visible * full * obs.cos)
    want = projection.bake(surface, albedo, assigned,
                           fallback=tuple(float(x) for x in rough["albedo"].reshape(-1, 3).mean(0)))
    assert 0 < assigned.sum() < len(surface)  # some texels unseen: the restriction matters
    np.testing.assert_array_equal(got["albedo"], want)
