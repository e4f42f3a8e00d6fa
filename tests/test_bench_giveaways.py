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


def _points():
    """Two scenes' rows as bench_giveaways.measures gives them: today, a floor sweep and Mean (the values of the
    warmt / warmsun tables of giveaways.md, rounded)."""
    import pandas as pd

    rows = [("meadow", "today", 33.15, 0.165, 0.60, 2.15, 0.63), ("meadow", "warmt01", 31.47, 0.231, 0.96, 1.36, 0.77),
            ("meadow", "warmt05", 32.27, 0.203, 0.80, 4.84, 0.70), ("meadow", "warmt035", 33.00, 0.170, 0.85, 1.60, 0.65),
            ("meadow", "worse", 31.00, 0.240, 0.96, 1.40, 0.80), ("meadow", "mean", 27.91, 0.394, 0.89, 7.82, 0.44),
            ("gravel", "warmt01", 33.25, 0.168, 1.05, 1.58, 0.64)]  # gravel without today: left out
    return pd.DataFrame([dict(zip(("scene", "arm", "psnr", "lpips_proxy", "detail_ratio", "tint", "shadow"), r))
                         for r in rows])


def test_pareto_front_and_targets_against_today(bench_module):
    """bench_giveaways.against_base: Δ PSNR and Δ LPIPS-proxy against today of the same scene, the tint as a share of
    today's, the detail band 0.8-1.25, the Pareto front over (PSNR, LPIPS-proxy, |ln detail|, tint) and ``meets``
    (band, tint cut, at most 0.3 dB and 0.01 LPIPS-proxy worse); Mean and a scene without today are left out."""
    bg_ = bench_module("bench_giveaways")
    t = bg_.against_base(_points()).set_index("arm")
    assert list(t.index) == ["today", "warmt01", "warmt05", "warmt035", "worse"]  # no Mean, no gravel
    assert t.loc["warmt01", "d_psnr"] == pytest.approx(-1.68) and t.loc["warmt01", "d_lpips"] == pytest.approx(0.066)
    assert t.loc["warmt01", "tint_share"] == pytest.approx(1.36 / 2.15)
    assert t.in_band.to_dict() == {"today": False, "warmt01": True, "warmt05": True, "warmt035": True, "worse": True}
    # "worse" is beaten on all four by warmt01 (lower PSNR, higher LPIPS-proxy, same detail, more tint), warmt05 by
    # warmt035 (33.00 > 32.27 dB, 0.170 < 0.203, |ln 0.85| < |ln 0.80|, 1.60 < 4.84 ΔE)
    assert t.pareto.to_dict() == {"today": True, "warmt01": True, "warmt05": False, "warmt035": True, "worse": False}
    # warmt035: in the band, tint 74 % of today's, -0.15 dB, +0.005: meets; warmt05's tint is worse, warmt01's PSNR
    assert t.meets.to_dict() == {"today": False, "warmt01": False, "warmt05": False, "warmt035": True, "worse": False}
    # a stricter tolerance drops warmt035 (0.15 dB below today)
    assert not bg_.against_base(_points(), psnr_tol=0.1).set_index("arm").loc["warmt035", "meets"]
    md = bg_.tradeoff_table(_points())
    assert "| meadow | warmt035 | 33.00 | -0.15 | +0.005 | **0.85** | 1.60 (74%) | 0.65 | yes | **yes** |" in md
    assert "| meadow | today | 33.15 | +0.00 | +0.000 | 0.60 | 2.15 (100%) | 0.63 | yes | no |" in md


def test_tradeoff_plot_writes_a_png_per_scene_row(tmp_path, bench_module):
    """bench_giveaways.tradeoff_plot: one row of two panels per scene with today, 7.5 x 2.6 inches at 90 dpi."""
    bg_ = bench_module("bench_giveaways")
    df = _points()
    dest = bg_.tradeoff_plot(df[df.scene == "meadow"], tmp_path / "p.png", curve=["warmt01", "warmt035", "warmt05"])
    im = Image.open(dest)
    assert im.format == "PNG" and im.size == (675, 234)
    two = pd_concat_scene(df)
    assert Image.open(bg_.tradeoff_plot(two, tmp_path / "q.png")).size == (675, 468)


def pd_concat_scene(df):
    """``df`` with its meadow rows copied as a second scene, ``room``."""
    import pandas as pd

    m = df[df.scene == "meadow"].copy()
    m["scene"] = "room"
    return pd.concat([df, m])


def test_floor_sweep_arms_make_the_specs_they_name(bench_module):
    """bench_giveaways: the floor-sweep arms give `camo optimize` specs that validate, with the warm start's ceiling 1,
    the named floor, the starting roughness fixed at 0.5 for the ``_r5`` arms (the search's two candidates otherwise)
    and the shadow weight 4 for ``warmt01_sw4`` (1, the default, otherwise)."""
    from camo.cli import build_parser
    from camo.optimize_cli import spec_of

    bg_ = bench_module("bench_giveaways")
    want = {"warmt065": 0.65, "warmt05": 0.5, "warmt035": 0.35, "warmt02": 0.2, "warmt01": 0.0, "warmt01_sw4": 0.0,
            "warmt065_r5": 0.65, "warmt05_r5": 0.5, "warmt01_r5": 0.0}
    for arm, floor in want.items():
        spec = spec_of(build_parser().parse_args(["optimize", "meadow", "--out", "/tmp/x", *bg_.SIZE, *bg_.ARMS[arm]]))
        spec.validate()
        assert spec.stage1.warm_transmittance == 1.0 and spec.stage1.warm_transmittance_low == floor, arm
        assert tuple(spec.stage1.roughness_search) == ((0.5,) if arm.endswith("_r5") else (0.5, 0.7)), arm
        assert spec.stage1.shadow_weight == (4.0 if arm == "warmt01_sw4" else 1.0), arm  # 1: no extra weight
        assert arm in bg_.LABELS
