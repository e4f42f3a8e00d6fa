"""The starting-roughness search before Stage 1 (optimizer/optimise/startsearch.py): the choice on scripted scores,
the flags and presets that turn it on and off, and end to end on a tiny gravel scene (the search's choice is Stage
1's start, its seconds are counted, and a resumed run keeps it)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camo.cli import main
from fixture_search_resume import assert_search_resumes
from optimizer.optimise.startsearch import StartSearchInfo, start_search

TINY = ["--views", "3", "--resolution", "32", "--map-resolution", "48", "--displacement-resolution", "16",
        "--target-vertices", "800", "--spp", "2", "--target-spp", "16", "--quiet", "--threads", "1"]


def scripted(scores: dict[float, float]):
    """``prepare`` (marks the albedo with the candidate, records the call) and ``score`` (a table by roughness)."""
    calls: list[float] = []

    def prepare(values):
        r = round(float(values["roughness"].flat[0]), 6)
        calls.append(r)
        out = dict(values)
        out["albedo"] = np.full_like(values["albedo"], r / 2)
        return out, {"warm": r}

    def score(values):
        return scores[round(float(values["roughness"].flat[0]), 6)]

    return prepare, score, calls


def start():
    return {"albedo": np.full((4, 4, 3), 0.5, np.float32), "roughness": np.full((4, 4, 1), 0.1, np.float32),
            "transmittance": np.full((4, 4, 1), 0.75, np.float32)}


def test_start_search_takes_the_lowest_score_and_the_first_of_equals():
    prepare, score, calls = scripted({0.5: 2.0, 0.7: 1.0, 0.9: 1.0})
    values, warm, info = start_search([0.5, 0.7, 0.9], start(), prepare, score)
    assert calls == [0.5, 0.7, 0.9]
    assert isinstance(info, StartSearchInfo) and info.chosen == 0.7 and info.scores == [2.0, 1.0, 1.0]
    assert info.roughness == [0.5, 0.7, 0.9] and info.seconds >= 0.0
    # the chosen start as prepared: a uniform roughness map, the prepare step's albedo and info
    assert values["roughness"].shape == (4, 4, 1) and np.all(values["roughness"] == np.float32(0.7))
    np.testing.assert_allclose(values["albedo"], 0.35, rtol=1e-6)
    assert warm == {"warm": 0.7}
    np.testing.assert_array_equal(values["transmittance"], start()["transmittance"])  # other maps as given


def test_start_search_skips_non_finite_scores_and_falls_back_to_the_first():
    prepare, score, _ = scripted({0.5: float("nan"), 0.7: 3.0, 0.9: float("inf")})
    assert start_search([0.5, 0.7, 0.9], start(), prepare, score)[2].chosen == 0.7
    prepare, score, calls = scripted({0.5: float("nan"), 0.9: float("nan")})
    values, _, info = start_search([0.9, 0.5], start(), prepare, score)
    assert info.chosen == 0.9 and np.all(values["roughness"] == np.float32(0.9))
    assert calls == [0.9, 0.5]  # the first candidate's prepared start is kept, not prepared again
    with pytest.raises(ValueError, match="at least one"):
        start_search([], start(), prepare, score)


def spec(*flags):
    from camo.cli import build_parser
    from camo.optimize_cli import spec_of

    return spec_of(build_parser().parse_args(["optimize", "gravel", "--out", "x", *flags]))


def test_presets_flags_and_the_options_that_turn_the_search_off():
    assert spec().stage1.roughness_search == (0.5, 0.7)
    assert spec("--preset", "paper").stage1.roughness_search == ()
    assert spec("--roughness-search", "0.4,0.6").stage1.roughness_search == (0.4, 0.6)
    assert spec("--roughness-search", "off").stage1.roughness_search == ()
    assert spec("--init", "roughness=0.3").stage1.roughness_search == ()  # the user's start is kept
    assert spec("--ablate", "bsdf").stage1.roughness_search == ()
    assert spec("--holdout-views", "0").stage1.roughness_search == ()  # nothing to score on
    assert spec("--init", "roughness=0.3", "--roughness-search", "0.5,0.6").stage1.roughness_search == (0.5, 0.6)


@pytest.mark.parametrize("flags, message", [
    (["--roughness-search", "0.5,x"], "--roughness-search must be a comma list of numbers in [0, 1] or 'off'"),
    (["--roughness-search", "0.5,1.5"], "--roughness-search must be numbers in [0, 1], got [0.5, 1.5]"),
    (["--roughness-search", "nan"], "--roughness-search must be numbers in [0, 1]"),
    (["--holdout-views", "0", "--roughness-search", "0.5"], "--roughness-search needs held-out views"),
    (["--method", "mean", "--roughness-search", "0.5"], "--roughness-search does not apply to --method mean"),
])
def test_bad_roughness_search_flags_are_one_line_errors(tmp_path, capsys, flags, message):
    assert main(["optimize", "gravel", "--out", str(tmp_path / "x"), "--quiet", *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "x").exists()


def test_the_chosen_start_is_stage_1s_and_a_resumed_run_keeps_it(tmp_path, capfd):
    """End to end: the summary records every candidate's score and the choice; Stage 1's first snapshot has the
    chosen uniform roughness; the search's seconds count in Stage 1's and the run's; the choice travels in the
    checkpoint, a resumed run does not search again and ends bit-exact with an uninterrupted one; a corrupt record
    is a one-line error."""
    args = [*TINY, "--stages", "1", "--roughness-search", "0.6,0.95", "--holdout-views", "2", "--holdout-spp", "4",
            "--holdout-every", "2", "--checkpoint-every", "2", "--snapshot-every", "1"]
    full, out = tmp_path / "full", tmp_path / "resumed"
    assert main(["optimize", "gravel", "--out", str(full), *args, "--iterations", "3"]) == 0
    s = json.loads((full / "summary.json").read_text())
    ss = s["start_search"]
    assert ss["roughness"] == [0.6, 0.95] and len(ss["scores"]) == 2 and all(x > 0 for x in ss["scores"])
    assert ss["chosen"] == [0.6, 0.95][int(np.argmin(ss["scores"]))]
    # Stage 1's first held-out check is the chosen start the search scored (not rendered again)
    assert s["holdout"]["checks"][0]["mse"] == ss["scores"][ss["roughness"].index(ss["chosen"])]
    first = np.load(full / "snapshots" / "s1_0000.npz")["roughness"]
    assert np.all(first == np.float32(ss["chosen"]))
    assert s["seconds_start_search"] == pytest.approx(ss["seconds"]) and ss["seconds"] > 0
    log = [json.loads(x) for x in (full / "log.jsonl").read_text().splitlines()]
    assert s["seconds_stage1"] == pytest.approx(s["seconds_pose_search"] + s["seconds_start_search"] +
                                                s["seconds_warm_start"] + sum(r["seconds"] + r.get("seconds_holdout", 0.0)
                                                                              for r in log), rel=1e-6)

    def run(o, *flags, quiet=True):
        a = args if quiet else [x for x in args if x != "--quiet"]
        return main(["optimize", "gravel", "--out", str(o), *a, *flags])

    assert_search_resumes(run, full, out, "start_search", "start search", capfd)


def test_candidates_at_the_ends_of_the_range_keep_the_run_finite(tmp_path):
    """Stress: candidates 0 and 1 (the render's roughness floor 0.035 and a fully rough lobe) under a sunlit scene,
    with the iterate average at its largest decay: every map finite and in range, no non-finite gradient entry."""
    out = tmp_path / "ends"
    assert main(["optimize", "meadow", "--out", str(out), *TINY, "--iterations", "3", "--stage2-iterations", "1",
                 "--roughness-search", "0,1", "--holdout-views", "2", "--holdout-spp", "4",
                 "--average", "0.999"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["start_search"]["chosen"] in (0.0, 1.0) and all(np.isfinite(s["start_search"]["scores"]))
    assert s["nonfinite_grads_total"] == 0
    for name in ("albedo", "metallic", "roughness", "transmittance", "displacement"):
        m = np.load(out / "maps" / f"{name}.npy")
        assert np.isfinite(m).all()
        lo = -1.0 if name == "displacement" else 0.0
        assert m.min() >= lo and m.max() <= 1.0
