"""The clear-glass candidate start (``--clear-candidate ETA``, optimizer/optimise/startsearch.py, issue 29): the
choice on scripted scores, a real tiny Stage 1 switching its IOR and training scene to the winner (and keeping its
own start when clear glass loses), the one-line option errors, and end to end through the CLI (the chosen start is
Stage 1's first held-out check, the exported asset carries the chosen IOR, a resumed run keeps it)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camo.cli import main
from fixture_search_resume import assert_search_resumes
from optimizer.optimise.startsearch import CLEAR_ROUGHNESS, ClearSearchInfo, clear_search

TINY = ["--views", "3", "--resolution", "32", "--map-resolution", "48", "--displacement-resolution", "16",
        "--target-vertices", "800", "--spp", "2", "--target-spp", "16", "--quiet", "--threads", "1"]


def scripted(by_eta: dict[float, float]):
    """``prepare`` (marks the albedo with the IOR it set) and ``score`` (a table by that IOR: score, bias2, var)."""
    state = {"eta": None}
    calls = []

    def prepare(label, eta):
        state["eta"] = eta
        calls.append((label, eta))
        return {"albedo": np.full((2, 2, 3), eta, np.float32)}, {"label": label}

    def score(values):
        s = by_eta[state["eta"]]
        return s, s * 0.75, s * 0.25

    return prepare, score, calls


def test_clear_search_takes_the_lower_score_and_the_start_on_ties():
    prepare, score, calls = scripted({1.5: 2e-3, 1.05: 1e-3})
    values, info_prep, info = clear_search(1.5, 1.05, prepare, score)
    assert calls == [("start", 1.5), ("clear glass", 1.05)]
    assert isinstance(info, ClearSearchInfo) and info.chosen == "clear glass" and info.chosen_eta == 1.05
    assert info.scores == [2e-3, 1e-3] and info.bias2 == [1.5e-3, 0.75e-3] and info.variance == [0.5e-3, 0.25e-3]
    assert info.eta == [1.5, 1.05] and info.seconds >= 0 and info_prep == {"label": "clear glass"}
    np.testing.assert_array_equal(values["albedo"], np.float32(1.05))
    for table in ({1.5: 1e-3, 1.05: 1e-3}, {1.5: 1e-3, 1.05: 2e-3}, {1.5: 1e-3, 1.05: float("nan")}):
        values, _, info = clear_search(1.5, 1.05, *scripted(table)[:2])
        assert info.chosen == "start" and info.chosen_eta == 1.5 and values["albedo"].flat[0] == np.float32(1.5)
    # a start whose score is not finite loses to a finite clear glass
    assert clear_search(1.5, 1.05, *scripted({1.5: float("inf"), 1.05: 5.0})[:2])[2].chosen == "clear glass"


def _eta_of(stage) -> float:
    """The shared IOR of the object's BSDF in a stage's built Mitsuba training scene."""
    keys = [k for k in stage.params.keys() if k.endswith(".eta")]
    assert keys, list(stage.params.keys())
    return float(stage.params[keys[0]][0])


@pytest.mark.parametrize("clear_wins", [True, False])
def test_a_real_stage_1_takes_the_winner_with_its_ior_and_rebuilt_scene(mi_backend, clear_wins):
    from tests.fixture_stage1 import tiny_gravel_stage1

    s1 = tiny_gravel_stage1(False, warm_start=True)  # the least-squares albedo at each candidate's IOR
    start, start_app = s1.values, s1.app
    assert _eta_of(s1) == pytest.approx(1.5)
    seen = []

    def score(values):  # scripted by the IOR the stage renders with at the time (what the held-out views see)
        seen.append((s1.app.eta, float(values["roughness"].mean())))
        return (0.5 if (s1.app.eta < 1.5) == clear_wins else 1.0), 0.0, 0.0

    info = s1.search_clear(1.05, score)
    # the start is scored at its own IOR and roughness, clear glass at 1.05 and the smooth start
    assert seen[0] == (1.5, pytest.approx(float(start["roughness"].mean())))
    assert seen[1] == (1.05, pytest.approx(CLEAR_ROUGHNESS))
    if clear_wins:
        assert info.chosen == "clear glass" and s1.app.eta == 1.05 and _eta_of(s1) == pytest.approx(1.05)
        assert np.all(s1.values["roughness"] == np.float32(CLEAR_ROUGHNESS))
        # warm-started at the new IOR (the albedo moved), the other maps the start's
        assert not np.array_equal(s1.values["albedo"], start["albedo"])
        np.testing.assert_array_equal(s1.values["transmittance"], start["transmittance"])
    else:
        assert info.chosen == "start" and s1.app is start_app and _eta_of(s1) == pytest.approx(1.5)
        assert s1.values is start
    rec = s1.step()  # the stage steps from the chosen start
    assert np.isfinite(rec["loss"])


def test_clear_roughness_sets_the_candidates_start(mi_backend):
    """``--clear-roughness R``: the clear-glass candidate is scored, and kept, at a uniform roughness R."""
    from tests.fixture_stage1 import tiny_gravel_stage1

    s1 = tiny_gravel_stage1(False, warm_start=True, clear_roughness=0.5)
    seen = []

    def score(values):
        seen.append((s1.app.eta, float(values["roughness"].mean())))
        return (0.5 if s1.app.eta < 1.5 else 1.0), 0.0, 0.0

    assert s1.search_clear(1.05, score).chosen == "clear glass"
    assert seen[1] == (1.05, pytest.approx(0.5)) and np.all(s1.values["roughness"] == np.float32(0.5))


def optimize(out, *flags):
    return main(["optimize", "gravel", "--out", str(out), *TINY, *flags])


@pytest.mark.parametrize("flags, message", [
    (["--clear-candidate", "1"], "--clear-candidate must be 0 (off) or an index of refraction in (1, 4], got 1.0"),
    (["--clear-candidate", "0.5"], "--clear-candidate must be 0 (off) or an index of refraction in (1, 4], got 0.5"),
    (["--clear-candidate", "5"], "--clear-candidate"),
    (["--clear-candidate", "x"], "--clear-candidate"),
    (["--holdout-views", "0", "--clear-candidate", "1.05"], "--clear-candidate needs held-out views"),
    (["--ablate", "bsdf", "--clear-candidate", "1.05"], "--clear-candidate needs the principled BSDF"),
    (["--method", "mean", "--clear-candidate", "1.05"], "--clear-candidate does not apply to --method mean"),
    (["--clear-roughness", "0.5"], "--clear-roughness is the start of --clear-candidate's clear glass: set "
                                   "--clear-candidate too"),
    (["--clear-candidate", "1.05", "--clear-roughness", "1.5"], "--clear-roughness: must be a number in [0, 1]"),
])
def test_bad_clear_candidate_flags_are_one_line_errors(tmp_path, capsys, flags, message):
    assert optimize(tmp_path / "x", *flags) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "x").exists()


def test_end_to_end_the_choice_is_the_runs_and_a_resumed_run_keeps_it(tmp_path, capfd):
    """Through the CLI on tiny gravel: summary.json records both candidates and chooses the lower score; Stage 1's
    first held-out check is the chosen start at the chosen IOR (the same score, not rendered again); the exported
    asset's IOR is the chosen one; the choice travels in the checkpoint and a resumed run does not search again and
    ends with the uninterrupted run's maps; a corrupt record is a one-line error."""
    args = ["--stages", "1", "--clear-candidate", "1.05", "--holdout-views", "2", "--holdout-spp", "4",
            "--holdout-every", "2", "--checkpoint-every", "2", "--snapshot-every", "1"]
    full, out = tmp_path / "full", tmp_path / "resumed"
    assert optimize(full, *args, "--iterations", "3") == 0
    s = json.loads((full / "summary.json").read_text())
    cs = s["clear_search"]
    assert cs["candidates"] == ["start", "clear glass"] and cs["eta"] == [1.5, 1.05]
    assert all(x > 0 for x in cs["scores"]) and cs["chosen"] == cs["candidates"][int(np.argmin(cs["scores"]))]
    for sc, b2, var in zip(cs["scores"], cs["bias2"], cs["variance"]):
        assert sc == pytest.approx(max(b2 + var * 4 / 64, 0.0))  # the held-out score: bias^2 + noise at 64 spp
    assert s["holdout"]["checks"][0]["mse"] == cs["scores"][cs["candidates"].index(cs["chosen"])]
    first = np.load(full / "snapshots" / "s1_0000.npz")["roughness"]
    assert np.all(first == np.float32(CLEAR_ROUGHNESS)) == (cs["chosen"] == "clear glass")
    mtl = sorted(full.glob("*.mtl"))  # the exported OBJ's material (result.glb holds the same IOR)
    assert mtl, sorted(p.name for p in full.iterdir())
    ni = [float(line.split()[1]) for line in mtl[0].read_text().splitlines() if line.split()[:1] == ["Ni"]]
    assert ni == [pytest.approx(cs["chosen_eta"])]
    assert s["seconds_clear_search"] == pytest.approx(cs["seconds"])
    # the evaluation renders the result at the IOR the run kept, not the spec's (config.toml holds 1.5)
    from optimizer.assets.rundir import open_run

    assert open_run(full).asset().eta == pytest.approx(cs["chosen_eta"])

    def run(o, *flags, quiet=True):
        tiny = TINY if quiet else [a for a in TINY if a != "--quiet"]
        return main(["optimize", "gravel", "--out", str(o), *tiny, *args, *flags])

    assert_search_resumes(run, full, out, "clear_search", "clear search", capfd)


def test_a_result_renders_with_the_kept_ior_and_a_bad_record_is_a_one_line_error(tmp_path):
    """``optimizer.assets.rundir.result_appearance``: the spec's appearance, with the IOR a clear-glass search kept
    (``summary.json``'s ``clear_search.chosen_eta``); no record: unchanged; a record without a usable IOR: CamoError."""
    from camo_base.errors import CamoError
    from optimizer.assets.rundir import result_appearance
    from optimizer.rendering.appearance import AppearanceConfig

    app = AppearanceConfig(eta=1.5, map_resolution=64)
    assert result_appearance(app, tmp_path) is app  # no summary.json
    (tmp_path / "summary.json").write_text(json.dumps({"clear_search": None}))
    assert result_appearance(app, tmp_path) is app
    (tmp_path / "summary.json").write_text(json.dumps({"clear_search": {"chosen": "clear glass", "chosen_eta": 1.05}}))
    kept = result_appearance(app, tmp_path)
    assert kept.eta == 1.05 and kept.map_resolution == 64
    for bad in ({"chosen_eta": "x"}, {"chosen_eta": 0.9}, {"chosen_eta": float("nan")}, {"chosen": "start"}):
        (tmp_path / "summary.json").write_text(json.dumps({"clear_search": bad}))
        with pytest.raises(CamoError, match="clear_search.chosen_eta must be an index of refraction > 1") as e:
            result_appearance(app, tmp_path)
        assert len(str(e.value).splitlines()) == 1
