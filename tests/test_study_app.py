"""Study site with Flask's test client: stimuli, participant flow, storage, protection, CLI."""

from __future__ import annotations

import argparse
import json
import re
import uuid
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from camo_base.errors import CamoError
from camo_base.tables import read_parquet
from study_site import create_app
from study_site.cli import register
from study_site.stimuli import StimulusSet, build_stimuli, outline_overlay
from study_site.testing import make_fake_eval_dir, mask_rects

SCENES = ("scn_kitchen_q7", "scn_forest_z3", "scn_office_k2")
METHODS = ("mth_ours_v9", "mth_random_r4", "mth_gan_g5")


@pytest.fixture(scope="module")
def stim_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("study")
    make_fake_eval_dir(root / "eval", scenes=SCENES, methods=METHODS, views=2, size=(64, 48))
    build_stimuli([root / "eval"], root / "stim", log=lambda m: None)
    return root / "stim"


ID_KEY = "k" * 64


def _app(stim_dir, tmp_path, **cfg):
    base = {
        "STIMULI_DIR": str(stim_dir),
        "DATABASE_URL": f"sqlite:///{tmp_path / 'study.sqlite'}",
        "PRACTICE_TRIALS": 2,
        "TRIAL_TIME_LIMIT_S": 40,
        "ADMIN_TOKEN": "admintok123",
        "ID_HMAC_KEY": ID_KEY, "SECRET_KEY": "s" * 64,
        "RT_FLOOR_MS": 0,  # answers follow their start at once here (too_fast: tests/test_study_protocol.py)
    }
    base.update(cfg)
    app = create_app(base)
    app.testing = True
    return app


def _csrf(html: str) -> str:
    m = re.search(r'name="csrf_token" value="([^"]+)"', html) or re.search(r'data-csrf="([^"]+)"', html)
    assert m, html[:500]
    return m.group(1)


def _to_task(client, pid="PID_0001", age="18-24"):
    r = client.get(f"/?PROLIFIC_PID={pid}&STUDY_ID=study1&SESSION_ID=sess{pid}")
    assert r.status_code == 302 and r.headers["Location"].endswith("/consent")
    r = client.get("/consent")
    tok = _csrf(r.text)
    assert client.post("/consent", data={"csrf_token": tok, "consent": "yes"}).status_code == 302
    assert client.post("/about-you", data={"csrf_token": tok, "age": age}).status_code == 302
    r = client.post("/instructions", data={"csrf_token": tok})
    assert r.status_code == 302 and r.headers["Location"].endswith("/task")
    return tok


def _start(client, tok, idx):
    return client.post("/api/start", json={"trial_index": idx}, headers={"X-CSRF-Token": tok})


def _post_trial(client, tok, idx, cid=None, start=True, **kw):
    """Answer trial ``idx`` (started first unless ``start=False``); rt 800 ms unless given."""
    if start:
        r = _start(client, tok, idx)
        assert r.status_code in (200, 409), r.text
    body = {"trial_index": idx, "client_trial_id": cid or f"cid{idx:04d}xx", "timed_out": False, "rt_ms": 800.0}
    body.update(kw)
    return client.post("/api/trial", json=body, headers={"X-CSRF-Token": tok})


def _age_trial(app, idx, seconds):
    """Move trial ``idx``'s server-side start ``seconds`` into the past (every participant of this app)."""
    from datetime import timedelta

    from sqlalchemy import select

    from study_site.db import PlanItem

    with app.extensions["camo_study"].db.write() as s, s.begin():
        for it in s.scalars(select(PlanItem).where(PlanItem.idx == idx, PlanItem.started_at.is_not(None))):
            it.started_at = it.started_at - timedelta(seconds=seconds)


def _finish(client, tok, rects, hit_every=2):
    state = client.get("/api/state").get_json()
    for t in state["trials"]:
        sid = t["src"].rsplit("/", 1)[1].split(".")[0]
        x0, y0, x1, y1 = rects[sid]
        if t["index"] % hit_every == 0:
            x, y = (x0 + x1) // 2, (y0 + y1) // 2
        else:
            x, y = (x1 + 1) % 64, (y1 + 1) % 48
        r = _post_trial(client, tok, t["index"], cid=f"c{t['index']:03d}{uuid.uuid4().hex[:16]}", x=x, y=y)
        assert r.status_code == 200, r.text
    r = client.post("/api/complete", json={}, headers={"X-CSRF-Token": tok})
    assert r.status_code == 200, r.text


# ---------------------------------------------------------------------------
# stimuli
# ---------------------------------------------------------------------------


def test_build_stimuli_layout_and_opacity(stim_dir):
    man = json.loads((stim_dir / "manifest.json").read_text())
    formal = [s for s in man["stimuli"] if not s["practice"]]
    practice = [s for s in man["stimuli"] if s["practice"]]
    assert len(formal) == len(SCENES) * len(METHODS) * 2
    # no practice source given: a synthetic practice set of 8 images, none in a formal scene
    assert len(practice) == 8 and all(s["scene"].startswith("practice_synthetic_") for s in practice)
    assert not {s["scene"] for s in practice} & set(SCENES)
    names = " ".join(p.name for p in stim_dir.rglob("*.png"))
    for secret in SCENES + METHODS + ("view_", "mask", "obj", "practice"):
        assert secret not in names
    ids = {s["id"] for s in man["stimuli"]}
    rids = {s["reveal_id"] for s in man["stimuli"]}
    assert len(ids) == len(man["stimuli"]) and not ids & rids
    rects = mask_rects(stim_dir)
    for s in formal:  # recorded placement = the fake renders' rectangles
        x0, y0, x1, y1 = rects[s["id"]]
        assert s["bbox"] == [x0, y0, x1, y1]
        assert s["centroid_x"] == pytest.approx((x0 + x1) / 2 / 64) and s["centroid_y"] == pytest.approx((y0 + y1) / 2 / 48)
        assert s["area_share"] == pytest.approx((x1 - x0) * (y1 - y0) / (64 * 48))
        assert s["centre_hit"] == (x0 <= 32 < x1 and y0 <= 24 < y1)
    for s in formal:
        img = np.asarray(Image.open(stim_dir / "images" / f"{s['id']}.png"))
        src = np.asarray(Image.open(s["source_image"]).convert("RGB"))
        assert np.array_equal(img, src)  # pixels unchanged, only re-encoded
        with Image.open(stim_dir / "images" / f"{s['id']}.png") as im:
            assert not im.text  # no PNG text chunks
        rev = np.asarray(Image.open(stim_dir / "reveal" / f"{s['reveal_id']}.png"))
        assert not np.array_equal(rev, img)


def test_outline_overlay_draws_boundary_only():
    rgb = np.full((40, 40, 3), 100, np.uint8)
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    out = outline_overlay(rgb, mask, thickness=1)
    drawn = np.all(out == [255, 40, 200], axis=-1)
    assert drawn[10, 20] and drawn[29, 15] and not drawn[20, 20] and not drawn[2, 2]


def test_build_stimuli_errors(tmp_path):
    with pytest.raises(CamoError, match="renders.json"):
        build_stimuli([tmp_path], tmp_path / "out")
    (tmp_path / "renders.json").write_text("{not json")
    with pytest.raises(CamoError, match="not valid JSON"):
        build_stimuli([tmp_path], tmp_path / "out")
    (tmp_path / "renders.json").write_text(json.dumps([{"run": "r", "scene": "s", "method": "m", "view": 0}]))
    with pytest.raises(CamoError, match="lacks image, mask"):
        build_stimuli([tmp_path], tmp_path / "out")
    ev = tmp_path / "ev"
    entries = make_fake_eval_dir(ev, scenes=("s",), methods=("m",), views=1, size=(32, 24))
    Image.fromarray(np.zeros((10, 10), np.uint8)).save(ev / entries[0]["mask"])
    with pytest.raises(CamoError, match="mask is 10x10 but the image is 32x24"):
        build_stimuli([ev], tmp_path / "out")


def test_hit_test_against_mask(stim_dir):
    ss = StimulusSet(stim_dir)
    rects = mask_rects(stim_dir)
    st = ss.stimuli[0]
    x0, y0, x1, y1 = rects[st.id]
    assert ss.hit(st, x0, y0) and ss.hit(st, x1 - 1, y1 - 1)
    assert not ss.hit(st, x1, y0) and not ss.hit(st, x0 - 1, y0) and not ss.hit(st, -1, -1)
    assert ss.hit(st, x1 + 1, y0, tolerance_px=2) and not ss.hit(st, x1 + 3, y0, tolerance_px=2)


# ---------------------------------------------------------------------------
# participant flow and storage
# ---------------------------------------------------------------------------


def test_full_session_rows_and_no_leak(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path)
    rects = mask_rects(stim_dir)
    secrets_ = set(SCENES) | set(METHODS) | {s.reveal_id for s in StimulusSet(stim_dir).stimuli}
    c = app.test_client()
    tok = _to_task(c)
    for page in ("/task", "/static/task.js", "/static/study.css", "/api/state"):
        body = c.get(page).get_data(as_text=True)
        assert not [s for s in secrets_ if s in body], page
    state = c.get("/api/state").get_json()
    assert state["total"] == 2 + len(SCENES) and state["practice"] == 2 and state["next"] == 0
    assert [t["practice"] for t in state["trials"]] == [True, True] + [False] * len(SCENES)
    # images only for the participant's own plan; reveal only after answering
    t0 = state["trials"][0]
    assert c.get(t0["src"]).status_code == 200
    rid = next(s.reveal_id for s in StimulusSet(stim_dir).stimuli if s.id == t0["src"].rsplit("/", 1)[1].split(".")[0])
    assert c.get(f"/r/{rid}").status_code == 404
    sid = t0["src"].rsplit("/", 1)[1].split(".")[0]
    x0, y0, x1, y1 = rects[sid]
    x0, y0 = (x0 + x1) // 2, (y0 + y1) // 2  # practice images are synthetic ellipses: aim at the centre
    r = _post_trial(c, tok, 0, x=x0, y=y0, display_w=640.0, display_h=480.0)
    j = r.get_json()
    assert r.status_code == 200 and j["hit"] is True and j["ack"] == "cid0000xx"
    assert c.get(j["reveal"]).status_code == 200 and j["reveal"] == f"/r/{rid}"
    # idempotent: same trial again (retry) -> same answer, one row
    r2 = _post_trial(c, tok, 0, x=0, y=0)
    assert r2.status_code == 200 and r2.get_json()["hit"] is True and r2.get_json()["duplicate"] is True
    # out of order
    assert _post_trial(c, tok, 3, x=1, y=1).status_code == 409
    # a timeout (the server's clock of trial 1 has run out)
    assert _start(c, tok, 1).status_code == 200
    _age_trial(app, 1, 41)
    r = _post_trial(c, tok, 1, cid="cid0001xx", start=False, timed_out=True, rt_ms=40010.0)
    assert r.status_code == 200 and r.get_json()["timed_out"] is True and r.get_json()["hit"] is False
    # completion refused while trials are missing
    assert c.post("/api/complete", json={}, headers={"X-CSRF-Token": tok}).status_code == 409
    _finish(c, tok, rects)
    r = c.get("/done")
    assert r.status_code == 200 and re.search(r'id="completion-code">[0-9A-F]{8}<', r.text)
    from study_site.analysis import load_tables

    trials, parts = load_tables(app.extensions["camo_study"].db.engine)
    assert len(trials) == state["total"]
    assert trials["trial_index"].tolist() == list(range(state["total"]))
    row0 = trials.iloc[0]
    assert (row0.click_x, row0.click_y, row0.hit, row0.display_w) == (x0, y0, True, 640.0)
    assert not row0.late and not row0.too_fast and row0.starts == 1 and 0 <= row0.server_rt_ms < 5000
    assert trials.iloc[1].timed_out and np.isnan(trials.iloc[1].click_x)
    assert sorted(trials.loc[~trials.practice, "scene"]) == sorted(SCENES)
    assert parts.iloc[0].age_bracket == "18-24" and parts.iloc[0].completed
    assert "PID_0001" not in parts.to_csv() and len(parts.iloc[0].pid_hmac) == 64
    # cannot take the study twice; resume of a finished session lands on /done
    c2 = app.test_client()
    r = c2.get("/?PROLIFIC_PID=PID_0001", follow_redirects=True)
    assert "already taken part" in r.text


def test_reload_resumes_without_reshowing(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path)
    c = app.test_client()
    tok = _to_task(c, "RESUME_1")
    for i in range(3):
        assert _post_trial(c, tok, i, x=1, y=1).status_code == 200
    st = c.get("/api/state").get_json()
    assert st["next"] == 3 and [t["index"] for t in st["trials"]] == list(range(3, st["total"]))
    # the landing link again (new browser) resumes the same participant at the task
    c2 = app.test_client()
    r = c2.get("/?PROLIFIC_PID=RESUME_1", follow_redirects=True)
    assert r.request.path == "/task"
    assert c2.get("/api/state").get_json()["next"] == 3
    # pre-task pages redirect to the current stage
    assert c.get("/consent").headers["Location"].endswith("/task")


def test_cells_fill_evenly(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path, PRACTICE_TRIALS=0)
    for i in range(2 * len(METHODS)):
        _to_task(app.test_client(), f"BAL_{i:03d}")
    with app.extensions["camo_study"].db.read() as s:
        from sqlalchemy import select

        from study_site.db import PlanItem

        cells = Counter((p.scene, p.method) for p in s.scalars(select(PlanItem)))
        orders = {}
        for p in s.scalars(select(PlanItem).order_by(PlanItem.participant_id, PlanItem.idx)):
            orders.setdefault(p.participant_id, []).append(p.scene)
    assert set(cells.values()) == {2} and len(cells) == len(SCENES) * len(METHODS)
    assert all(sorted(o) == sorted(SCENES) for o in orders.values())
    assert len({tuple(o) for o in orders.values()}) > 1  # orders are shuffled


def test_declined_and_age_required(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path)
    c = app.test_client()
    c.get("/?id=someone_42")
    tok = _csrf(c.get("/consent").text)
    r = c.post("/consent", data={"csrf_token": tok, "consent": "no"}, follow_redirects=True)
    assert "chose not to take part" in r.text
    c.get("/?id=someone_42")  # came back: asked again
    assert c.get("/consent").status_code == 200
    c.post("/consent", data={"csrf_token": tok, "consent": "yes"})
    r = c.post("/about-you", data={"csrf_token": tok})  # adults only: the age bracket is required
    assert r.status_code == 400 and "Please choose your age bracket" in r.text
    assert c.post("/about-you", data={"csrf_token": tok, "age": "99"}).status_code == 400
    assert c.post("/about-you", data={"csrf_token": tok, "age": "prefer_not"}).status_code == 400
    assert c.post("/about-you", data={"csrf_token": tok, "age": "25-34"}).status_code == 302


def test_anonymous_start_and_admin(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path)
    c = app.test_client()
    tok = _csrf(c.get("/").text)
    r = c.post("/", data={"csrf_token": tok, "participant_id": ""})
    assert r.status_code == 302
    r = c.get("/admin/")
    assert r.status_code == 401 and r.headers["WWW-Authenticate"].startswith("Bearer") and "Admin token" in r.text
    assert c.get("/admin/export/trials.csv").status_code == 401
    assert c.get("/admin/", headers={"Authorization": "Bearer wrong"}).status_code == 403
    assert c.get("/admin/export/trials.csv", headers={"Authorization": "Bearer wrong"}).status_code == 403
    assert c.post("/admin/login", data={"csrf_token": tok, "token": "nope"}).status_code == 403
    r = c.get("/admin/export/participants.csv", headers={"Authorization": "Bearer admintok123"})
    assert r.status_code == 200 and r.text.startswith("participant,")
    c.post("/admin/login", data={"csrf_token": tok, "token": "admintok123"})
    r = c.get("/admin/")
    assert r.status_code == 200 and "scn_forest_z3" in r.text and "mth_ours_v9" in r.text
    app2 = _app(stim_dir, tmp_path, ADMIN_TOKEN=None)
    assert app2.test_client().get("/admin/").status_code == 404


# ---------------------------------------------------------------------------
# protection: CSRF, validation, sizes, rate limits
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "body",
    [
        None,
        "[" * 8000,  # nesting deeper than the JSON parser's recursion limit
        [],
        {"trial_index": "0", "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1},
        {"trial_index": True, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "a b", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": "no", "rt_ms": 1, "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": -5, "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1e308 * 10, "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 10**30, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 64, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 99_000, "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": True, "rt_ms": 1, "x": 1, "y": 1},
        {"trial_index": 999, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1, "z": 2},
        # a timeout 3 ms into a 40 s trial
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": True, "rt_ms": 3},
        # more time than the server has seen since the start
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 5000, "x": 1, "y": 1},
        # 401-digit integers (json.loads makes Python ints; float() of them overflows)
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 10**400, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": -(10**400), "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1,
         "display_w": 10**400},
        {"trial_index": 10**400, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1, "dpr": 0},
        {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1,
         "viewport_w": -1},
    ],
)
def test_malformed_trials_are_4xx(stim_dir, tmp_path, body):
    app = _app(stim_dir, tmp_path)
    c = app.test_client()
    tok = _to_task(c)
    assert _start(c, tok, 0).status_code == 200
    if body is None or isinstance(body, str):
        raw = "{nope" if body is None else body
        r = c.post("/api/trial", data=raw, content_type="application/json", headers={"X-CSRF-Token": tok})
    else:
        raw = json.dumps(body, allow_nan=True)
        r = c.post("/api/trial", data=raw, content_type="application/json", headers={"X-CSRF-Token": tok})
    assert 400 <= r.status_code < 500, (body, r.status_code)
    assert r.is_json and "error" in r.get_json() and "\n" not in r.get_json()["error"]
    assert c.get("/api/state").get_json()["next"] == 0  # nothing stored


def test_csrf_size_and_rate_limits(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path, RATE_LIMIT_PER_S=1.0, RATE_LIMIT_BURST=12)
    c = app.test_client()
    tok = _to_task(c)
    ok = {"trial_index": 0, "client_trial_id": "abcdefgh", "timed_out": False, "rt_ms": 1, "x": 1, "y": 1}
    assert c.post("/api/trial", json=ok).status_code == 400  # no CSRF header
    assert c.post("/api/trial", json=ok, headers={"X-CSRF-Token": "forged"}).status_code == 400
    big = dict(ok, pad="x" * 40_000)
    assert c.post("/api/trial", json=big, headers={"X-CSRF-Token": tok}).status_code == 413
    assert c.post("/consent", data={"consent": "yes"}).status_code in (302, 400)  # no token on a form
    other = app.test_client()  # a foreign session's token is useless
    other_tok = _csrf(other.get("/").text)
    assert c.post("/api/trial", json=ok, headers={"X-CSRF-Token": other_tok}).status_code == 400
    codes = [c.get("/api/state").status_code for _ in range(20)]
    assert 429 in codes and codes[0] == 200
    assert other.get("/?PROLIFIC_PID=" + "x" * 300).status_code == 400
    assert other.get("/?PROLIFIC_PID=bad%20id%00").status_code == 400
    assert other.get("/i/..%2f..%2fmanifest.json").status_code == 404
    assert other.get("/r/notatoken!").status_code == 404


def test_new_participant_limit(stim_dir, tmp_path):
    app = _app(stim_dir, tmp_path, NEW_PARTICIPANTS_PER_MIN=2)
    codes = [app.test_client().get(f"/?id=flood{i}").status_code for i in range(4)]
    assert codes[:2] == [302, 302] and codes[2:] == [429, 429]


# ---------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------


def _parser():
    p = argparse.ArgumentParser(prog="camo")
    register(p.add_subparsers(dest="command", required=True))
    return p


def test_cli_build_and_report(tmp_path, capsys):
    ev = tmp_path / "ev"
    make_fake_eval_dir(ev, scenes=("s1", "s2"), methods=("m1", "m2"), views=1, size=(40, 30))
    p = _parser()
    # --observer-trials 0: the site and the report are under test; the predictions: tests/test_power.py
    args = p.parse_args(["study", "build-stimuli", str(ev), "--out", str(tmp_path / "stim"), "--copy",
                         "--observer-trials", "0"])
    assert args.func(args) == 0
    assert "2 scenes x 2 methods" in capsys.readouterr().out
    app = _app(tmp_path / "stim", tmp_path, PRACTICE_TRIALS=1)
    rects = mask_rects(tmp_path / "stim")
    for i in range(3):
        c = app.test_client()
        _finish(c, _to_task(c, f"REP_{i}"), {k: (0, 0, 1, 1) if i else v for k, v in rects.items()})
    args = p.parse_args(["study", "report", "--db", str(tmp_path / "study.sqlite"), "--out", str(tmp_path / "rep"),
                         "--bootstrap", "200"])
    assert args.func(args) == 0
    for f in ("table_i.md", "table_i.csv", "km.png", "pairwise.csv", "trials.csv", "trials.parquet",
              "participants.csv", "participants.parquet"):
        assert (tmp_path / "rep" / f).stat().st_size > 0, f
    import pandas as pd

    t = read_parquet(tmp_path / "rep" / "trials.parquet")
    assert len(t) == 3 * 3 and t["practice"].sum() == 3
    assert set(t.loc[t.practice, "scene"]) <= {f"practice_synthetic_{i:02d}" for i in range(8)}


def test_cli_bad_input_raises_camoerror(tmp_path):
    p = _parser()
    for argv in (
        ["study", "build-stimuli", str(tmp_path / "missing"), "--out", str(tmp_path / "o")],
        ["study", "serve", "--stimuli", str(tmp_path / "missing"), "--db", "sqlite:///x.db"],
        ["study", "serve", "--stimuli", str(tmp_path), "--db", str(tmp_path / "x.db")],  # no manifest
        ["study", "report", "--db", str(tmp_path / "none.sqlite"), "--out", str(tmp_path / "r")],
        ["study", "report", "--db", "nosuchdialect://x", "--out", str(tmp_path / "r")],
    ):
        args = p.parse_args(argv)
        with pytest.raises(CamoError):
            args.func(args)
    with pytest.raises(SystemExit):
        p.parse_args(["study"])
    with pytest.raises(SystemExit):  # out of range: refused by the flag's type (tests/test_cli_ranges.py)
        p.parse_args(["study", "serve", "--stimuli", str(tmp_path), "--db", "sqlite:///x.db", "--port", "70000"])


# ---------------------------------------------------------------------------
# property: no request body makes the trial API fail with a 5xx
# ---------------------------------------------------------------------------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as hs  # noqa: E402

_json = hs.recursive(
    hs.none() | hs.booleans() | hs.integers() | hs.floats(allow_nan=True) | hs.text(max_size=20),
    lambda kids: hs.lists(kids, max_size=4) | hs.dictionaries(hs.text(max_size=8), kids, max_size=4),
    max_leaves=12,
)
_keys = hs.sampled_from(["trial_index", "client_trial_id", "timed_out", "x", "y", "rt_ms", "display_w", "extra"])


@pytest.fixture(scope="module")
def fuzz_client(stim_dir, tmp_path_factory):
    app = _app(stim_dir, tmp_path_factory.mktemp("fuzz"), RATE_LIMIT_PER_S=0)
    c = app.test_client()
    return c, _to_task(c, "FUZZ_1")


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(body=hs.dictionaries(_keys, _json, max_size=8) | _json)
def test_trial_api_never_5xx(fuzz_client, body):
    c, tok = fuzz_client
    r = c.post("/api/trial", data=json.dumps(body), content_type="application/json", headers={"X-CSRF-Token": tok})
    assert r.status_code < 500, (body, r.status_code, r.get_data(as_text=True)[:200])


def test_locked_database_is_503_then_retry_succeeds(stim_dir, tmp_path):
    import sqlite3

    app = _app(stim_dir, tmp_path, SQLITE_BUSY_TIMEOUT_MS=100)
    c = app.test_client()
    tok = _to_task(c, "LOCK_1")
    assert _start(c, tok, 0).status_code == 200
    _age_trial(app, 0, 40)
    con = sqlite3.connect(tmp_path / "study.sqlite", isolation_level=None)
    con.execute("BEGIN IMMEDIATE")  # another writer holds the database
    r = _post_trial(c, tok, 0, start=False, timed_out=True, rt_ms=40000.0)
    assert r.status_code == 503 and r.headers["Retry-After"] == "1"
    con.execute("ROLLBACK")
    con.close()
    r = _post_trial(c, tok, 0, start=False, timed_out=True, rt_ms=40000.0)  # the client's retry
    assert r.status_code == 200 and r.get_json()["duplicate"] is False


# ---------------------------------------------------------------------------
# stimulus images: static, immutable, headers without build times
# ---------------------------------------------------------------------------


def test_stimulus_headers_reveal_nothing(stim_dir, tmp_path):
    """/i/<id>.webp and .png: immutable caching, ETag = content hash (304 on If-None-Match), no Last-Modified,
    the same pixels in both formats; a file's modification time changes no header; the reveal image likewise."""
    import hashlib
    import io
    import os

    app = _app(stim_dir, tmp_path)
    c = app.test_client()
    tok = _to_task(c)
    state = c.get("/api/state").get_json()
    t0 = state["trials"][0]
    assert t0["src"].endswith(".webp") and t0["fallback"] == t0["src"][:-5] + ".png"
    got = {}
    for url, mime in ((t0["src"], "image/webp"), (t0["fallback"], "image/png")):
        other = app.test_client()  # static: the unguessable URL is the permission, no session needed
        r = other.get(url)
        assert r.status_code == 200 and r.mimetype == mime, url
        body = r.get_data()
        assert "Last-Modified" not in r.headers and "Set-Cookie" not in r.headers
        assert r.headers["ETag"] == '"' + hashlib.sha256(body).hexdigest()[:32] + '"'
        assert r.headers["Cache-Control"] == "public, max-age=31536000, immutable"
        assert r.headers["Content-Length"] == str(len(body))
        r304 = other.get(url, headers={"If-None-Match": r.headers["ETag"]})
        assert r304.status_code == 304 and r304.get_data() == b""
        got[mime] = np.asarray(Image.open(io.BytesIO(body)).convert("RGB"))
    assert np.array_equal(got["image/webp"], got["image/png"])  # lossless: pixel-identical
    # every stimulus of the set: WebP smaller than PNG, pixel-identical, and the ETag does not move with the mtime
    ss = StimulusSet(stim_dir)
    for st in ss.stimuli:
        a = np.asarray(Image.open(ss.image_path(st, ".webp")).convert("RGB"))
        assert np.array_equal(a, np.asarray(Image.open(ss.image_path(st)).convert("RGB")))
    etag = c.get(t0["src"]).headers["ETag"]
    sid = t0["src"].rsplit("/", 1)[1].split(".")[0]
    os.utime(ss.image_path(ss.by_id[sid], ".webp"), (1_000_000_000, 1_000_000_000))
    (tmp_path / "b").mkdir()
    assert _app(stim_dir, tmp_path / "b").test_client().get(t0["src"]).headers["ETag"] == etag
    for bad in ("/i/nope.webp", "/i/" + sid, "/i/../manifest.json", "/i/" + sid + ".png/x"):
        assert c.get(bad).status_code == 404, bad
    assert c.post(t0["src"]).status_code == 405
    # the reveal, once answered: WebP to a browser that takes it, PNG otherwise; content-hash ETag, no time
    rects = mask_rects(stim_dir)
    x0, y0, x1, y1 = rects[sid]
    j = _post_trial(c, tok, 0, x=(x0 + x1) // 2, y=(y0 + y1) // 2).get_json()
    rw = c.get(j["reveal"], headers={"Accept": "image/avif,image/webp,image/png,*/*"})
    rp = c.get(j["reveal"], headers={"Accept": "image/png"})
    assert (rw.status_code, rw.mimetype, rp.mimetype) == (200, "image/webp", "image/png")
    for r in (rw, rp):
        assert "Last-Modified" not in r.headers and "Accept" in r.headers["Vary"]
        assert r.headers["ETag"] == '"' + hashlib.sha256(r.get_data()).hexdigest()[:32] + '"'
        assert c.get(j["reveal"], headers={"If-None-Match": r.headers["ETag"],
                                           "Accept": r.request.headers.get("Accept")}).status_code == 304


def test_cookie_key_outside_the_database(stim_dir, tmp_path, capsys):
    """The cookie-signing key is read from a file (`make-key`, --secret-key-file), never written to the database;
    without one the server refuses to start in one line (DEV keeps one in the database)."""
    from camo.cli import main
    from study_site.db import Setting

    cfg = {"STIMULI_DIR": str(stim_dir), "DATABASE_URL": f"sqlite:///{tmp_path / 'c.sqlite'}", "ID_HMAC_KEY": ID_KEY}
    with pytest.raises(CamoError, match=r"^SECRET_KEY \(the cookie-signing key\) is not set: .*camo study make-key"):
        create_app(cfg)
    key = tmp_path / "cookie.key"
    assert main(["study", "make-key", str(key)]) == 0
    app = create_app(dict(cfg, SECRET_KEY_FILE=str(key)))
    assert app.secret_key == key.read_text().strip()
    with app.extensions["camo_study"].db.read() as s:
        assert s.get(Setting, "secret_key") is None
    (tmp_path / "short.key").write_text("x" * 10)
    with pytest.raises(CamoError, match="SECRET_KEY file .* shorter than 32"):
        create_app(dict(cfg, SECRET_KEY_FILE=str(tmp_path / "short.key")))
    with pytest.raises(CamoError, match="must be different keys"):
        create_app(dict(cfg, SECRET_KEY=ID_KEY))
    dev = create_app(dict(cfg, DEV=True))
    with dev.extensions["camo_study"].db.read() as s:
        assert s.get(Setting, "secret_key").value == dev.secret_key
    idk = tmp_path / "id.key"
    idk.write_text("ab" * 32)
    capsys.readouterr()
    rc = main(["study", "serve", "--stimuli", str(stim_dir), "--db", str(tmp_path / "d.sqlite"), "--id-key-file",
               str(idk)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("camo: error: SECRET_KEY (the cookie-signing key) is not set")
