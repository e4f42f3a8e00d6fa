"""Issue #21: what the study measures. The server-side trial clock (reloads keep the deadline, late and
too-fast answers), practice never sharing a scene with formal trials, object placement spread over the
frame, location baselines in the report, the id key outside the database, age brackets and serve flags."""

from __future__ import annotations

import argparse
import json
import math
import re

import numpy as np
import pytest
from PIL import Image

from camo_base.errors import CamoError
from study_site import create_app
from study_site.cli import register
from study_site.stimuli import StimulusSet, build_stimuli, location_baselines
from study_site.testing import make_fake_eval_dir, mask_rects

ID_KEY = "0123456789abcdef" * 4


@pytest.fixture(scope="module")
def stim_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("proto")
    make_fake_eval_dir(root / "eval", scenes=("sa", "sb"), methods=("m1", "m2"), views=2, size=(64, 48), seed=4)
    build_stimuli([root / "eval"], root / "stim", log=lambda m: None)
    return root / "stim"


def _app(stim_dir, tmp_path, **cfg):
    base = {"STIMULI_DIR": str(stim_dir), "DATABASE_URL": f"sqlite:///{tmp_path / 'study.sqlite'}",
            "PRACTICE_TRIALS": 2, "TRIAL_TIME_LIMIT_S": 6, "ID_HMAC_KEY": ID_KEY, "SECRET_KEY": "s" * 64, "RATE_LIMIT_PER_S": 0}
    base.update(cfg)
    app = create_app(base)
    app.testing = True
    return app


def _to_task(c, pid="P1"):
    c.get(f"/?PROLIFIC_PID={pid}")
    tok = re.search(r'name="csrf_token" value="([^"]+)"', c.get("/consent").text).group(1)
    c.post("/consent", data={"csrf_token": tok, "consent": "yes"})
    assert c.post("/about-you", data={"csrf_token": tok, "age": "25-34"}).status_code == 302
    assert c.post("/instructions", data={"csrf_token": tok}).status_code == 302
    return tok


def _age(app, idx, seconds):
    from datetime import timedelta

    from sqlalchemy import select

    from study_site.db import PlanItem

    with app.extensions["camo_study"].db.write() as s, s.begin():
        for it in s.scalars(select(PlanItem).where(PlanItem.idx == idx, PlanItem.started_at.is_not(None))):
            it.started_at = it.started_at - timedelta(seconds=seconds)


def _centre_of_object(app, c, idx):
    sid = next(t for t in c.get("/api/state").get_json()["trials"] if t["index"] == idx)["src"].rsplit("/", 1)[1].split(".")[0]
    x0, y0, x1, y1 = mask_rects(app.config["STIMULI_DIR"])[sid]
    return (x0 + x1) // 2, (y0 + y1) // 2


def _rows(app):
    from study_site.analysis import load_tables

    return load_tables(app.extensions["camo_study"].db.engine)[0].set_index("trial_index")


# ---------------------------------------------------------------------------
# the trial clock
# ---------------------------------------------------------------------------


def test_reload_keeps_the_deadline(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path)
    c = app.test_client()
    tok = _to_task(c)
    h = {"X-CSRF-Token": tok}
    first = c.post("/api/start", json={"trial_index": 0}, headers=h).get_json()
    assert first["starts"] == 1 and first["time_limit_ms"] == 6000 and first["elapsed_ms"] < 1000
    _age(app, 0, 2.5)  # 2.5 s into the trial the page is reloaded: the clock is not reset
    again = c.post("/api/start", json={"trial_index": 0}, headers=h).get_json()
    assert again["starts"] == 2 and 2500 <= again["elapsed_ms"] < 5000
    assert again["remaining_ms"] == pytest.approx(6000 - again["elapsed_ms"], abs=0.2)
    assert c.get("/api/state").get_json()["trials"][0]["started"] is True
    # the page reports the time since the first showing; it is stored with the reload count
    x, y = _centre_of_object(app, c, 0)
    body = {"trial_index": 0, "client_trial_id": "reload0001", "timed_out": False, "rt_ms": 2900.0, "x": x, "y": y}
    j = c.post("/api/trial", json=body, headers=h).get_json()
    assert j["hit"] is True and j["late"] is False
    row = _rows(app).loc[0]
    assert row.starts == 2 and row.rt_ms == 2900.0 and 2500 <= row.server_rt_ms < 5000
    # a trial whose time ran out during a reload answers remaining 0; a timeout is then accepted
    c.post("/api/start", json={"trial_index": 1}, headers=h)
    _age(app, 1, 30)
    late = c.post("/api/start", json={"trial_index": 1}, headers=h).get_json()
    assert late["remaining_ms"] == 0 and late["elapsed_ms"] >= 30000
    body = {"trial_index": 1, "client_trial_id": "reload0002", "timed_out": True, "rt_ms": late["elapsed_ms"]}
    j = c.post("/api/trial", json=body, headers=h).get_json()
    assert j["timed_out"] is True and j["hit"] is False
    # start is only for the next trial
    assert c.post("/api/start", json={"trial_index": 0}, headers=h).status_code == 409
    assert c.post("/api/start", json={"trial_index": 3}, headers=h).status_code == 409  # 2 is next
    assert c.post("/api/start", json={"trial_index": 99}, headers=h).status_code == 400
    assert c.post("/api/start", json={"trial_index": 10**400}, headers=h).status_code == 400
    assert c.post("/api/start", json={"trial_index": 2}).status_code == 400  # no CSRF token


def _click_object_after(app, c, h, idx, server_s, rt_ms, cid):
    """Start trial ``idx``, move its server clock ``server_s`` back, then click the object's centre with the page's
    ``rt_ms``: ``(answer JSON, the body sent)``."""
    c.post("/api/start", json={"trial_index": idx}, headers=h)
    _age(app, idx, server_s)
    x, y = _centre_of_object(app, c, idx)
    body = {"trial_index": idx, "client_trial_id": cid, "timed_out": False, "rt_ms": rt_ms, "x": x, "y": y}
    return c.post("/api/trial", json=body, headers=h).get_json(), body


def test_late_and_too_fast_answers(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path, DEADLINE_GRACE_S=2.0, RT_FLOOR_MS=300)
    c = app.test_client()
    tok = _to_task(c)
    h = {"X-CSRF-Token": tok}
    # not started: refused
    x, y = _centre_of_object(app, c, 0)
    body = {"trial_index": 0, "client_trial_id": "fast000001", "timed_out": False, "rt_ms": 0, "x": x, "y": y}
    assert c.post("/api/trial", json=body, headers=h).status_code == 409
    # a click with rt 0 on the object: stored as a hit, flagged too_fast
    c.post("/api/start", json={"trial_index": 0}, headers=h)
    j = c.post("/api/trial", json=body, headers=h).get_json()
    assert j["hit"] is True and j["too_fast"] is True and j["late"] is False
    # a click on the object at 7.9 s with a 6 s limit (the page's clock): a timeout, not "Found it"
    j, late1 = _click_object_after(app, c, h, 1, server_s=8, rt_ms=7900, cid="late000001")
    assert j["timed_out"] is True and j["hit"] is False and j["late"] is True
    # the page claims 3 s, but the server saw 9 s: past limit + grace -> a timeout as well
    j, body = _click_object_after(app, c, h, 2, server_s=9, rt_ms=3000, cid="late000002")
    assert j["timed_out"] is True and j["late"] is True and j["hit"] is False
    # a timeout 3 ms in: refused (page clock), also when the page says 6 s but the server saw 0.1 s
    c.post("/api/start", json={"trial_index": 3}, headers=h)
    for rt in (3, 6000):
        r = c.post("/api/trial", json={"trial_index": 3, "client_trial_id": f"to{rt:08d}", "timed_out": True,
                                       "rt_ms": rt}, headers=h)
        err = r.get_json()["error"]
        assert r.status_code == 400 and err in ("a timeout before the time limit",
                                                "rt_ms exceeds the time since the trial started"), err
    # a retry after the deadline returns the stored answer unchanged (idempotent, not re-judged)
    _age(app, 1, 100)
    r = c.post("/api/trial", json=dict(body, trial_index=1, client_trial_id="late000001"), headers=h).get_json()
    assert r["duplicate"] is True and r["late"] is True
    rows = _rows(app)
    assert bool(rows.loc[0, "too_fast"]) and bool(rows.loc[0, "hit"]) and rows.loc[0, "rt_ms"] == 0
    assert bool(rows.loc[1, "late"]) and bool(rows.loc[1, "timed_out"]) and not bool(rows.loc[1, "hit"])
    assert rows.loc[1, "rt_ms"] == 7900 and rows.loc[1, "click_x"] == late1["x"]  # the click is kept for the record
    assert 8000 <= rows.loc[1, "server_rt_ms"] < 12000
    assert 3 not in rows.index


def test_under_reported_time_is_decided_on_the_server_clock(stim_dir, tmp_path):
    """A page claiming 320 ms where the server measured ~6.2 s: stored with clock_mismatch, not too fast, and
    Table I reports the server's 6.2 s and says which clock it reports; a page claiming more than the server
    measured is refused; an honest page within the tolerance is not flagged."""
    from study_site.analysis import write_report

    app = _app(stim_dir, tmp_path, TRIAL_TIME_LIMIT_S=40, PRACTICE_TRIALS=0, RT_FLOOR_MS=300)
    c = app.test_client()
    tok = _to_task(c, "CLOCK1")
    h = {"X-CSRF-Token": tok}
    j, _ = _click_object_after(app, c, h, 0, server_s=6.224, rt_ms=320.0, cid="clock00001")
    assert (j["hit"], j["too_fast"], j["late"], j["clock_mismatch"]) == (True, False, False, True)
    # trial 1: the page claims 5 s but only ~1.6 s passed on the server: impossible, refused
    c.post("/api/start", json={"trial_index": 1}, headers=h)
    _age(app, 1, 1.6)
    x, y = _centre_of_object(app, c, 1)
    r = c.post("/api/trial", json={"trial_index": 1, "client_trial_id": "clock00002", "timed_out": False,
                                   "rt_ms": 5000.0, "x": x, "y": y}, headers=h)
    assert r.status_code == 400 and r.get_json()["error"] == "rt_ms exceeds the time since the trial started"
    # the same trial answered honestly (1.45 s on the page; the server's 1.6 s adds the round trip): not flagged
    r = c.post("/api/trial", json={"trial_index": 1, "client_trial_id": "clock00003", "timed_out": False,
                                   "rt_ms": 1450.0, "x": x, "y": y}, headers=h)
    assert r.status_code == 200 and r.get_json()["clock_mismatch"] is False
    assert c.post("/api/complete", json={}, headers=h).status_code == 200
    rows = _rows(app)
    assert rows.loc[0, "rt_ms"] == 320.0 and 6224 <= rows.loc[0, "server_rt_ms"] < 6224 + 3000
    assert bool(rows.loc[0, "clock_mismatch"]) and not bool(rows.loc[0, "too_fast"])
    assert rows.loc[0, "rt_s"] == pytest.approx(rows.loc[0, "server_rt_ms"] / 1000) and rows.loc[0, "page_rt_s"] == 0.32
    assert not bool(rows.loc[1, "clock_mismatch"]) and 1600 <= rows.loc[1, "server_rt_ms"] < 1600 + 3000
    res = write_report(app.config["DATABASE_URL"], tmp_path / "rep", n_boot=10)
    t = res["table"].set_index("condition")
    first = rows.loc[0, "condition"]
    same = rows[rows["condition"] == first]  # trial 1 may show the same condition
    assert t.loc[first, "mean_time_found_s"] == pytest.approx(same["server_rt_ms"].mean() / 1000)
    assert t.loc[first, "mean_time_found_s"] >= (6.2 + 1.6 * (len(same) - 1)) / len(same)  # not the page's 0.32 s
    md = (tmp_path / "rep" / "table_i.md").read_text()
    assert "the **server's clock**" in md
    assert "1 analysed trial(s) whose page claimed more than 1000 ms less than the server measured" in md
    with pytest.raises(CamoError, match=r"^config CLOCK_TOLERANCE_MS must be a number in \[50, 10000\], got "):
        _app(stim_dir, tmp_path, CLOCK_TOLERANCE_MS=20000)


def test_report_excludes_too_fast_and_gives_location_baselines(stim_dir, tmp_path):
    from study_site.analysis import write_report

    app = _app(stim_dir, tmp_path)
    rects = mask_rects(stim_dir)
    ss = StimulusSet(stim_dir)
    for i in range(3):
        c = app.test_client()
        tok = _to_task(c, f"R{i}")
        h = {"X-CSRF-Token": tok}
        for t in c.get("/api/state").get_json()["trials"]:
            sid = t["src"].rsplit("/", 1)[1].split(".")[0]
            x0, y0, x1, y1 = rects[sid]
            c.post("/api/start", json={"trial_index": t["index"]}, headers=h)
            rt = 100.0 if (i == 0 and t["index"] == 2) else 700.0  # participant 0's first formal: too fast
            _age(app, t["index"], rt / 1000.0)  # the server's clock decides: that much time passed
            body = {"trial_index": t["index"], "client_trial_id": f"rep{i}x{t['index']:04d}", "timed_out": False,
                    "rt_ms": rt, "x": (x0 + x1) // 2, "y": (y0 + y1) // 2}
            assert c.post("/api/trial", json=body, headers=h).status_code == 200
        assert c.post("/api/complete", json={}, headers=h).status_code == 200
    res = write_report(app.config["DATABASE_URL"], tmp_path / "rep", n_boot=50, stimuli_dir=stim_dir)
    assert int(res["table"]["n_trials"].sum()) == 3 * 2 - 1  # 2 formal scenes each, one too fast dropped
    b = res["baselines"].set_index("condition")
    trials = res["trials"]
    formal = trials[~trials.practice & ~trials.too_fast]
    # centre click: exactly the stimuli whose mask covers the centre pixel
    want = np.mean([ss.hit(ss.by_id[s], 32, 24) for s in formal.stimulus_id])
    assert b.loc["all", "centre_click_hit_rate"] == pytest.approx(want)
    assert b.loc["all", "mean_area_share"] == pytest.approx(np.mean([ss.mask(ss.by_id[s]).mean()
                                                                      for s in formal.stimulus_id]))
    # last practice location: the participant's practice centroid, tested on each formal mask
    hits = []
    for r in formal.itertuples():
        p = trials[(trials.participant == r.participant) & trials.practice].iloc[-1]
        ps = ss.by_id[p.stimulus_id]
        st = ss.by_id[r.stimulus_id]
        hits.append(ss.hit(st, int(ps.centroid_x * 64), int(ps.centroid_y * 48)))
    assert b.loc["all", "last_practice_hit_rate"] == pytest.approx(np.mean(hits))
    md = (tmp_path / "rep" / "table_i.md").read_text()
    assert "Excluded: 1 formal trial(s)" in md and "## Location baselines" in md
    assert (tmp_path / "rep" / "baselines.csv").is_file()


# ---------------------------------------------------------------------------
# practice never shares a scene with formal trials
# ---------------------------------------------------------------------------


def test_leaking_practice_is_refused(tmp_path):
    make_fake_eval_dir(tmp_path / "formal", scenes=("s1", "s2", "s3"), methods=("m",), views=1, size=(40, 30))
    make_fake_eval_dir(tmp_path / "prac", scenes=("s2", "p9"), methods=("m",), views=1, size=(40, 30))
    with pytest.raises(CamoError, match=r"practice scene\(s\) s2 also appear in the formal trials"):
        build_stimuli([tmp_path / "formal"], tmp_path / "o1", practice_dirs=[tmp_path / "prac"], log=lambda m: None)
    assert not (tmp_path / "o1" / "manifest.json").exists()
    # named practice scenes leave the formal pool
    man = build_stimuli([tmp_path / "formal"], tmp_path / "o2", practice_scenes=["s3"], log=lambda m: None)
    assert {s["scene"] for s in man["stimuli"] if s["practice"]} == {"s3"}
    assert {s["scene"] for s in man["stimuli"] if not s["practice"]} == {"s1", "s2"}
    with pytest.raises(CamoError, match="no such scene nope"):
        build_stimuli([tmp_path / "formal"], tmp_path / "o3", practice_scenes=["nope"], log=lambda m: None)
    with pytest.raises(CamoError, match="names every scene"):
        build_stimuli([tmp_path / "formal"], tmp_path / "o3", practice_scenes=["s1", "s2", "s3"], log=lambda m: None)
    # a hand-edited manifest that leaks is refused when loaded (so the server refuses to start)
    mpath = tmp_path / "o2" / "manifest.json"
    data = json.loads(mpath.read_text())
    next(s for s in data["stimuli"] if s["practice"])["scene"] = "s1"
    mpath.write_text(json.dumps(data))
    with pytest.raises(CamoError, match=r"practice scene\(s\) s1"):
        StimulusSet(tmp_path / "o2")
    # no practice stimuli and PRACTICE_TRIALS > 0: the app refuses to start
    build_stimuli([tmp_path / "formal"], tmp_path / "o4", synthetic_practice_n=0, log=lambda m: None)
    with pytest.raises(CamoError, match="no practice stimuli"):
        create_app({"STIMULI_DIR": str(tmp_path / "o4"), "DATABASE_URL": f"sqlite:///{tmp_path / 'x.sqlite'}",
                    "ID_HMAC_KEY": ID_KEY, "SECRET_KEY": "s" * 64, "PRACTICE_TRIALS": 2})


def test_practice_leak_by_content_is_refused(tmp_path, capsys):
    """Practice is compared with the formal trials by what the images show, not by scene names: the formal images
    (and backgrounds) copied under another scene name are refused by perceptual hash, when built and when a
    hand-edited manifest is loaded; different pictures pass."""
    import shutil

    from camo.cli import main
    from study_site.stimuli import phash, phash_distance

    make_fake_eval_dir(tmp_path / "formal", scenes=("s1", "s2"), methods=("m",), views=1, size=(96, 72), seed=1)
    make_fake_eval_dir(tmp_path / "other", scenes=("p1", "p2"), methods=("m",), views=1, size=(96, 72), seed=2)
    # the practice folder shows formal scene s2's view under the name p9
    make_fake_eval_dir(tmp_path / "copy", scenes=("p9",), methods=("m",), views=1, size=(96, 72), seed=3)
    src = tmp_path / "formal" / "renders" / "s2__m"
    dst = tmp_path / "copy" / "renders" / "p9__m"
    for f in ("view_00_obj.png", "view_00_bg.png"):
        shutil.copy(src / f, dst / f)
    rc = main(["study", "build-stimuli", str(tmp_path / "formal"), "--out", str(tmp_path / "o1"), "--copy",
               "--practice", str(tmp_path / "copy")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("camo: error: ") and "practice image of scene p9 (view 0) looks like formal scene s2" in err[0]
    assert not (tmp_path / "o1" / "manifest.json").exists()
    # other pictures: accepted, hashes recorded, and far apart
    man = build_stimuli([tmp_path / "formal"], tmp_path / "o2", practice_dirs=[tmp_path / "other"], log=lambda m: None)
    pr = [x for x in man["stimuli"] if x["practice"]]
    fo = [x for x in man["stimuli"] if not x["practice"]]
    assert all(len(x["phash"]) == 16 and len(x["background_phash"]) == 16 for x in man["stimuli"])
    assert min(phash_distance(a["phash"], b["phash"]) for a in pr for b in fo) > 8
    img = np.asarray(Image.open(tmp_path / "o2" / "images" / f"{fo[0]['id']}.png"))
    assert phash(img) == fo[0]["phash"] and phash(img[:, ::-1]) != fo[0]["phash"]
    # a hand-edited manifest whose practice image is a formal one is refused when loaded (the server won't start)
    mpath = tmp_path / "o2" / "manifest.json"
    data = json.loads(mpath.read_text())
    p0 = next(x for x in data["stimuli"] if x["practice"])
    f0 = next(x for x in data["stimuli"] if not x["practice"])
    shutil.copy(tmp_path / "o2" / "images" / f"{f0['id']}.png", tmp_path / "o2" / "images" / f"{p0['id']}.png")
    for x in data["stimuli"]:
        x.pop("phash", None)  # as a manifest from before hashes were recorded: computed from the images
    mpath.write_text(json.dumps(data))
    with pytest.raises(CamoError, match=r"practice image of scene p\d .* looks like formal scene s\d"):
        StimulusSet(tmp_path / "o2")


def test_same_environment_under_another_name_is_refused():
    """meadow:teapot (practice) and meadow (formal) show the same grass, sun and camera orbit: refused by their
    environment, whatever the scene names; a panorama is compared by its bytes, not its name."""
    from optimizer.scenes.builtin_scenes import resolve_scene
    from study_site.stimuli import check_no_content_leak, environment_key

    def rows(formal, practice):
        return ([{"practice": False, "scene": n, "view": "0", "environment": environment_key(resolve_scene(n).environment)}
                 for n in formal]
                + [{"practice": True, "scene": n, "view": "0", "environment": environment_key(resolve_scene(n).environment)}
                   for n in practice])

    with pytest.raises(CamoError, match=r"practice scene meadow(:|_)teapot shows the same environment "
                                        r"\(builtin:meadow\) as formal scene meadow"):
        check_no_content_leak([dict(r, scene=n) for r, n in zip(rows(["meadow"], ["meadow:teapot"]),
                                                                 ["meadow", "meadow:teapot"])], "build-stimuli")
    check_no_content_leak(rows(["meadow", "room"], ["gravel:teapot"]))  # another environment: fine


def test_panorama_environment_by_content(tmp_path):
    from optimizer.scenes.scenepack import EnvironmentSpec
    from study_site.stimuli import environment_key

    a, b, c = tmp_path / "plaza.hdr", tmp_path / "renamed.hdr", tmp_path / "forest.hdr"
    a.write_bytes(b"#?RADIANCE\n" + bytes(range(256)) * 4)
    b.write_bytes(a.read_bytes())
    c.write_bytes(b"#?RADIANCE\n" + bytes(range(255, -1, -1)) * 4)
    ka, kb, kc = (environment_key(EnvironmentSpec(panorama=str(p))) for p in (a, b, c))
    assert ka == kb != kc and ka.startswith("panorama:")


def test_cli_leak_refusal_is_one_line_exit_2(tmp_path, capsys):
    from camo.cli import main

    make_fake_eval_dir(tmp_path / "formal", scenes=("s1",), methods=("m",), views=1, size=(40, 30))
    rc = main(["study", "build-stimuli", str(tmp_path / "formal"), "--out", str(tmp_path / "o"), "--copy",
               "--practice", str(tmp_path / "formal")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "practice would reveal where the object is" in err


# ---------------------------------------------------------------------------
# placement: where the object lands in the frame
# ---------------------------------------------------------------------------


def test_place_camera_puts_the_object_where_drawn():
    from optimizer.scenes.cameras import Camera
    from study_site.render_stimuli import draw_placement, place_camera, project_ndc

    rng = np.random.default_rng(0)
    errs = []
    for k in range(200):
        origin = tuple(rng.normal(0, 1, 3) * 0.3 + np.array([4.0 * math.cos(k), 4.0 * math.sin(k), 1.5]))
        centre = (0.1, -0.2, 0.5)
        cam = Camera(origin, centre, 40.0, 48, 48)
        d = draw_placement(f"scene:{k}", 0)
        new, fov, _ = place_camera(cam, centre, 1.0, d, 512)
        assert new.origin == cam.origin and new.width == new.height == 512
        px, py = project_ndc(new, centre)
        errs.append(max(abs(px - d["px"]), abs(py - d["py"])))
        # the field of view makes an object of extent 1 span the drawn share of the frame
        dist = math.dist(origin, centre)
        if 8.0 < fov < 100.0:  # not clamped
            assert (0.5 / dist) / math.tan(math.radians(fov / 2)) == pytest.approx(d["object_frac"], rel=1e-9)
    assert max(errs) < 1e-4  # the object centre projects where it was drawn


def test_placement_spread_centre_click_near_area_share():
    """Discs of the drawn size at the drawn positions: the centre pixel is covered about as often as the
    object's area share (an object always at the centre would give 100 %)."""
    from study_site.render_stimuli import draw_placement

    from study_site.render_stimuli import DEFAULT_MARGIN

    n, covered, shares, expected, xs = 4000, 0, [], [], []
    for k in range(n):
        d = draw_placement(f"scene:{k}", 1)
        r = d["object_frac"]  # disc radius in NDC (the frame is 2 NDC units wide)
        covered += d["px"] ** 2 + d["py"] ** 2 <= r * r
        shares.append(math.pi * r * r / 4.0)
        # the centre is uniform in a square of half-side 1 - s - 2 margin (the object stays in the frame)
        expected.append(math.pi * r * r / (2 * (1 - r - 2 * DEFAULT_MARGIN)) ** 2)
        xs.append(d["px"])
    rate, share, want = covered / n, float(np.mean(shares)), float(np.mean(expected))
    assert rate == pytest.approx(want, abs=4 * math.sqrt(want * (1 - want) / n))
    # keeping the whole object inside the frame costs a factor ~2 over the area share; far from 100 %
    assert share < rate < 2.5 * share and rate < 0.12
    assert np.std(xs) > 0.3  # spread over the frame, not clustered at the centre


def test_copy_mode_summary_reports_centre_bias(tmp_path):
    """Evaluation renders with the object at the centre: the manifest says so (centre click 100 %)."""
    from PIL import Image

    ev = tmp_path / "ev"
    (ev / "r").mkdir(parents=True)
    entries = []
    for v in range(4):
        img = np.full((48, 48, 3), 120, np.uint8)
        mask = np.zeros((48, 48), np.uint8)
        mask[18:30, 19:29] = 255
        Image.fromarray(img).save(ev / "r" / f"{v}_obj.png")
        Image.fromarray(mask).save(ev / "r" / f"{v}_mask.png")
        entries.append({"run": "run", "scene": "sc", "method": "m", "view": v, "image": f"r/{v}_obj.png",
                        "mask": f"r/{v}_mask.png"})
    (ev / "renders.json").write_text(json.dumps(entries))
    man = build_stimuli([ev], tmp_path / "stim", log=lambda m: None)
    b = location_baselines(man)
    assert (b["n"], b["centre_hits"]) == (4, 4) and b["mean_area_share"] == pytest.approx(120 / 48**2)


# ---------------------------------------------------------------------------
# keys, age brackets, serve flags
# ---------------------------------------------------------------------------


def test_id_key_outside_the_database(stim_dir, tmp_path, capsys):
    from camo.cli import main

    cfg = {"STIMULI_DIR": str(stim_dir), "DATABASE_URL": f"sqlite:///{tmp_path / 'k.sqlite'}", "SECRET_KEY": "s" * 64}
    with pytest.raises(CamoError, match=r"camo study make-key"):
        create_app(cfg)
    with pytest.raises(CamoError, match="at least 32"):
        create_app(dict(cfg, ID_HMAC_KEY="short"))
    key = tmp_path / "id.key"
    assert main(["study", "make-key", str(key)]) == 0
    assert key.stat().st_mode & 0o777 == 0o600 and len(key.read_text().strip()) == 64
    assert main(["study", "make-key", str(key)]) == 2  # never overwritten
    assert "already exists" in capsys.readouterr().err
    app = create_app(dict(cfg, ID_HMAC_KEY_FILE=str(key)))
    assert app.extensions["camo_study"].id_key == key.read_text().strip()
    from study_site.db import Setting

    with app.extensions["camo_study"].db.read() as s:
        assert s.get(Setting, "id_hmac_key") is None  # not in the database
    dev = create_app(dict(cfg, DEV=True, SECRET_KEY=None))  # development: keys kept in the database
    with dev.extensions["camo_study"].db.read() as s:
        assert s.get(Setting, "id_hmac_key").value == dev.extensions["camo_study"].id_key
    with pytest.raises(CamoError, match="ID_HMAC_KEY file"):
        create_app(dict(cfg, ID_HMAC_KEY_FILE=str(tmp_path / "missing.key")))


def test_adults_only_age_required(stim_dir, tmp_path, capsys):
    """The age bracket is required, brackets are adult only, "Under 18" ends the participation, and a minimum
    below 18 is refused in one line (config and `serve --min-age`)."""
    from camo.cli import main

    app = _app(stim_dir, tmp_path)
    c = app.test_client()
    c.get("/?id=age_1")
    page = c.get("/consent").text
    assert "Adults only" in page and "18 or older" in page and "guardian" not in page
    tok = re.search(r'name="csrf_token" value="([^"]+)"', page).group(1)
    c.post("/consent", data={"csrf_token": tok, "consent": "yes"})
    about = c.get("/about-you").text
    values = re.findall(r'name="age" value="([^"]+)" required', about)
    assert values == ["18-24", "25-34", "35-44", "45-54", "55-64", "65+", "under"]
    assert "Under 18" in about and "optional" not in about
    assert c.post("/about-you", data={"csrf_token": tok}).status_code == 400  # no answer
    assert c.post("/about-you", data={"csrf_token": tok, "age": "10-20"}).status_code == 400
    assert c.post("/about-you", data={"csrf_token": tok, "age": "prefer_not"}).status_code == 400
    r = c.post("/about-you", data={"csrf_token": tok, "age": "under"})
    assert r.status_code == 302 and r.headers["Location"].endswith("/not-eligible")
    assert "for adults aged 18 or older" in c.get("/not-eligible").text
    # stays out: every page and the API lead back to /not-eligible; no plan was made
    assert c.get("/instructions").headers["Location"].endswith("/not-eligible")
    assert c.get("/task").headers["Location"].endswith("/not-eligible")
    assert c.get("/api/state").status_code == 409
    c.get("/?id=age_1")
    assert c.get("/consent").headers["Location"].endswith("/not-eligible")
    from study_site.analysis import load_tables

    parts = load_tables(app.extensions["camo_study"].db.engine)[1]
    assert parts["age_bracket"].tolist() == ["under"] and parts["n_trials"].tolist() == [0]
    (tmp_path / "y").mkdir()
    c = _app(stim_dir, tmp_path / "y", MIN_AGE=21).test_client()  # a higher minimum: brackets from 21
    c.get("/?id=age_2")
    tok = re.search(r'name="csrf_token" value="([^"]+)"', c.get("/consent").text).group(1)
    c.post("/consent", data={"csrf_token": tok, "consent": "yes"})
    assert re.findall(r'name="age" value="([^"]+)"', c.get("/about-you").text)[:2] == ["21-24", "25-34"]
    for low in (17, 10):
        with pytest.raises(CamoError, match=rf"^MIN_AGE must be 18-99, not {low}: the study takes "
                                            "adults only$"):
            _app(stim_dir, tmp_path, MIN_AGE=low)
    key = tmp_path / "k.key"
    key.write_text("ab" * 32)
    skey = tmp_path / "s.key"
    skey.write_text("cd" * 32)
    rc = main(["study", "serve", "--stimuli", str(stim_dir), "--db", str(tmp_path / "m.sqlite"), "--id-key-file",
               str(key), "--secret-key-file", str(skey), "--min-age", "10"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == ["camo: error: MIN_AGE (--min-age) must be 18-99, not 10: the study takes adults only"]


def test_serve_flags_reach_the_config(stim_dir, tmp_path, monkeypatch):
    import study_site.cli as cli

    seen = {}
    monkeypatch.setattr(cli, "serve_app", lambda app, *a, **k: seen.update(app.config))
    key, tok, skey = tmp_path / "id.key", tmp_path / "admin.tok", tmp_path / "cookie.key"
    key.write_text("ab" * 32)
    skey.write_text("cd" * 32)
    tok.write_text("admintoken-" + "x" * 20)
    p = argparse.ArgumentParser(prog="camo")
    register(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(["study", "serve", "--stimuli", str(stim_dir), "--db", str(tmp_path / "s.sqlite"),
                         "--id-key-file", str(key), "--secret-key-file", str(skey), "--admin-token-file", str(tok),
                         "--time-limit", "25",
                         "--practice-trials", "3", "--min-age", "21", "--completion-code", "XYZ123"])
    assert args.func(args) == 0
    assert (seen["TRIAL_TIME_LIMIT_S"], seen["PRACTICE_TRIALS"], seen["MIN_AGE"], seen["COMPLETION_CODE"]) == (
        25.0, 3, 21, "XYZ123")
    assert seen["ADMIN_TOKEN"] == tok.read_text() and seen["ID_HMAC_KEY"] == "ab" * 32
    assert seen["SECRET_KEY"] == "cd" * 32
    with pytest.raises(SystemExit):  # out of range: refused by the flag's type (tests/test_cli_ranges.py)
        p.parse_args(["study", "serve", "--stimuli", str(stim_dir), "--db", str(tmp_path / "s.sqlite"),
                      "--id-key-file", str(key), "--secret-key-file", str(skey), "--time-limit", "0.5"])


def test_old_database_is_refused_in_one_line(stim_dir, tmp_path):
    import sqlite3

    db = tmp_path / "old.sqlite"
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE trials (id INTEGER PRIMARY KEY, participant_id INTEGER)")
    con.commit()
    con.close()
    with pytest.raises(CamoError, match="table trials lacks .* older camo"):
        _app(stim_dir, tmp_path, DATABASE_URL=f"sqlite:///{db}")



def test_trial_starts_commit_without_fsync_trials_with(tmp_path):
    """Starts go through write_light (SQLite synchronous=NORMAL: no fsync per commit, still safe against a
    killed server process); trials through write (synchronous=FULL)."""
    from sqlalchemy import text

    from study_site.db import Database

    db = Database(f"sqlite:///{tmp_path / 'x.sqlite'}")
    with db.write_light() as s, s.begin():
        assert s.execute(text("PRAGMA synchronous")).scalar() == 1  # NORMAL
    with db.write() as s, s.begin():
        assert s.execute(text("PRAGMA synchronous")).scalar() == 2  # FULL
    db.dispose()


def test_start_api_never_5xx(stim_dir, tmp_path):
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as hs

    app = _app(stim_dir, tmp_path)
    c = app.test_client()
    tok = _to_task(c, "FUZZ_START")
    leaf = hs.none() | hs.booleans() | hs.integers() | hs.floats(allow_nan=True) | hs.text(max_size=10)
    body = hs.dictionaries(hs.sampled_from(["trial_index", "x", ""]), leaf, max_size=3) | leaf | hs.lists(leaf)

    @settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(b=body)
    def check(b):
        r = c.post("/api/start", data=json.dumps(b), content_type="application/json", headers={"X-CSRF-Token": tok})
        assert r.status_code < 500 and "error" in r.get_json() or r.status_code == 200, (b, r.status_code)

    check()
