"""The turn search before Stage 1 (optimizer/optimise/posesearch.py): its score by hand, the choice on scripted
scores, and end to end on a tiny gravel scene, where turning the box shrinks its long shadow."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from camo.cli import main
from optimizer.optimise.posesearch import outside_score, search_turn

TINY = ["--views", "3", "--resolution", "32", "--map-resolution", "48", "--displacement-resolution", "16",
        "--target-vertices", "800", "--spp", "2", "--target-spp", "16", "--quiet", "--threads", "1"]


def test_outside_score_counts_only_uncovered_pixels_in_srgb():
    """One view of 2 x 2 pixels: a covered pixel's difference does not count, an uncovered one's counts in sRGB
    (linear 0.5 vs 0.25 -> 0.1982582^2), averaged over every pixel and channel; NaN reads as black."""
    bg = np.full((1, 2, 2, 3), 0.25, np.float32)
    img = bg.copy()
    img[0, 0, 0] = 0.5  # uncovered: counts
    img[0, 1, 1] = 0.9  # covered: does not
    cov = np.zeros((1, 2, 2))
    cov[0, 1, 1] = 1.0
    d = (1.055 * 0.5 ** (1 / 2.4) - 0.055) - (1.055 * 0.25 ** (1 / 2.4) - 0.055)
    assert outside_score(img, bg, cov) == pytest.approx(d * d / 4, rel=1e-6)
    cov[0, 0, 0] = 0.5  # partly covered pixels are the object's too
    assert outside_score(img, bg, cov) == 0.0
    nan = bg.copy()
    nan[0, 0, 1] = np.nan
    s = 1.055 * 0.25 ** (1 / 2.4) - 0.055
    assert outside_score(nan, bg, np.zeros((1, 2, 2))) == pytest.approx(s * s / 4, rel=1e-6)


def test_search_turn_takes_the_lowest_score_and_the_first_of_equals():
    bg = np.zeros((1, 1, 4, 3), np.float32)

    def render_with(errors):
        def render(theta):
            k = int(round(theta / (2 * math.pi / len(errors))))
            img = bg.copy()
            img[0, 0, 0] = errors[k]
            return img, np.zeros((1, 1, 4))
        return render

    best, thetas, scores = search_turn(4, render_with([0.3, 0.1, 0.2, 0.1]), bg)
    assert thetas == pytest.approx([0, math.pi / 2, math.pi, 3 * math.pi / 2])
    assert best == pytest.approx(math.pi / 2)  # the first of the two equal minima
    assert scores[1] == scores[3] and scores[1] < scores[2] < scores[0]
    best, _, scores = search_turn(4, render_with([0.2, 0.2, 0.2, 0.2]), bg)
    assert best == 0.0  # a turn that does not matter keeps the pose
    best, _, scores = search_turn(2, render_with([np.nan, 0.5]), bg)
    assert all(math.isfinite(s) for s in scores)  # NaN pixels read as black: a finite score


@pytest.fixture(scope="module")
def turned(tmp_path_factory):
    out = tmp_path_factory.mktemp("pose") / "run"
    assert main(["optimize", "gravel", "--out", str(out), *TINY, "--iterations", "2", "--stages", "1",
                 "--pose-search", "8", "--holdout-views", "0"]) == 0
    return out


def test_the_box_turns_to_shrink_its_shadow(turned):
    """gravel's box under a low sun: turned by 135 or 315 degrees its shadow darkens far less ground than at 0
    (measured 4.9e-4 against 1.1e-3 at these sizes); the run starts there and the gradient steps refine it by at
    most their rate (1e-2 rad) per step."""
    s = json.loads((turned / "summary.json").read_text())
    ps = s["pose_search"]
    assert ps["angles_deg"] == pytest.approx([45.0 * k for k in range(8)])
    k = int(np.argmin(ps["scores"]))
    assert ps["chosen_deg"] == pytest.approx(ps["angles_deg"][k])
    assert ps["chosen_deg"] in (135.0, 315.0)
    assert min(ps["scores"]) < 0.6 * ps["scores"][0]
    theta = json.loads((turned / "pose.json").read_text())["theta_z"]
    want = math.remainder(math.radians(ps["chosen_deg"]), 2 * math.pi)
    assert abs(math.remainder(theta - want, 2 * math.pi)) <= 2 * 1e-2 + 1e-6
    # its seconds are part of Stage 1's and of the optimisation's
    log = [json.loads(x) for x in (turned / "log.jsonl").read_text().splitlines()]
    assert s["seconds_pose_search"] == pytest.approx(ps["seconds"]) and ps["seconds"] > 0
    assert s["seconds_stage1"] == pytest.approx(
        s["seconds_pose_search"] + s["seconds_warm_start"] + sum(r["seconds"] for r in log), rel=1e-6)


def test_no_search_without_a_trainable_turn_or_when_off(tmp_path):
    """--ablate pose (nothing turns) and --pose-search 0 (the paper preset's setting) leave theta at 0 before
    the steps and write no pose_search."""
    for name, flags in (("ablated", ["--ablate", "pose", "--pose-search", "8"]), ("off", ["--pose-search", "0"])):
        out = tmp_path / name
        assert main(["optimize", "gravel", "--out", str(out), *TINY, "--iterations", "1", "--stages", "1",
                     *flags]) == 0
        assert json.loads((out / "summary.json").read_text())["pose_search"] is None


def test_bad_pose_search_is_a_one_line_error(tmp_path, capsys):
    assert main(["optimize", "gravel", "--out", str(tmp_path / "x"), "--quiet", "--pose-search", "-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--pose-search: must be an integer in [0, 3600]" in err and len(err.splitlines()) == 1
    assert main(["optimize", "gravel", "--out", str(tmp_path / "y"), "--quiet", "--method", "mean",
                 "--pose-search", "4"]) == 2
    assert "--pose-search does not apply to --method mean" in capsys.readouterr().err


def test_a_resumed_run_keeps_the_turn_it_chose(tmp_path):
    """The chosen turn travels in the checkpoint: a resumed run starts from it without searching again (renders at
    more than one thread are not bit-stable, and the turn decides the loss domain); a corrupt record is a one-line
    error."""
    out = tmp_path / "run"
    args = ["optimize", "gravel", "--out", str(out), *TINY, "--stages", "1", "--pose-search", "8",
            "--holdout-views", "0", "--checkpoint-every", "1"]
    assert main([*args, "--iterations", "1"]) == 0
    first = json.loads((out / "summary.json").read_text())["pose_search"]
    ck = dict(np.load(out / "checkpoint.npz"))
    assert json.loads(str(ck["pose_search/info"]))["rotation"] == pytest.approx(first["rotation"])
    assert main([*args, "--iterations", "2", "--resume"]) == 0
    again = json.loads((out / "summary.json").read_text())["pose_search"]
    assert again == first  # the same record, seconds included: nothing was searched again
    ck["pose_search/info"] = np.array("{not json")
    with open(out / "checkpoint.npz", "wb") as f:
        np.savez(f, **ck)
    assert main([*args, "--iterations", "3", "--resume"]) == 2
