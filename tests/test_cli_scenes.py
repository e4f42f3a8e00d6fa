"""`camo doctor`, `camo scenes list|render` and `camo plan` end to end."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from camo.cli import main


def test_doctor_reports_backend(capsys):
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "variant llvm_ad_rgb" in out or "variant cuda_ad_rgb" in out
    assert "test render            ok" in out and "status: ok" in out


def test_scenes_list_one_name_per_line(capsys):
    assert main(["scenes", "list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    names = [line.split("\t")[0] for line in lines]
    assert names == ["meadow", "gravel", "split", "room", "occluded", "panorama"]


@pytest.mark.parametrize("scene", ["room", "split:duck"])
def test_scenes_render_writes_every_view(tmp_path, scene, mi_backend):
    out = tmp_path / "r"
    assert main(["scenes", "render", scene, "--out", str(out), "--views", "2", "--resolution", "24", "--spp", "4"]) == 0
    for v in range(2):
        for suffix in ("bg.png", "obj.png", "mask.png", "bg.exr", "obj.exr", "depth.exr"):
            assert (out / f"view_{v:02d}_{suffix}").is_file()
    from camo_base.imaging import load_exr, load_png

    mask = load_png(out / "view_00_mask.png")
    assert 0.02 < mask.mean() < 0.6  # the object is in the frame, not everywhere
    bg, obj = load_exr(out / "view_00_bg.exr"), load_exr(out / "view_00_obj.exr")
    assert bg.shape == (24, 24, 3) and np.isfinite(obj).all()
    assert np.abs(obj - bg)[mask > 0.5].mean() > np.abs(obj - bg)[mask < 0.5].mean()
    meta = json.loads((out / "scene.json").read_text())
    assert meta["plan"]["integrator"]["type"] == "path" and len(meta["cameras"]) == 2


def test_plan_prints_reasons(capsys):
    assert main(["plan", "room", "--ablate", "pose,displacement", "--no-pilot"]) == 0
    out = capsys.readouterr().out
    assert "integrator: {'type': 'prb'" in out and "- max_depth: 12" in out and "- sensors:" in out
    assert main(["plan", "room", "--ablate", "wings"]) == 2
    capsys.readouterr()
    assert main(["plan", "room", "--denoise", "oidn-through", "--no-pilot"]) == 2  # the evaluation's denoiser only
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "only with --purpose evaluate" in err[0], err
    assert main(["plan", "room", "--purpose", "evaluate", "--denoise", "bm3d"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "invalid choice: 'bm3d'" in err[0], err
    for extra in (["--purpose", "evaluate"], ["--no-pilot"]):  # a timed cut is the training plan's, from its pilot
        assert main(["plan", "room", "--timed", *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--timed: only with --purpose optimize" in err[0], err


def test_plan_runs_the_pilot_and_draws_the_curve(tmp_path, capsys, mi_backend):
    """`camo plan`: the pilot's decisions with their measured contributions, spp per stage, and the accuracy-vs-
    seconds curve of the plan and of full path tracing, as text and as a PNG."""
    png = tmp_path / "curve.png"
    assert main(["plan", "meadow", "--resolution", "32", "--views", "4", "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "pilot: 4 views" in out and "measured effects" in out and "transmissive chains" in out
    assert "spp per stage" in out and "accuracy vs seconds" in out and f"wrote {png}" in out
    from camo_base.imaging import load_png

    assert load_png(png).shape[0] > 100
    assert main(["plan", "meadow", "--purpose", "evaluate", "--resolution", "32", "--views", "4"]) == 0
    out = capsys.readouterr().out
    assert "integrator: {'type': 'path'" in out and "the whole frame" in out
    assert "object spp" not in out
    # with the see-through denoiser: its reason and the object's spp factor, measured by its own pilot
    assert main(["plan", "meadow", "--purpose", "evaluate", "--resolution", "32", "--views", "2", "--spp", "16",
                 "--denoise", "oidn-through"]) == 0
    out = capsys.readouterr().out
    assert "- denoise: oidn-through" in out and "- object spp: the denoised object and rim are" in out, out
    assert main(["plan", "meadow", "--png", str(tmp_path / "curve.jpg")]) == 2
    assert "must end in .png" in capsys.readouterr().err


def test_plan_timed_prices_the_room_s_depth_cut_in_seconds(capsys, mi_backend):
    """`camo plan --timed`: the room's opaque start has an admissible cut (to 3); timed, its row gives the seconds at
    the cut and at depth 12 and the path vertices, and the depth follows the timed saving (10 %); untimed (a run's
    plan) the same row is priced in path vertices only."""
    args = ["plan", "room", "--ablate", "transmittance", "--resolution", "32", "--views", "4", "--spp", "4"]
    assert main([*args, "--timed"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if "depth cut to 3" in line)
    assert "of a training render's seconds (timed" in row and "path vertices:" in row, row
    saving = float(row.split("(saves ")[1].split("%")[0])
    assert f"- max_depth: {3 if saving >= 10 else 12}" in out
    assert main(args) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if "depth cut to 3" in line)
    assert "of the path vertices (not timed)" in row and "seconds" not in row.split("depth cut to 3")[1].split(")")[0]


def test_closed_stdout_is_not_a_traceback():
    """`camo scenes list | head -0`: the reader is gone before camo writes; exit 141 like a shell pipeline, no traceback."""
    proc = subprocess.Popen([sys.executable, "-m", "camo.cli", "scenes", "list"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141
    assert "Traceback" not in err, err
