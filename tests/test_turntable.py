"""``camo video``: path-traced turntables of run directories and assets.

Checks: the orbit is the evaluation's rig without jitter (a full turn passes through every training camera); the
panels share each frame's sampler seed (pixels whose paths miss the object are identical in the background and the
object panels); the layout and difference row are what they say; the encoders round-trip; the recorded plan is
read through one function; a real Ctrl-C of the command and a rerun continue from the cached frames; the time
budget chooses spp from a pilot; bad input is one line, exit 2, and an earlier video stays untouched.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from camo.cli import main

REPO = Path(__file__).resolve().parents[1]
BASE = ["--views", "4", "--resolution", "32", "--map-resolution", "32", "--target-vertices", "1500",
        "--target-spp", "8", "--quiet"]
TINY_VIDEO = ["--frames", "8", "--resolution", "32", "--spp", "2", "--quiet"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two baseline runs of meadow (seconds each, unlike a run of ours) and their scene."""
    root = tmp_path_factory.mktemp("turntable_runs")
    out = {}
    for m in ("mean", "random"):
        out[m] = root / m
        assert main(["optimize", "meadow", "--method", m, "--out", str(out[m]), *BASE]) == 0
    return out


def _one_line_error(capsys, rc):
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert err.startswith("camo: error: ") and "\n" not in err, err
    return err


# ------------------------------------------------------------------------------------------ cameras and seeds


def test_full_turn_passes_through_every_training_camera(runs):
    from evaluation.turntable import evaluation_orbit
    from optimizer.assets.rundir import open_run
    from optimizer.scenes.cameras import cameras

    pack = open_run(runs["mean"]).pack
    train = cameras(pack, (64, 64))
    orbit = evaluation_orbit(pack, frames=4 * len(train), resolution=64)
    cams = orbit.cameras()
    assert orbit.full_turn and len(cams) == 4 * len(train)
    for v, t in enumerate(train):  # every 4th frame is a training camera: radius, elevation, start, target, fov
        c = cams[4 * v]
        assert np.allclose(c.origin, t.origin, atol=1e-9) and np.allclose(c.target, t.target)
        assert c.fov == t.fov and (c.width, c.height) == (64, 64)
    # a full turn leaves out its end point (a seamless loop); equal steps
    az = orbit.azimuths()
    assert np.allclose(np.diff(az), 360.0 / len(az)) and az[-1] < az[0] + 360.0
    # an arc includes both ends
    arc = evaluation_orbit(pack, frames=5, arc=90.0, start=10.0, resolution=64)
    assert arc.azimuths() == [10.0, 32.5, 55.0, 77.5, 100.0]
    r = [math.dist(c.origin, c.target) for c in arc.cameras()]
    assert np.allclose(r, pack.cameras.radius)


def test_camera_list_rigs_orbit_at_their_mean_distance_and_elevation():
    from evaluation.turntable import evaluation_orbit
    from optimizer.scenes.scenepack import parse_pack

    r, el = 5.0, math.radians(30.0)
    pos = [[r * math.cos(el) * math.cos(a), r * math.cos(el) * math.sin(a), 0.5 + r * math.sin(el)]
           for a in (0.3, 1.9, 4.0)]
    pack = parse_pack({"name": "l", "object": {"primitive": "vase"}, "environment": {"builtin": "gravel"},
                       "cameras": {"mode": "list", "positions": pos, "targets": [[0, 0, 0.5]] * 3, "fov": 40.0}})
    orbit = evaluation_orbit(pack, frames=12, resolution=32)
    assert orbit.radius == pytest.approx(r) and orbit.elevation == pytest.approx(30.0)
    assert orbit.centre == pytest.approx((0, 0, 0.5)) and orbit.start == pytest.approx(math.degrees(0.3))
    assert np.allclose(orbit.cameras()[0].origin, pos[0]) and orbit.fov == 40.0


def test_frame_seeds_come_from_the_seed_table():
    from camo_base import seeds
    from evaluation.turntable import frame_seed

    assert frame_seed(0, 0) == 611953 and frame_seed(2, 3) == (2 * 7919 + 611953 + 3)
    assert frame_seed(1, 5) == seeds.seed("turntable_render", 1, frame=5)
    assert len({frame_seed(0, f) for f in range(120)}) == 120


# ------------------------------------------------------------------------------------------ layout, codecs


def test_compose_places_panels_labels_and_the_difference_row():
    from evaluation.turntable import BACKDROP, DIFF_GAIN, compose, layout_for

    rng = np.random.default_rng(0)
    bg = rng.integers(0, 200, (40, 40, 3), dtype=np.uint8)
    obj = bg.copy()
    obj[10:20, 10:20] = 250
    lay = layout_for(40, 40, 2, difference=True, labels=True)
    frame = compose(lay, [bg, obj], ["background", "ours"])
    w, h = lay.size
    assert frame.shape == (h, w, 3) and w == 2 * 40 + lay.gap and h == lay.bar + 2 * 40 + lay.gap
    x0, y0 = lay.origin(0, 0)
    x1, y1 = lay.origin(0, 1)
    assert np.array_equal(frame[y0:y0 + 40, x0:x0 + 40], bg) and np.array_equal(frame[y1:y1 + 40, x1:x1 + 40], obj)
    dx, dy = lay.origin(1, 1)
    want = np.clip(DIFF_GAIN * np.abs(obj.astype(np.float32) - bg), 0, 255).astype(np.uint8)
    assert np.array_equal(frame[dy:dy + 40, dx:dx + 40], want)
    bar = frame[:lay.bar]  # the labels are drawn in the bar, in light text on the backdrop
    assert (bar > 200).any() and (np.abs(bar.astype(int) - BACKDROP).sum(-1) == 0).mean() > 0.5
    # one panel: no bar, no row
    single = layout_for(40, 40, 1, difference=False, labels=False)
    assert single.size == (40, 40) and np.array_equal(compose(single, [obj], ["x"], None), obj)


def test_video_and_animation_round_trip(tmp_path):
    from evaluation.video import read_video, video_info, write_animation, write_video

    rng = np.random.default_rng(1)
    base = (rng.random((1, 1, 3)) * 255).astype(np.uint8)
    frames = []
    for k in range(10):  # smooth moving gradients (what a video codec is for)
        y, x = np.mgrid[0:37, 0:51]
        f = np.clip(128 + 100 * np.sin((x + 3 * k) / 8.0)[..., None] * np.cos(y / 9.0)[..., None] + base * 0.2, 0,
                    255).astype(np.uint8)
        frames.append(np.repeat(f, 3, axis=-1) if f.shape[-1] == 1 else f)
    for name, codec in (("a.mp4", "h264"), ("a.webm", "vp9")):
        info = write_video(tmp_path / name, frames, 12.0, codec)
        got = video_info(tmp_path / name)
        assert got["frames"] == 10 and (got["width"], got["height"]) == (52, 38)  # padded to even sizes
        assert got["pix_fmt"] == "yuv420p" and got["codec"] == {"h264": "h264", "vp9": "vp9"}[codec]
        assert info["bytes"] == (tmp_path / name).stat().st_size and abs(got["fps"] - 12.0) < 1e-6
        dec = list(read_video(tmp_path / name))
        err = np.mean([np.mean((d[:37, :51].astype(float) - f) ** 2) for d, f in zip(dec, frames)])
        assert 10 * np.log10(255 ** 2 / err) > 30  # dB
    n = write_animation(tmp_path / "a.webp", frames, 12.0)
    with Image.open(tmp_path / "a.webp") as im:
        assert im.n_frames == 10 and n == (tmp_path / "a.webp").stat().st_size
    write_animation(tmp_path / "a.gif", frames, 12.0)
    with Image.open(tmp_path / "a.gif") as im:
        assert im.n_frames == 10 and im.info.get("loop") == 0


def test_budget_arithmetic():
    from evaluation.turntable import MAX_SPP, fit_cost, spp_for_budget

    a, b = fit_cost(0.3, 0.9, 1, 4)
    assert a == pytest.approx(0.1) and b == pytest.approx(0.2)
    assert spp_for_budget(100.0, 10, a, b) == 49  # 10 * (0.1 + 0.2 * 49) = 99 s
    assert spp_for_budget(1.0, 10, a, b) == 0
    assert spp_for_budget(1e9, 1, a, b) == MAX_SPP
    assert fit_cost(1.0, 0.5, 1, 4)[1] > 0  # timing noise never gives a free sample


# ------------------------------------------------------------------------------------------ the recorded plan


def test_recorded_plan_is_read_from_either_layout():
    from optimizer.assets.rundir import recorded_plan

    cfg = {"plan": {"integrator": {"type": "prb_projective", "max_depth": 6}, "reasons": ["max_depth: 6"]}}
    summ = {"final_render": {"integrator": {"type": "path", "max_depth": 6, "rr_depth": 6}, "spp": 8}}
    p = recorded_plan(cfg, summ)
    assert p.training["type"] == "prb_projective" and p.render["type"] == "path" and p.max_depth == 6
    assert p.reasons == ("max_depth: 6",)
    # a planner that records its own plan in summary.json, per purpose, wins
    summ2 = {**summ, "plan": {"integrator": {"type": "prb", "max_depth": 3},
                              "evaluate": {"integrator": {"type": "path", "max_depth": 9}}, "reasons": ["measured"]}}
    p2 = recorded_plan(cfg, summ2)
    assert p2.render == {"type": "path", "max_depth": 9} and p2.max_depth == 9 and p2.reasons == ("measured",)
    assert recorded_plan({}, {}).max_depth is None and recorded_plan({}, {}).render is None


def test_video_integrator_is_the_evaluations_deepened_by_a_recorded_plan(runs, mi_backend):
    import dataclasses

    from evaluation.inputs import InputSpec, resolve
    from evaluation.turntable import video_integrator
    from evaluation.views import evaluation_plan
    from optimizer.assets.rundir import RecordedPlan
    from optimizer.scenes.environments import get_environment

    (e,) = resolve([InputSpec("run", str(runs["mean"]))])
    env = get_environment(e.pack.environment)
    integ, why = video_integrator(e.pack, env, [e])
    assert integ == evaluation_plan(e.pack, env).integrator and "evaluation path tracer" in why[0]

    class Deeper:  # a run whose recorded plan renders deeper
        def __init__(self, run):
            self.run = run

        def recorded_plan(self):
            return RecordedPlan({"type": "path", "max_depth": integ["max_depth"] + 2}, None, (), {})

    deep = dataclasses.replace(e, run=Deeper(e.run))
    integ2, why2 = video_integrator(e.pack, env, [e, deep])
    assert integ2["max_depth"] == integ["max_depth"] + 2 and integ2["rr_depth"] == integ["rr_depth"]
    assert "recorded plan" in why2[-1]


# ------------------------------------------------------------------------------------------ end to end


def _png(path):
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def test_side_by_side_video_end_to_end(runs, tmp_path, capsys):
    from evaluation.turntable import read_sidecar
    from evaluation.video import read_video, video_info

    out = tmp_path / "tt.mp4"
    glb = runs["random"] / "result.glb"  # an external asset of the same scene beside the two runs
    rc = main(["video", str(runs["mean"]), str(runs["random"]), "--asset", str(glb), "--scene", "meadow",
               "--method", "theirs", "--out", str(out), "--difference", *TINY_VIDEO])
    assert rc == 0, capsys.readouterr().err
    assert "wrote" in capsys.readouterr().out
    rec = read_sidecar(out)
    assert rec["panels"] == ["background", "Mean [6]", "Random [6]", "theirs"]
    assert rec["spp"] == 2 and rec["integrator"]["type"] == "path" and rec["difference"] is True
    assert rec["seconds"]["rendered"] == 8 * 4 and rec["seconds"]["cached"] == 0
    info = video_info(out)
    assert info["frames"] == 8 and info["codec"] == "h264"
    assert (info["width"], info["height"]) == (rec["layout"]["width"], rec["layout"]["height"])
    with Image.open(tmp_path / "tt.webp") as im:
        assert im.n_frames == 8
    # the cache: one folder per panel, one PNG per frame; the video shows them (H.264 at crf 18)
    cache = Path(rec["cache"])
    folders = sorted(p for p in cache.iterdir() if p.is_dir())
    assert len(folders) == 4 and all(len(list(f.glob("*.png"))) == 8 for f in folders)
    # common random numbers: far from the object the background and an object panel agree pixel for pixel
    bg_dir = next(f for f in folders if f.name.startswith("background-"))
    mean_dir = next(f for f in folders if f.name.startswith("mean-"))
    # file names are hashes that include the panel: frames are matched by order of creation (frame by frame)
    bg_frames = [_png(p) for p in sorted(bg_dir.glob("*.png"), key=lambda p: p.stat().st_mtime_ns)]
    mean_frames = [_png(p) for p in sorted(mean_dir.glob("*.png"), key=lambda p: p.stat().st_mtime_ns)]
    identical = [np.mean(np.all(a == b, axis=-1)) for a, b in zip(bg_frames, mean_frames)]
    assert min(identical) > 0.5, identical  # the object and its shadow cover less than half of a 32 px frame
    decoded = list(read_video(out))
    from evaluation.turntable import layout_for

    lay = layout_for(32, 32, 4, True, True)
    x, y = lay.origin(0, 0)
    err = np.mean([(d[y:y + 32, x:x + 32].astype(float) - b) ** 2 for d, b in zip(decoded, bg_frames)])
    assert 10 * np.log10(255 ** 2 / err) > 28


def test_first_frame_is_the_evaluation_camera(runs, tmp_path):
    """Frame 0 at the run's resolution is the run's training view 0 without jitter: its background panel matches the
    run's own (independently rendered, other spp and seed) background of view 0."""
    from evaluation.turntable import read_sidecar

    out = tmp_path / "one.mp4"
    assert main(["video", str(runs["mean"]), "--side-by-side", "--out", str(out), "--frames", "4", "--resolution",
                 "32", "--spp", "16", "--no-preview", "--quiet"]) == 0
    rec = read_sidecar(out)
    cache = Path(rec["cache"])
    bg_dir = next(p for p in cache.iterdir() if p.name.startswith("background-"))
    first = min(bg_dir.glob("*.png"), key=lambda p: p.stat().st_mtime_ns)
    from camo_base.imaging import linear_to_srgb

    ref = linear_to_srgb(np.load(runs["mean"] / "renders.npz")["background"][0]) * 255
    got = _png(first).astype(float)

    def blur(a):  # 4x4 box means: compare the picture, not the noise
        return a.reshape(8, 4, 8, 4, 3).mean((1, 3))

    assert np.abs(blur(got) - blur(ref)).mean() < 6.0  # same camera; a turned or moved one differs by tens
    shifted = np.roll(blur(ref), 2, axis=1)
    assert np.abs(blur(got) - shifted).mean() > np.abs(blur(got) - blur(ref)).mean()


def test_interrupted_video_continues_from_its_cached_frames(runs, tmp_path):
    """A real Ctrl-C (SIGINT) of `camo video` in a subprocess, then the same command again."""
    out = tmp_path / "int.mp4"
    out.write_bytes(b"an earlier video")
    cmd = [sys.executable, "-m", "camo.cli", "video", str(runs["mean"]), "--out", str(out), "--frames", "48",
           "--resolution", "32", "--spp", "64", "--no-preview", "--side-by-side"]
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cache = Path(str(out) + ".frames")

    def finished_frames():  # pathlib's glob also matches the dot-named half-written frame, which an interrupt removes
        return [p for p in cache.glob("*/*.png") if not p.name.startswith(".")]

    # SIGINT as a terminal leaves it: a test run started in the background (`nohup ... &`, a CI runner) ignores
    # SIGINT, an ignored signal is inherited, and Python then installs no KeyboardInterrupt handler -- the command
    # rendered on and exited 0 (seen in a pytest-xdist worker, which had not imported anything that resets it)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 240
        # interrupt early (4 of 96 panel frames) and poll often: under load the render once finished all 48 of
        # an earlier 24-frame version before the 0.2 s poll saw 6 frames
        while time.monotonic() < deadline and len(finished_frames()) < 4:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert "interrupted:" in stderr and "run the same command again" in stderr
    assert "panel frames [" in stderr and "<" in stderr.split("panel frames [")[-1]  # the progress bar and its ETA
    assert out.read_bytes() == b"an earlier video"  # nothing replaced it
    kept = {p: p.read_bytes() for p in finished_frames()}
    assert 4 <= len(kept) < 96
    assert not list(cache.glob("*/.*.png"))  # no half-written frame
    r = subprocess.run(cmd + ["--quiet"], env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    rec = json.loads(Path(str(out) + ".json").read_text())
    assert rec["seconds"]["cached"] == len(kept) and rec["seconds"]["rendered"] == 96 - len(kept)
    assert all(p.read_bytes() == b for p, b in kept.items())  # cached frames were used, not rendered again
    from evaluation.video import video_info

    assert video_info(out)["frames"] == 48


def test_time_budget_chooses_spp_from_a_pilot(runs, tmp_path, capsys):
    from evaluation.turntable import read_sidecar

    out = tmp_path / "budget.mp4"
    args = ["video", str(runs["mean"]), "--out", str(out), "--frames", "6", "--resolution", "32", "--no-preview",
            "--time-budget", "12"]
    assert main(args) == 0
    err = capsys.readouterr().err
    rec = read_sidecar(out)
    pilot = rec["pilot"]
    assert "pilot" in err and rec["spp"] == pilot["spp"] >= 1 and pilot["renders"] == 6
    assert pilot["estimate"] <= 12 - pilot["pilot_seconds"] + 1e-6
    assert pilot["estimate"] == pytest.approx(6 * (pilot["fixed"] + pilot["per_sample"] * pilot["spp"]))
    # the same command again keeps the spp its pilot chose (and so every cached frame)
    assert main(args) == 0
    assert "chosen by this budget's pilot earlier" in capsys.readouterr().err
    assert read_sidecar(out)["seconds"]["cached"] == 6
    # a budget that cannot be met: one line, nothing written
    short = tmp_path / "short.mp4"
    rc = main(["video", str(runs["mean"]), "--out", str(short), "--frames", "200", "--resolution", "32",
               "--time-budget", "0.5", "--quiet"])
    assert "too short" in _one_line_error(capsys, rc) and not short.exists()


@pytest.mark.parametrize("extra, message", [
    (["--codec", "mpeg2"], "unknown --codec"),
    (["--codec", "vp9", "--out-suffix", ".mkv"], None),
    (["--frames", "1"], "--frames: must be an integer in [2, 10000]"),
    (["--frames", "0"], "--frames"),
    (["--resolution", "8"], "--resolution"),
    (["--spp", "0"], "--spp"),
    (["--arc", "0"], "--arc"),
    (["--arc", "400"], "--arc"),
    (["--arc", "nan"], "--arc"),
    (["--fps", "0"], "--fps"),
    (["--elevation", "95"], "--elevation"),
    (["--radius", "-1"], "--radius"),
    (["--quality", "99"], "--quality"),
    (["--spp", "4", "--time-budget", "10"], "not both"),
    (["--time-budget", "-3"], "--time-budget"),
    (["--preview", "x.png"], "--preview"),
])
def test_bad_settings_are_one_line_errors_that_keep_the_earlier_video(runs, tmp_path, capsys, extra, message):
    out = tmp_path / "v.mp4"
    out.write_bytes(b"earlier")
    if "--out-suffix" in extra:  # h264 cannot go into WebM: the pair is checked too
        extra = ["--codec", "h264"]
        out = tmp_path / "v.webm"
        message = "cannot be written to a .webm"
    rc = main(["video", str(runs["mean"]), "--out", str(out), *extra, "--quiet"])
    err = _one_line_error(capsys, rc)
    assert message in err, err
    assert not out.exists() or out.read_bytes() == b"earlier"
    assert not Path(str(out) + ".frames").exists()


def test_bad_inputs_are_one_line_errors(runs, tmp_path, capsys):
    import shutil

    out = tmp_path / "v.mp4"
    rc = main(["video", str(tmp_path / "nope"), "--out", str(out), "--quiet"])
    assert "run directory not found" in _one_line_error(capsys, rc)
    broken = tmp_path / "no_result"  # a run directory whose result files are missing
    shutil.copytree(runs["mean"], broken)
    (broken / "result.ply").unlink()
    rc = main(["video", str(broken), "--out", str(out), "--quiet"])
    assert "incomplete run directory" in _one_line_error(capsys, rc)
    rc = main(["video", "--out", str(out), "--quiet"])
    assert "at least one input" in _one_line_error(capsys, rc)
    rc = main(["video", str(runs["mean"]), "--asset", str(runs["mean"] / "result.glb"), "--scene", "gravel",
               "--method", "x", "--out", str(out), "--quiet"])
    assert "different scenes" in _one_line_error(capsys, rc)
    rc = main(["video", str(runs["mean"]), "--out", str(tmp_path), "--quiet"])
    assert "is a folder" in _one_line_error(capsys, rc)
    rc = main(["video", str(runs["mean"]), "--out", str(tmp_path / "v.avi"), "--quiet"])
    assert "must end in" in _one_line_error(capsys, rc)
    trip = tmp_path / "trip.toml"
    trip.write_text(f'[[triplets]]\npath = "{tmp_path}"\nmethod = "2d"\n')
    rc = main(["video", "--inputs", str(trip), "--out", str(out), "--quiet"])
    err = _one_line_error(capsys, rc)
    assert "triplets" in err or "no triplets" in err
    assert not out.exists()
