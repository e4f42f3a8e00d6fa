"""Condition ids and labels come from one module (optimizer.assets.conditions) and read the same in the
evaluation report, the stimuli manifest, the study database and Table I -- for every method and ablation the run
spec can name (taken from the method registry and the ablation list, so a new one cannot be forgotten)."""

from __future__ import annotations

import json
import re

import pytest

from camo_base.errors import CamoError
from optimizer.assets import conditions as C
from optimizer.assets.conditions import condition, condition_of_config, label_of_id, parse_id
from optimizer.assets.conditions import ABLATIONS
from optimizer.optimise.methods import METHOD_ALIASES, METHOD_NAMES, METHODS
from optimizer.optimise.spec import RunSpec


def _all_conditions():
    """Every method alone, ours without each ablation, and ours without two of them."""
    out = [(m, "none") for m in (*METHODS, *METHOD_ALIASES)]
    out += [("ours", a) for a in ABLATIONS]
    out += [("ours", "bsdf,pose")]
    return out


def test_every_method_and_ablation_of_the_run_spec_has_a_label():
    # the paper's methods have the paper's labels; a method added since shows its own name (CONTRIBUTING.md,
    # "Adding a baseline"): no label may name a method that does not exist
    assert {"ours", "transparent", "random", "mean", "greedy", "ganmouflage", "diffusion2d"} <= set(C.METHOD_LABELS)
    assert set(C.METHOD_LABELS) <= set(METHOD_NAMES), sorted(set(C.METHOD_LABELS) - set(METHOD_NAMES))
    assert tuple(ABLATIONS) == ("pose", "displacement", "bsdf", "transmittance", "inpainting")  # the paper's order
    ids, labels = set(), set()
    for m, a in _all_conditions():
        c = condition(m, a)
        assert parse_id(c.id) == c and label_of_id(c.id) == c.label
        ids.add(c.id)
        labels.add(c.label)
    assert len(ids) == len(labels) == len(_all_conditions())  # no two conditions share an id or a label


def test_an_ablation_reads_as_without():
    c = condition("ours", "inpainting")
    assert (c.id, c.label, c.ablation) == ("ours-without-inpainting", "w/o Inpainting", "inpainting")
    for a in ABLATIONS:
        c = condition("ours", a)
        assert c.id == f"ours-without-{a}" and c.label.startswith("w/o ") and "+" not in c.label
    both = condition("ours", "bsdf,pose")
    assert (both.id, both.label) == ("ours-without-pose+bsdf", "w/o Pose + BSDF")
    assert condition("ours", ["pose", "bsdf"]) == condition("ours", "bsdf, pose") == both
    assert condition("ours", "none") == condition("ours", "") == condition("ours") and condition("ours").label == "Ours"
    assert condition("ganmouflage").label == "GANmouflage [7]" and condition("theirs", "none").label == "theirs"
    orders = [condition(m, a).order for m, a in _all_conditions()]
    assert max(orders) == condition("ours").order  # Ours last, as in the paper's tables
    with pytest.raises(CamoError, match="may not contain"):
        condition("a-without-b")


def test_condition_of_a_run_spec():
    """The condition comes from the run spec that config.toml records (both layouts)."""
    from optimizer.scenes.builtin_scenes import get

    pack = get("meadow")
    for m in METHODS:
        d = RunSpec(scene="meadow", pack=pack, method=m).to_dict()
        assert condition_of_config(d) == condition(m)
    for a in ABLATIONS:
        d = RunSpec(scene="meadow", pack=pack, ablate=(a,)).to_dict()
        assert condition_of_config(d).id == f"ours-without-{a}"
    assert condition_of_config({"run": {"method": "ours", "ablate": ["inpainting"]}}).label == "w/o Inpainting"


def test_labels_identical_in_report_manifest_database_and_table_i(tmp_path):
    """One scene per condition (so one participant sees them all): the evaluation report's label, the manifest's
    condition and label, the database's plan and trial rows and Table I's rows agree, for every condition."""
    from evaluation.report import method_label
    from study_site import create_app
    from study_site.analysis import load_tables, write_report
    from study_site.stimuli import build_stimuli
    from study_site.testing import make_fake_eval_dir

    conds = _all_conditions()
    dirs = []
    for i, (m, a) in enumerate(conds):
        name = f"run{i:02d}"
        make_fake_eval_dir(tmp_path / f"ev{i}", scenes=(f"scene{i:02d}",), methods=(name,), views=1, size=(32, 24),
                           seed=i, ablations={name: (m, a)})
        dirs.append(tmp_path / f"ev{i}")
    build_stimuli(dirs, tmp_path / "stim", log=lambda s: None, synthetic_practice_n=0)
    man = json.loads((tmp_path / "stim" / "manifest.json").read_text())["stimuli"]
    by_scene = {s["scene"]: s for s in man}
    for i, (m, a) in enumerate(conds):
        s, c = by_scene[f"scene{i:02d}"], condition(m, a)
        assert (s["condition"], s["label"]) == (c.id, c.label) == (c.id, method_label(m, a))

    app = create_app({"STIMULI_DIR": str(tmp_path / "stim"), "DATABASE_URL": f"sqlite:///{tmp_path / 's.sqlite'}",
                      "PRACTICE_TRIALS": 0, "RT_FLOOR_MS": 0, "RATE_LIMIT_PER_S": 0, "ID_HMAC_KEY": "k" * 64,
                      "SECRET_KEY": "s" * 64})
    app.testing = True
    cl = app.test_client()
    cl.get("/?PROLIFIC_PID=labels")
    tok = re.search(r'name="csrf_token" value="([^"]+)"', cl.get("/consent").text).group(1)
    cl.post("/consent", data={"csrf_token": tok, "consent": "yes"})
    cl.post("/about-you", data={"csrf_token": tok, "age": "25-34"})
    cl.post("/instructions", data={"csrf_token": tok})
    h = {"X-CSRF-Token": tok}
    for t in cl.get("/api/state").get_json()["trials"]:
        cl.post("/api/start", json={"trial_index": t["index"]}, headers=h)
        r = cl.post("/api/trial", json={"trial_index": t["index"], "client_trial_id": f"lab{t['index']:05d}",
                                        "timed_out": False, "rt_ms": 0.0, "x": 0, "y": 0}, headers=h)
        assert r.status_code == 200, r.text
    assert cl.post("/api/complete", json={}, headers=h).status_code == 200
    trials, _ = load_tables(app.extensions["camo_study"].db.engine)
    assert len(trials) == len(conds)
    for r in trials.itertuples():
        s = by_scene[r.scene]
        assert (r.condition, r.label, r.method) == (s["condition"], s["label"], s["method"])
    res = write_report(app.config["DATABASE_URL"], tmp_path / "rep", n_boot=10)
    table = res["table"]
    assert sorted(zip(table["condition"], table["label"])) == sorted((condition(m, a).id, condition(m, a).label)
                                                                     for m, a in conds)
    assert table["label"].iloc[-1] == "Ours"  # paper order
    md = (tmp_path / "rep" / "table_i.md").read_text()
    assert "| w/o Inpainting | `ours-without-inpainting` |" in md and "ours+inpainting" not in md
    app.extensions["camo_study"].db.dispose()
