"""bench/bench_giveaways.py: the contact sheets (where they go, which arms they show) and the arms that run an
edited run spec."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

def test_contact_sheet_finds_arms_in_later_evaluations(tmp_path, bench_module):
    """bench_giveaways.contact_sheet: an arm evaluated later (``eval_NAME/SCENE``) is a column beside the first
    evaluation's arms, the background first and Mean last; one row per view, zoomed 3x."""
    bg_ = bench_module("bench_giveaways")
    img = np.zeros((8, 10, 3), np.uint8)
    for ev, run in (("eval", "today"), ("eval", "mean"), ("eval_later", "r5")):
        d = tmp_path / ev / "meadow" / "renders" / f"meadow-{run}"
        d.mkdir(parents=True)
        for v in range(2):
            for kind in ("bg", "obj"):
                Image.fromarray(img).save(d / f"view_{v:02d}_{kind}.png")
    dest = bg_.contact_sheet(tmp_path / "eval" / "meadow", "meadow", ["today", "r5", "missing"], tmp_path / "s.png")
    w, h = Image.open(dest).size
    assert (w, h) == (4 * (30 + 4) + 4, 22 + 2 * (24 + 4) + 4)  # background, today, r5, Mean; 2 views
    assert bg_.sheet_path(tmp_path, "caustic", "meadow", True) == tmp_path / "giveaways_caustic_meadow.png"

def test_spec_field_arm_runs_its_edited_spec(tmp_path, bench_module, monkeypatch):
    """bench_giveaways: an arm with a spec field no flag sets (``coarse1_auto_r5_keepdisp``: the displacement's
    proximal L1 step off) runs ``camo optimize --spec``; that spec is its flags' spec (clear glass, coarse level) with
    only ``appearance.displacement_shrink`` changed, 0.5 -> 0, and it loads back as a run spec."""
    from camo.cli import build_parser
    from camo.optimize_cli import spec_of
    from optimizer.optimise.spec import spec_from_file

    bg_ = bench_module("bench_giveaways")
    calls = []
    monkeypatch.setattr(bg_, "camo", lambda *a: calls.append(a))
    bg_.optimise(tmp_path, "meadow", ["coarse1_auto_r5_keepdisp"], ["--iterations", "2"], mean=False)
    run = tmp_path / "runs" / "meadow-coarse1_auto_r5_keepdisp"
    spec_path = run.with_name(run.name + ".spec.toml")
    assert calls == [("optimize", "--spec", str(spec_path), "--out", str(run), "--quiet")]
    edited = spec_from_file(str(spec_path))
    flags = spec_of(build_parser().parse_args(["optimize", "meadow", "--out", str(run), *bg_.SIZE,
                                               "--displacement-resolution", "64", "--iterations", "2",
                                               *bg_.ARMS["coarse1_auto_r5_keepdisp"]]))
    assert flags.appearance.displacement_shrink == 0.5 and edited.appearance.displacement_shrink == 0.0
    assert edited.stage1.clear_candidate == 1.05 and edited.stage1.clear_roughness == 0.5
    assert edited.stage1.coarse_grid == 1 and edited.stage1.iterations == 2
    a, b = flags.to_dict(), edited.to_dict()
    a["appearance"].pop("displacement_shrink"), b["appearance"].pop("displacement_shrink")
    assert a == b

    with pytest.raises(SystemExit, match="no field appearance.nonexistent"):
        bg_.spec_file(["meadow", "--out", str(run)], {"appearance.nonexistent": 1.0}, tmp_path / "x.toml")


def test_baseline_arms_run_their_method_and_sheets_can_be_jpeg(tmp_path, bench_module, monkeypatch):
    """bench_giveaways: a baseline arm (``transparent_eta105``) runs ``camo optimize --method transparent --eta 1.05``
    with the bench's sizes and no Stage 1 flags; a ``.jpg`` contact sheet is a JPEG of the same size as the PNG."""
    bg_ = bench_module("bench_giveaways")
    calls = []
    monkeypatch.setattr(bg_, "camo", lambda *a: calls.append(a))
    bg_.optimise(tmp_path, "meadow", ["transparent_eta105"], ["--iterations", "2"], mean=False)
    run = str(tmp_path / "runs" / "meadow-transparent_eta105")
    assert calls == [("optimize", "meadow", "--method", "transparent", "--eta", "1.05", "--out", run, *bg_.SIZE,
                      "--quiet")]
    img = np.zeros((8, 10, 3), np.uint8)
    for run_ in ("today", "mean"):
        d = tmp_path / "eval" / "meadow" / "renders" / f"meadow-{run_}"
        d.mkdir(parents=True)
        for kind in ("bg", "obj"):
            Image.fromarray(img).save(d / f"view_00_{kind}.png")
    png = bg_.contact_sheet(tmp_path / "eval" / "meadow", "meadow", ["today"], tmp_path / "s.png")
    jpg = bg_.contact_sheet(tmp_path / "eval" / "meadow", "meadow", ["today"], tmp_path / "s.jpg")
    assert Image.open(jpg).format == "JPEG" and Image.open(png).format == "PNG"
    assert Image.open(jpg).size == Image.open(png).size == (3 * (30 + 4) + 4, 22 + (24 + 4) + 4)
