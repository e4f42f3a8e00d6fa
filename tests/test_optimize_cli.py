"""Stage 1 end to end through the CLI on a tiny scene: the loss goes down, every exported file
loads back, ``--resume`` continues to the same numbers, and bad input leaves earlier results alone."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camo.cli import main
from camo_base.tables import read_parquet

TINY = ["--views", "4", "--resolution", "32", "--map-resolution", "64", "--displacement-resolution", "32",
        "--target-vertices", "1500", "--spp", "4", "--target-spp", "32", "--quiet", "--stages", "1",
        "--threads", "1",  # one thread: bit-exact (parallel float atomics reorder sums)
        # from the grey start with constant rates: the loss must visibly descend, and a run extended from 5 to 10
        # iterations equals a 10-iteration run (a cosine schedule depends on the planned count; the fast preset's
        # warm start, schedule and kills are in test_convergence.py and test_stress_faults.py)
        "--warm-start", "off", "--lr-schedule", "constant",
        # Eq. 9: its 4-spp loss values fall visibly within 10 steps (a squared error's are dominated by the
        # render's own variance at these sizes; its descent shows at high spp, test_convergence.py)
        "--loss", "gated"]


def optimize(out, iterations, *extra):
    return main(["optimize", "gravel", "--out", str(out), "--iterations", str(iterations), *TINY, *extra])


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "full"
    assert optimize(out, 10, "--checkpoint-every", "5") == 0
    return out


def log_of(d):
    return [json.loads(line) for line in (d / "log.jsonl").read_text().splitlines()]


def test_run_directory_contents(run_dir):
    for name in ("config.toml", "log.jsonl", "result.glb", "result.obj", "result.mtl", "scene.xml", "pose.json",
                 "loss.png", "checkpoint.npz", "summary.json", "maps/albedo.png", "maps/albedo.npy",
                 "maps/displacement.npy", "previews/view_00.png", "previews/view_03.png"):
        assert (run_dir / name).is_file(), name
    log = log_of(run_dir)
    assert [r["iteration"] for r in log] == list(range(1, 11))
    assert all({"iteration", "loss", "seconds", "nonfinite_grads", "loss_photo", "loss_disp"} <= set(r) for r in log)
    import tomllib

    cfg = tomllib.loads((run_dir / "config.toml").read_text())
    assert cfg["seed"] == 0 and "mitsuba" in cfg["versions"] and cfg["spec_version"] == 2
    assert cfg["plan"]["integrator"]["type"] == "prb_projective"
    # the training renders' integrator: 4 spp continuous, 2 * (32 + 32) * 4 silhouette samples per view,
    # rendered with spp=0
    assert cfg["plan"]["training_integrator"] == dict(cfg["plan"]["integrator"], type="camo_prb_projective", sppc=4,
                                                      sppp=1, sppi=0, silhouette_samples=512)
    assert cfg["plan"]["render_spp"] == 0
    assert cfg["stage1"]["silhouette_every"] == 4  # silhouettes on a random quarter of the views per step
    # the measured plan: recorded with the pilot's figures in summary.json, and in the checkpoint for --resume
    summary = json.loads((run_dir / "summary.json").read_text())
    plan = summary["plan"]
    assert plan["pilot"]["seconds"] > 0 and plan["effects"] and plan["curve"]["rows"]
    assert plan["max_depth"] == cfg["plan"]["max_depth"] == cfg["plan"]["integrator"]["max_depth"]
    assert plan["rr_depth"] == 5 and plan["region"] is True
    assert "plan/json" in np.load(run_dir / "checkpoint.npz").files


def test_loss_decreases(run_dir):
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["final_loss_high_spp"] < s["initial_loss_high_spp"]
    log = log_of(run_dir)
    assert np.mean([r["loss_photo"] for r in log[-3:]]) < np.mean([r["loss_photo"] for r in log[:3]])


def test_displacement_warmup_keeps_the_first_steps_small(run_dir):
    """The fast preset's displacement warm-up (10 steps; optimizer/optimise/adam.py): Adam's first step moves a texel
    by at most the ramped rate lr / 10 and the proximal step keeps half of it, so the L1 term logged at iteration 2
    (measured before that step) is at most 0.5 lr / 10 = 0.0025; without the ramp it is up to 0.025 (0.010 measured
    on meadow, 10x its photometric loss). Over the ramp the term stays below the sum of the ramped half-steps."""
    import tomllib

    cfg = tomllib.loads((run_dir / "config.toml").read_text())["appearance"]
    assert cfg["displacement_warmup"] == 10 and cfg["lr_displacement"] == 0.05 and cfg["displacement_shrink"] == 0.5
    disp = [r["loss_disp"] for r in log_of(run_dir)]
    assert disp[0] == 0.0 and 0.0 < disp[1] <= 0.5 * 0.05 / 10 * 1.0001
    bounds = [0.5 * 0.05 * sum(range(1, t + 1)) / 10 * 1.0001 for t in range(10)]
    assert all(d <= b for d, b in zip(disp, bounds)), (disp, bounds)


def test_maps_stay_in_range_and_pose_is_clipped(run_dir):
    for name in ("albedo", "metallic", "roughness", "transmittance"):
        m = np.load(run_dir / "maps" / f"{name}.npy")
        assert np.isfinite(m).all() and m.min() >= 0.0 and m.max() <= 1.0
    pose = json.loads((run_dir / "pose.json").read_text())
    assert abs(pose["dx"]) <= 0.05 + 1e-7 and abs(pose["dy"]) <= 0.05 + 1e-7 and pose["dz"] == 0.0


def test_exports_load_back(run_dir, mi_backend):
    import trimesh

    mesh = trimesh.load(run_dir / "result.glb", force="mesh")
    assert len(mesh.faces) > 1000
    tex = mesh.visual.material.baseColorTexture
    assert tex is not None and tex.size == (64, 64)
    obj = trimesh.load(run_dir / "result.obj", force="mesh")
    assert len(obj.faces) == len(mesh.faces)

    mi, dr = mi_backend
    from optimizer.backend import load_file

    sc = load_file(run_dir / "scene.xml")
    renders = np.load(run_dir / "renders.npz")
    final = renders["final"]
    for v in (0, 2):
        img = np.asarray(mi.render(sc, sensor=v, spp=32, seed=99))
        mask = renders["coverage"][v] > 0.5
        # same scene, independent noise: the object's pixels agree within Monte-Carlo noise
        rel = np.abs(img[mask].mean(0) - final[v][mask].mean(0)) / final[v][mask].mean(0)
        assert np.all(rel < 0.1), rel
        assert abs(img.mean() - final[v].mean()) < 0.05 * final[v].mean()


def test_resume_matches_uninterrupted_run(run_dir, tmp_path):
    out = tmp_path / "resumed"
    assert optimize(out, 5, "--checkpoint-every", "5") == 0  # "killed" after its checkpoint at 5
    assert optimize(out, 10, "--checkpoint-every", "5", "--resume") == 0
    a, b = log_of(run_dir), log_of(out)
    assert [r["iteration"] for r in b] == list(range(1, 11))
    assert [r["loss"] for r in b] == [r["loss"] for r in a]
    np.testing.assert_array_equal(np.load(out / "maps" / "albedo.npy"), np.load(run_dir / "maps" / "albedo.npy"))


def test_bad_input_keeps_earlier_results(run_dir, capsys):
    before = (run_dir / "log.jsonl").read_bytes()
    assert optimize(run_dir, 3) == 2  # not empty, no --resume / --overwrite
    assert "not empty" in capsys.readouterr().err
    assert main(["optimize", "gravel", "--out", str(run_dir), "--iterations", "0", "--quiet"]) == 2
    assert main(["optimize", "gravel", "--out", str(run_dir), "--ablate", "colour", "--quiet"]) == 2
    assert main(["optimize", "gravel", "--out", str(run_dir), "--silhouette-every", "0", "--quiet"]) == 2
    assert "--silhouette-every: must be an integer in [1, " in capsys.readouterr().err
    assert (run_dir / "log.jsonl").read_bytes() == before


def test_corrupt_checkpoint_is_one_line_error(tmp_path, capsys):
    out = tmp_path / "broken"
    out.mkdir()
    (out / "checkpoint.npz").write_bytes(b"not a zip")
    assert optimize(out, 4, "--resume") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "corrupt" in err[0]


def test_parse_init():
    from camo_base.errors import CamoError
    from optimizer.optimise.spec import parse_init

    assert parse_init("") == {}
    assert parse_init("roughness=0.5, albedo=0.25") == {"roughness": 0.5, "albedo": (0.25, 0.25, 0.25)}
    assert parse_init("albedo=0.1/0.2/0.3,metallic=1,transmittance=0") == {
        "albedo": (0.1, 0.2, 0.3), "metallic": 1.0, "transmittance": 0.0}
    for bad in ("roughness", "shine=0.2", "roughness=1.5", "roughness=-0.1", "roughness=a", "metallic=0.1/0.2/0.3",
                "albedo=0.1/0.2", "roughness=0.1,roughness=0.2"):
        with pytest.raises(CamoError):
            parse_init(bad)


def test_built_in_scenes_start_rough_user_packs_at_the_paper_values(tmp_path):
    from optimizer.scenes import builtin_scenes
    from optimizer.scenes.scenepack import MaterialSpec, parse_pack

    rough = MaterialSpec(albedo=(0.5, 0.5, 0.5), metallic=0.0, roughness=0.5, transmittance=0.5, eta=1.5)
    for name in [*builtin_scenes.names(), "room:vase", "meadow:chair"]:
        assert builtin_scenes.get(name).material == rough, name
    a, b = builtin_scenes.get("gravel"), builtin_scenes.get("gravel")
    a.material.roughness = 0.0  # one pack's edit leaves the next pack (and the module constant) alone
    assert b.material.roughness == 0.5 == builtin_scenes.get("gravel").material.roughness
    # a pack a user writes, even around a built-in environment, starts where the paper does (Sec. IV-A)
    user = parse_pack({"object": {"primitive": "utility_box"}, "environment": {"builtin": "gravel"}})
    assert user.material == MaterialSpec(albedo=(0.5, 0.5, 0.5), metallic=0.0, roughness=0.0, transmittance=0.5)
    # --init restores the paper's start on a built-in scene and records it (with the init search off: on, the fast
    # preset also tries the start without --init and keeps the better, tests/test_hard_cases.py)
    import tomllib

    assert optimize(tmp_path / "paper", 1, "--init", "roughness=0", "--init-search", "off") == 0
    cfg = tomllib.loads((tmp_path / "paper" / "config.toml").read_text())
    assert cfg["pack"]["material"]["roughness"] == 0.0
    assert np.load(tmp_path / "paper" / "maps" / "roughness.npy").max() < 0.035 + 0.011


def test_init_sets_the_starting_maps_and_is_recorded(tmp_path, capsys):
    import tomllib

    out = tmp_path / "init"
    # the init search off: on, the fast preset also tries the start without --init (tests/test_hard_cases.py)
    assert optimize(out, 1, "--init", "roughness=0.3,albedo=0.2/0.4/0.6,metallic=0.1", "--init-search", "off") == 0
    cfg = tomllib.loads((out / "config.toml").read_text())
    mat = cfg["pack"]["material"]
    assert mat["roughness"] == 0.3 and mat["metallic"] == 0.1 and mat["albedo"] == [0.2, 0.4, 0.6]
    maps = {k: np.load(out / "maps" / f"{k}.npy") for k in ("albedo", "roughness", "metallic")}
    # one Adam step (lr 1e-2) from the initial values; roughness is exported as rendered (0.035 + 0.965 r)
    assert np.abs(maps["roughness"] - (0.035 + 0.965 * 0.3)).max() < 0.011
    assert np.abs(maps["metallic"] - 0.1).max() < 0.011
    # the albedo: one step of its map and one of its coarse level (the fast preset's --coarse-grid 1), each <= lr
    assert np.abs(maps["albedo"] - [0.2, 0.4, 0.6]).max() < 0.021
    capsys.readouterr()
    assert optimize(tmp_path / "bad", 1, "--init", "roughness=2") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--init roughness" in err[0]
    assert optimize(tmp_path / "bad2", 1, "--init", "metallic=0.2", "--ablate", "bsdf") == 2
    assert "conflicts" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())


# --- the run spec: flags fill it, config.toml is it, a flag the method does not use is an error -------------------


def spec_of(*argv):
    from camo.cli import build_parser
    from camo.optimize_cli import spec_of as spec_of_args

    return spec_of_args(build_parser().parse_args(["optimize", *argv]))


from optimizer.assets.rundir import PROVENANCE  # noqa: E402


def test_config_toml_is_the_spec_and_holds_each_spp_once(run_dir):
    import tomllib

    from optimizer.optimise.spec import RunSpec

    cfg = tomllib.loads((run_dir / "config.toml").read_text())
    spec = spec_of("gravel", "--out", str(run_dir), "--iterations", "10", *TINY, "--checkpoint-every", "5")
    assert {k: v for k, v in cfg.items() if k not in PROVENANCE} == spec.to_dict()
    assert RunSpec.from_dict({k: v for k, v in cfg.items() if k not in PROVENANCE}) == spec
    # each spp once: --spp is the training spp only (the pack's own spp is not recorded), --target-spp the targets'
    assert cfg["spp"] == {"train": 4, "target": 32, "stage2_preview": 16}
    assert "spp" not in cfg["pack"]["render"] and spec.pack.render.spp == 16
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["final_render"]["spp"] == 32 and s["method"] == "ours"
    assert cfg["fingerprint"]["value"] == spec.fingerprint()


@pytest.mark.parametrize("method", ["ours", "transparent", "mean", "random", "greedy", "diffusion2d", "ganmouflage",
                                    "ganmouflage-paper"])
def test_spec_round_trips_through_toml(method, tmp_path):
    import tomllib

    import tomli_w

    from optimizer.optimise.spec import RunSpec

    extra = {"ours": ["--iterations", "7", "--stage2-strength", "0.3", "--ablate", "pose", "--init", "roughness=0.2"],
             "ganmouflage": ["--iterations", "5"], "diffusion2d": ["--stage2-backend", "patch"],
             "transparent": ["--no-planner", "--shadow-gradients", "--loss", "mse", "--domain", "frame", "--preset",
                             "paper", "--map-resolution", "16"]}.get(method, [])
    pack = tmp_path / "p.toml"
    pack.write_text('name = "p"\n[object]\nprimitive = "vase"\n[environment]\nbuiltin = "meadow"\n[render]\nspp = 3\n')
    spec = spec_of(str(pack), "--out", "x", "--method", method, "--seed", "5", "--target-spp", "9", "--views", "3",
                   *extra)
    text = tomli_w.dumps(spec.to_dict())
    back = RunSpec.from_dict(tomllib.loads(text))
    assert back == spec and back.to_dict() == spec.to_dict() and back.normalised() == spec
    assert back.seed == 5 and back.spp.target == 9 and back.pack.cameras.views == 3
    assert back.method == ("ganmouflage" if method.startswith("ganmouflage") else method)
    if method == "ours":
        assert back.stage1.iterations == 7 and back.stage2.strength == 0.3 and back.ablate == ("pose",)
        assert back.appearance.pose is False and back.pack.material.roughness == 0.2
        assert back.stage1_config().seed == 5 and back.stage1_config().spp == 4 and back.stage2_config().preview_spp == 16
    else:  # a baseline's spec holds only what it reads
        d = spec.to_dict()
        assert "stage2" not in d and "stages" not in d and "train" not in d["spp"] and "iterations" not in d["stage1"]
    if method == "transparent":
        assert (back.planner, back.shadow_gradients, back.stage1.loss, back.stage1.domain) == (False, True, "mse", "frame")
        assert back.preset == "paper" and back.appearance.map_resolution == 16 and back.options is None
    if method == "ganmouflage":
        assert back.options.iterations == 5
    if method == "ganmouflage-paper":
        assert back.options.preset == "paper" and back.options.iterations == 8000


@pytest.mark.parametrize("method, flags", [
    ("mean", ["--stage2-iterations", "3"]),
    ("mean", ["--spp", "2"]),
    ("random", ["--iterations", "3"]),
    ("transparent", ["--ablate", "pose"]),
    ("greedy", ["--stages", "1"]),
    ("diffusion2d", ["--checkpoint-every", "2"]),
    ("ganmouflage", ["--stage2-strength", "0.5"]),
    ("ganmouflage", ["--no-planner", "--lr-maps", "0.1"]),
    ("transparent", ["--sdxl-path", "/nowhere"]),
])
def test_a_flag_the_method_does_not_use_is_a_one_line_error(method, flags, tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["optimize", "gravel", "--method", method, "--out", str(out), *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    bad = next(f for f in flags if f.startswith("--") and f != "--no-planner")
    assert len(err) == 1 and err[0].startswith(f"camo: error: {bad} does not apply to --method {method}"), err
    assert not out.exists()


def test_flags_the_method_uses_are_taken():
    """--iterations is GANmouflage's training iterations (its own option), --stage2-backend diffusion2d's
    inpainter; ours keeps both for its stages."""
    gan = spec_of("gravel", "--out", "x", "--method", "ganmouflage", "--iterations", "11")
    assert gan.options.iterations == 11 and gan.stage1.iterations == 50  # (its default: a baseline has no Stage 1)
    diff = spec_of("gravel", "--out", "x", "--method", "diffusion2d", "--stage2-backend", "diffusers",
                   "--sdxl-path", "/a", "--controlnet-path", "/b")
    assert diff.options.backend == "diffusers" and diff.options.backend_options == {"sdxl_path": "/a",
                                                                                   "controlnet_path": "/b"}
    ours = spec_of("gravel", "--out", "x", "--iterations", "11", "--stage2-backend", "patch")
    assert ours.stage1.iterations == 11 and ours.stage2.backend == "patch" and ours.options is None


def test_absent_options_mean_the_spec_defaults():
    """optimizer.optimise.options.ABSENT (what camo grid drops from cell keys) is what an absent option gives."""
    from optimizer.optimise.options import ABSENT

    explicit = []
    for dest, value in ABSENT.items():
        explicit += [f"--{dest.replace('_', '-')}", str(value)] if value != "" else [f"--{dest.replace('_', '-')}="]
    assert spec_of("gravel", "--out", "x", *explicit) == spec_of("gravel", "--out", "x")


def test_spec_from_a_dict_refuses_what_the_method_does_not_use():
    from camo_base.errors import CamoError
    from optimizer.optimise.spec import RunSpec

    d = spec_of("gravel", "--out", "x", "--method", "mean").to_dict()
    with pytest.raises(CamoError, match="method mean does not use stage2.iterations"):
        RunSpec.from_dict({**d, "stage2": {"iterations": 3}})
    with pytest.raises(CamoError, match="unknown field"):
        RunSpec.from_dict({**d, "colour": 1})
    with pytest.raises(CamoError, match=r"\[spp\] target must be an integer"):
        RunSpec.from_dict({**d, "spp": {"target": "many"}})
    with pytest.raises(CamoError, match="no spec_version"):
        RunSpec.from_dict({k: v for k, v in d.items() if k != "spec_version"})
    with pytest.raises(CamoError, match="pack.render. spp is not part of a run"):
        RunSpec.from_dict({**d, "pack": {**d["pack"], "render": {"resolution": [8, 8], "spp": 4}}})
    import dataclasses

    from optimizer.optimise.stage2 import Stage2Settings

    spec = RunSpec.from_dict(d)
    with pytest.raises(CamoError, match="method mean does not use stage2.iterations"):
        dataclasses.replace(spec, stage2=Stage2Settings(iterations=3)).validate()


# --- run directories written before run specs -------------------------------------------------------------------

#: config.toml as camo wrote it before run specs (layout 1; from a real run at git 380cf23, with the values of TINY
#: and 10 iterations): a [run] table, the pack's spp set by --spp.
V1_CONFIG = """
[run]
scene = "gravel"
method = "ours"
stages = [1]
ablate = []
checkpoint_every = 5
planner = true
shadow_gradients = false
threads = 1
preset = "fast"
snapshot_every = 0
rough_start = true

[run.stage1]
iterations = 10
spp = 4
target_spp = 32
seed = 0
loss = "gated"
alpha = 1.0
eps = 0.01
domain = "object+shadow"
domain_dilate = 0.04
shadow_threshold = 0.05
silhouette_every = 4
warm_start = false
lr_schedule = "constant"
lr_floor = 0.1

[run.stage2]
iterations = 4
strength = 0.5
backend = "patch"
prompt = "background"
preview_spp = 16
displacement = true

[run.appearance]
map_resolution = 64
displacement_resolution = 32
displacement_bound = 0.02
translation_fraction = 0.05
allow_dz = false
pose = true
displacement = true
bsdf = true
transmittance = true
eta = 1.5
lr_maps = 0.01
lr_displacement = 0.05
lr_translation = 0.002
lr_rotation = 0.01
displacement_weight = 1.0
displacement_shrink = 0.5
freeze_displacement = false

[pack]
name = "gravel"
source = "builtin:gravel"

[pack.object]
primitive = "utility_box"
size = 1.0
rotation = [0.0, 0.0, -15.0]
translation = [0.0, 0.0, 0.0]
target_vertices = 1500

[pack.environment]
builtin = "gravel"
capture_height = 1.6
ground = true
ground_extent = 30.0
rotation = 0.0

[pack.cameras]
mode = "orbit"
views = 4
radius = 4.0
elevation = 20.0
fov = 30.0
azimuth_offset = 0.0

[pack.render]
resolution = [32, 32]
spp = 4

[pack.material]
albedo = [0.5, 0.5, 0.5]
metallic = 0.0
roughness = 0.5
transmittance = 0.75
eta = 1.5

[versions]
camo = "0.1.0"
mitsuba = "3.9.1"

[plan]
render_spp = 0

[plan.integrator]
type = "prb_projective"
max_depth = 6
rr_depth = 6
sppi = 0

[fingerprint]
value = "c23b18d7bb87ae7c"
"""


def test_run_directory_written_before_run_specs_still_evaluates(run_dir, tmp_path, capsys):
    """A run directory whose config.toml has the old layout: rundir reads it (same pack, appearance, method as the
    new layout gives), `camo evaluate` scores it exactly like the same result under a new config.toml, and
    `--resume` says in one line that it cannot continue it."""
    import dataclasses
    import shutil

    import pandas as pd

    from optimizer.assets.rundir import open_run

    old = tmp_path / "old_run"
    shutil.copytree(run_dir, old)
    (old / "config.toml").write_text(V1_CONFIG)
    a, b = open_run(old), open_run(run_dir)
    # the old layout predates --grad-blur and the displacement warm-up: its runs had per-texel gradients (0) and a
    # full displacement rate from the first step (0); today's fast preset blurs by 2 and ramps over 10 steps
    assert (a.app.grad_blur, a.app.displacement_warmup) == (0.0, 0) and (b.app.grad_blur, b.app.displacement_warmup) == (2.0, 10)
    assert (a.method, a.ablation, a.app) == (b.method, b.ablation,
                                             dataclasses.replace(b.app, grad_blur=0.0, displacement_warmup=0))
    assert a.pack.render.spp == 4 and a.pack == dataclasses.replace(b.pack, render=dataclasses.replace(b.pack.render, spp=4))
    assert (a.object, a.scene) == ("utility_box", "gravel")
    flags = ["--views", "2", "--spp", "4", "--metrics", "psnr,ssim", "--quiet", "--threads", "1"]
    assert main(["evaluate", str(old), "--out", str(tmp_path / "e_old"), *flags]) == 0
    assert main(["evaluate", str(run_dir), "--out", str(tmp_path / "e_new"), *flags]) == 0
    m_old = read_parquet(tmp_path / "e_old" / "metrics.parquet")
    m_new = read_parquet(tmp_path / "e_new" / "metrics.parquet")
    assert len(m_old) == len(m_new) == 2 * 2
    # same result, same cameras, same seeds, one render thread: the same numbers. (With 2 threads the LLVM render's
    # float order varies under load and a 4-spp sample path can branch differently: 0.02 dB apart was seen; a
    # different appearance, IOR or pack moves PSNR by tenths of a dB or more.)
    np.testing.assert_allclose(m_old["psnr"].to_numpy(), m_new["psnr"].to_numpy(), rtol=0, atol=1e-6)
    assert np.isfinite(m_old["psnr"]).all()
    capsys.readouterr()
    assert optimize(old, 12, "--resume") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "before run specs" in err[0] and "start a new run" in err[0]
    # a baseline's old layout ([run] method, [baseline] table) names its method too
    (old / "config.toml").write_text(V1_CONFIG.replace('method = "ours"', 'method = "mean"') +
                                     '\n[baseline]\nmethod = "mean"\n')
    assert open_run(old).method == "mean"


def test_every_flag_lands_in_its_spec_field():
    from optimizer.optimise.options import OPTIONS

    argv = ["gravel", "--out", "x", "--time-budget", "30", "--snapshot-every", "2", "--checkpoint-every", "3",
            "--warm-start", "off", "--lr-schedule", "cosine", "--lr-maps", "0.02", "--lr-displacement", "0.03",
            "--grad-blur", "1.5", "--map-update", "large_steps", "--map-smoothness", "4", "--displacement-bound", "0.01", "--stage2-fixed-displacement", "--stage2-backend", "diffusers",
            "--sdxl-path", "/a", "--controlnet-path", "/b", "--stage2-strength", "0.7", "--silhouette-every", "2",
            "--domain", "frame", "--loss", "mse", "--map-resolution", "40", "--displacement-resolution", "20",
            "--target-vertices", "500", "--views", "3", "--resolution", "16", "--spp", "3", "--target-spp", "9",
            "--seed", "8", "--preset", "paper", "--no-planner", "--shadow-gradients", "--stages", "1,2", "--ablate",
            "pose", "--init", "albedo=0.3", "--iterations", "5", "--stage2-iterations", "6", "--method", "ours",
            "--holdout-views", "3", "--holdout-every", "7", "--holdout-spp", "5", "--patience", "2",
            "--pose-search", "5", "--average", "0.8", "--roughness-search", "0.4,0.6", "--loss-clamp", "4",
            "--grad-clip", "2", "--init-search", "on", "--perceptual", "0.002", "--perceptual-net", "vgg",
            "--eta", "1.3", "--detail-match", "6", "--tint-match", "3", "--tint-scale", "1.5", "--clear-candidate", "1.1",
            "--clear-roughness", "0.4", "--shadow-weight", "2.5", "--coarse-grid", "2", "--coarse-lr", "0.02"]
    # the grain layer is projected by the warm start, which the first command line turns off: a second one
    argv_grain = ["gravel", "--out", "x", "--grain", "0.5", "--grain-sharpen", "1.5", "--warm-transmittance", "0.9",
                  "--warm-transmittance-low", "0.25", "--warm-transmittance-sun", "shadow"]
    flags = {a[2:].replace("-", "_") for a in argv + argv_grain if a.startswith("--")} - {"out"}
    assert flags == set(OPTIONS) - {"scene"}
    g = spec_of(*argv_grain).to_dict()["stage1"]
    assert (g["grain"], g["grain_sharpen"], g["warm_start"]) == (0.5, 1.5, True)
    assert (g["warm_transmittance"], g["warm_transmittance_low"], g["warm_transmittance_sun"]) == (0.9, 0.25, "shadow")
    d = spec_of(*argv).to_dict()
    assert {k: d[k] for k in ("seed", "preset", "stages", "ablate", "planner", "shadow_gradients", "rough_start",
                              "time_budget", "checkpoint_every", "snapshot_every", "spp")} == {
        "seed": 8, "preset": "paper", "stages": [1, 2], "ablate": ["pose"], "planner": False, "shadow_gradients": True,
        "rough_start": False, "time_budget": 30.0, "checkpoint_every": 3, "snapshot_every": 2,
        "spp": {"train": 3, "target": 9, "stage2_preview": 16}}
    assert d["stage1"] == {"iterations": 5, "loss": "mse", "alpha": 1.0, "eps": 0.01, "domain": "frame",
                           "domain_dilate": 0.04, "shadow_threshold": 0.05, "silhouette_every": 2, "warm_start": False,
                           "pose_search": 5, "lr_schedule": "cosine", "lr_floor": 0.1, "average": 0.8,
                           "roughness_search": [0.4, 0.6], "loss_clamp": 4.0, "grad_clip": 2.0, "init_search": True,
                           "perceptual": 0.002, "perceptual_net": "vgg", "detail_match": 6.0,
                           "tint_match": 3.0, "tint_scale": 1.5, "clear_candidate": 1.1, "clear_roughness": 0.4,
                           "coarse_grid": 2, "coarse_lr": 0.02, "shadow_weight": 2.5, "grain": 0.0, "grain_sharpen": 0.0,
                           "warm_transmittance": 0.0, "warm_transmittance_low": 1.0, "warm_transmittance_sun": "off"}
    assert d["stage2"] == {"iterations": 6, "strength": 0.7, "backend": "diffusers", "prompt": "background",
                           "displacement": False, "sdxl_path": "/a", "controlnet_path": "/b"}
    app = d["appearance"]
    assert (app["lr_maps"], app["lr_displacement"], app["displacement_bound"], app["map_resolution"],
            app["displacement_resolution"], app["pose"], app["grad_blur"]) == (0.02, 0.03, 0.01, 40, 20, False, 1.5)
    assert (app["map_update"], app["map_smoothness"], app["eta"]) == ("large_steps", 4.0, 1.3)
    assert d["holdout"] == {"views": 3, "every": 7, "spp": 5, "patience": 2, "noise_spp": 64}
    pack = d["pack"]
    assert pack["cameras"]["views"] == 3 and pack["render"] == {"resolution": [16, 16]}
    assert pack["object"]["target_vertices"] == 500 and pack["material"]["albedo"] == [0.3, 0.3, 0.3]


def test_cli_method_names_are_the_registry_s():
    from camo.cli import build_parser
    from optimizer.optimise.methods import METHOD_NAMES

    help_text = build_parser()._subparsers._group_actions[0].choices["optimize"].format_help()
    assert all(f"{name}:" in " ".join(help_text.split()) for name in METHOD_NAMES)  # the help is the registry's
    with pytest.raises(Exception, match="takes no options"):
        from optimizer.optimise.baselines.owens2014 import OwensOptions
        from optimizer.optimise.spec import RunSpec
        from optimizer.scenes.builtin_scenes import resolve_scene

        RunSpec(scene="gravel", pack=resolve_scene("gravel"), options=OwensOptions())


def test_spec_reruns_a_run_from_its_config_toml(run_dir, tmp_path, capsys):
    """`camo optimize --spec RUN_DIR` runs the recorded spec again: the same config.toml spec and, at one thread,
    the same maps bit for bit; `--seed` makes a replicate (only the seed differs); every other spec option, a
    SCENE next to --spec, a missing file and an old-layout config.toml are one-line errors."""
    import tomllib

    from optimizer.assets.rundir import PROVENANCE

    def spec_part(d):
        cfg = tomllib.loads((d / "config.toml").read_text())
        return {k: v for k, v in cfg.items() if k not in PROVENANCE}

    again = tmp_path / "again"
    assert main(["optimize", "--spec", str(run_dir), "--out", str(again), "--quiet", "--threads", "1"]) == 0
    assert spec_part(again) == spec_part(run_dir)
    for name in ("albedo", "roughness", "transmittance"):
        np.testing.assert_array_equal(np.load(again / "maps" / f"{name}.npy"), np.load(run_dir / "maps" / f"{name}.npy"))
    rep = tmp_path / "replicate"
    assert main(["optimize", "--spec", str(run_dir / "config.toml"), "--seed", "7", "--out", str(rep), "--quiet",
                 "--threads", "1"]) == 0
    a, b = spec_part(rep), spec_part(run_dir)
    assert a.pop("seed") == 7 and b.pop("seed", 0) == 0 and a == b
    assert not np.array_equal(np.load(rep / "maps" / "albedo.npy"), np.load(run_dir / "maps" / "albedo.npy"))

    old = tmp_path / "old"
    old.mkdir()
    (old / "config.toml").write_text(V1_CONFIG)
    for argv, needle in (
        (["--spec", str(run_dir), "--iterations", "3"], "--iterations would change it"),
        (["gravel", "--spec", str(run_dir)], "not both"),
        ([], "give a SCENE"),
        (["--spec", str(tmp_path / "nope.toml")], "no such file"),
        (["--spec", str(old)], "before run specs"),
    ):
        capsys.readouterr()
        assert main(["optimize", *argv, "--out", str(tmp_path / "x")]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("camo: error:") and needle in err[0], (argv, err)
    assert not (tmp_path / "x").exists()


def test_a_spec_built_in_python_has_no_preset_and_options_get_one():
    """RunSpec() field by field holds the dataclass defaults (the paper's values): it is not labelled with a preset;
    RunSpec.from_options applies one (default fast) and says so."""
    from optimizer.optimise.spec import RunSpec
    from optimizer.scenes.builtin_scenes import resolve_scene

    plain = RunSpec(scene="gravel", pack=resolve_scene("gravel")).validate()
    assert plain.preset is None and "preset" not in plain.to_dict()
    assert RunSpec.from_dict(plain.to_dict()) == plain
    assert RunSpec.from_options({"scene": "gravel"}).preset == "fast"
    paper = RunSpec.from_options({"scene": "gravel"}, preset="paper")
    assert paper.preset == "paper" and paper.stage1.iterations == 50 and paper.stage1.silhouette_every == 1
