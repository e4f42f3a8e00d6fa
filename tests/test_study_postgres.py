"""The study app's storage on a real PostgreSQL server (the documented hosting database).

The server is a throw-away cluster started by the ``postgres_url`` fixture (tests/conftest.py: initdb +
pg_ctl in a temporary folder, unix socket only; ``.ci/system-deps postgresql`` installs the server when
missing), or the database named by CAMO_TEST_POSTGRES_URL. Study tables are dropped first."""

from __future__ import annotations

import re
import threading
from collections import Counter
from datetime import timedelta

import pytest
from sqlalchemy import select

ID_KEY = "p" * 64


@pytest.fixture()
def pg(postgres_url):
    from study_site.db import Base, make_engine

    eng = make_engine(postgres_url)
    Base.metadata.drop_all(eng)
    eng.dispose()
    return postgres_url


@pytest.fixture(scope="module")
def stim(tmp_path_factory):
    from study_site.stimuli import build_stimuli
    from study_site.testing import make_fake_eval_dir

    root = tmp_path_factory.mktemp("pgstim")
    make_fake_eval_dir(root / "ev", scenes=("pa", "pb"), methods=("m1", "m2", "m3"), views=1, size=(40, 30))
    build_stimuli([root / "ev"], root / "stim", log=lambda m: None)
    return root / "stim"


def _app(stim, url, **cfg):
    from study_site import create_app

    app = create_app({"STIMULI_DIR": str(stim), "DATABASE_URL": url, "PRACTICE_TRIALS": 1, "RATE_LIMIT_PER_S": 0,
                      "ID_HMAC_KEY": ID_KEY, "SECRET_KEY": "s" * 64, "TRIAL_TIME_LIMIT_S": 10, **cfg})
    app.testing = True
    return app


def _to_task(client, pid):
    client.get(f"/?PROLIFIC_PID={pid}")
    tok = re.search(r'name="csrf_token" value="([^"]+)"', client.get("/consent").text).group(1)
    client.post("/consent", data={"csrf_token": tok, "consent": "yes"})
    client.post("/about-you", data={"csrf_token": tok, "age": "35-44"})
    assert client.post("/instructions", data={"csrf_token": tok}).status_code == 302
    return tok


def test_postgres_round_trip_retries_and_clock(pg, stim):
    """One participant: stored values read back exactly, retries (same and new client id) never duplicate,
    out-of-order answers are refused, the server clock survives a reload, late answers become timeouts."""
    from study_site.analysis import load_tables
    from study_site.db import PlanItem
    from study_site.testing import mask_rects

    from sqlalchemy import text

    app = _app(stim, pg)
    assert app.extensions["camo_study"].db.dialect == "postgresql"
    with app.extensions["camo_study"].db.write_light() as s, s.begin():  # trial starts: no WAL flush wait
        assert s.execute(text("SHOW synchronous_commit")).scalar() == "off"
    with app.extensions["camo_study"].db.read() as s:
        default = s.execute(text("SHOW synchronous_commit")).scalar()  # "off" in this fsync-less test cluster
    with app.extensions["camo_study"].db.write() as s, s.begin():  # trials: the server's (durable) setting
        assert s.execute(text("SHOW synchronous_commit")).scalar() == default
    c = app.test_client()
    tok = _to_task(c, "PG_ROUND")
    h = {"X-CSRF-Token": tok}
    rects = mask_rects(stim)
    trials = c.get("/api/state").get_json()["trials"]
    assert [t["practice"] for t in trials] == [True, False, False]
    # trial 0: hit, then two retries
    sid = trials[0]["src"].rsplit("/", 1)[1].split(".")[0]
    x0, y0, x1, y1 = rects[sid]
    assert c.post("/api/start", json={"trial_index": 0}, headers=h).get_json()["starts"] == 1
    body = {"trial_index": 0, "client_trial_id": "pground-0", "timed_out": False, "rt_ms": 612.5,
            "x": (x0 + x1) // 2, "y": (y0 + y1) // 2, "display_w": 576.0, "display_h": 432.0,
            "viewport_w": 1280.0, "viewport_h": 800.0, "dpr": 2.0}
    first = c.post("/api/trial", json=body, headers=h).get_json()
    again = c.post("/api/trial", json=body, headers=h).get_json()
    other = c.post("/api/trial", json=dict(body, client_trial_id="pground-0b", x=0, y=0), headers=h).get_json()
    assert first["hit"] is True and first["duplicate"] is False
    assert again["duplicate"] is True and other["duplicate"] is True and other["hit"] is True
    assert other["stored_client_trial_id"] == "pground-0"
    # out of order
    r = c.post("/api/trial", json=dict(body, trial_index=2, client_trial_id="pground-2"), headers=h)
    assert r.status_code == 409
    # trial 1: reload after 4 s keeps the clock; trial answered late -> timeout
    c.post("/api/start", json={"trial_index": 1}, headers=h)
    db = app.extensions["camo_study"].db
    with db.write() as s, s.begin():
        it = s.scalar(select(PlanItem).where(PlanItem.idx == 1))
        it.started_at -= timedelta(seconds=13)
    st = c.post("/api/start", json={"trial_index": 1}, headers=h).get_json()
    assert st["starts"] == 2 and st["remaining_ms"] == 0 and st["elapsed_ms"] >= 13000
    sid = trials[1]["src"].rsplit("/", 1)[1].split(".")[0]
    x0, y0, x1, y1 = rects[sid]
    late = {"trial_index": 1, "client_trial_id": "pground-1", "timed_out": False, "rt_ms": 12000.0,
            "x": (x0 + x1) // 2, "y": (y0 + y1) // 2}
    j = c.post("/api/trial", json=late, headers=h).get_json()
    assert j["timed_out"] is True and j["late"] is True and j["hit"] is False
    c.post("/api/start", json={"trial_index": 2}, headers=h)
    j = c.post("/api/trial", json={"trial_index": 2, "client_trial_id": "pground-2", "timed_out": False,
                                   "rt_ms": 10.0, "x": 1, "y": 1}, headers=h).get_json()
    assert j["too_fast"] is True
    assert c.post("/api/complete", json={}, headers=h).status_code == 200
    t, parts = load_tables(db.engine)
    assert t["trial_index"].tolist() == [0, 1, 2] and t["client_trial_id"].tolist() == ["pground-0", "pground-1",
                                                                                      "pground-2"]
    r0 = t.iloc[0]
    assert (r0.rt_ms, r0.display_w, r0.viewport_h, r0.dpr, r0.click_x) == (612.5, 576.0, 800.0, 2.0, body["x"])
    assert bool(r0.hit) and not bool(r0.late) and r0.starts == 1
    assert bool(t.iloc[1].late) and bool(t.iloc[1].timed_out) and t.iloc[1].starts == 2
    assert t.iloc[1].server_rt_ms >= 13000 and bool(t.iloc[2].too_fast)
    assert parts.iloc[0].age_bracket == "35-44" and bool(parts.iloc[0].completed)
    db.dispose()


def test_postgres_concurrent_sessions_and_report(pg, stim, tmp_path):
    from study_site.analysis import write_report

    app = _app(stim, pg, RT_FLOOR_MS=0)  # answers follow their start at once
    errors = []

    def participant(i):
        try:
            c = app.test_client()
            tok = _to_task(c, f"PG_{i}")
            h = {"X-CSRF-Token": tok}
            st = c.get("/api/state").get_json()
            for t in st["trials"]:
                assert c.post("/api/start", json={"trial_index": t["index"]}, headers=h).status_code == 200
                body = {"trial_index": t["index"], "client_trial_id": f"pg{i:03d}t{t['index']:02d}",
                        "timed_out": False, "rt_ms": 400.0 + i, "x": 1, "y": 1}
                for _ in range(2):  # a retry of the same answer is ignored
                    r = c.post("/api/trial", json=body, headers=h)
                    assert r.status_code == 200, r.text
            assert c.post("/api/complete", json={}, headers=h).status_code == 200
        except Exception as exc:  # noqa: BLE001
            errors.append(repr(exc))

    threads = [threading.Thread(target=participant, args=(i,)) for i in range(12)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    res = write_report(pg, tmp_path / "rep", n_boot=100, stimuli_dir=stim)
    trials = res["trials"]
    assert len(trials) == 12 * 3 and trials.groupby(["participant", "trial_index"]).size().max() == 1
    cells = Counter(zip(trials.loc[~trials.practice, "scene"], trials.loc[~trials.practice, "condition"]))
    assert set(cells.values()) == {4}  # 12 participants over 3 methods per scene, least-filled first
    assert res["baselines"].set_index("condition").loc["all", "n_trials"] == 24
    app.extensions["camo_study"].db.dispose()


def test_production_command_gunicorn_on_postgres(pg, stim, tmp_path):
    """The documented production command, `camo study serve --workers 2 --db postgresql+psycopg://...` (gunicorn,
    two worker processes), started as a subprocess: simulated participants take the whole study over HTTP, every
    trial is stored once, the image headers are the static ones, and both workers are up."""
    import http.client
    import os
    import signal
    import socket
    import subprocess
    import sys
    import time
    from pathlib import Path

    from study_site.analysis import load_tables
    from study_site.simulate import simulate

    root = Path(__file__).resolve().parents[1]
    keys = []
    for name in ("id.key", "cookie.key"):
        keys.append(tmp_path / name)
        subprocess.run([sys.executable, "-m", "camo.cli", "study", "make-key", str(keys[-1])], check=True,
                       capture_output=True, cwd=root, env=dict(os.environ, PYTHONPATH=str(root)))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, PYTHONPATH=str(root), CAMO_STUDY_PRACTICE_TRIALS="1", CAMO_STUDY_RT_FLOOR_MS="0")
    cmd = [sys.executable, "-m", "camo.cli", "study", "serve", "--stimuli", str(stim), "--db", pg, "--port", str(port),
           "--workers", "2", "--threads", "4", "--id-key-file", str(keys[0]), "--secret-key-file", str(keys[1]),
           "--time-limit", "3"]
    proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        t_end = time.monotonic() + 90
        while True:
            assert proc.poll() is None and time.monotonic() < t_end, proc.stdout.read().decode()[-2000:]
            try:
                c = http.client.HTTPConnection("127.0.0.1", port, timeout=2)
                c.request("GET", "/healthz")
                if c.getresponse().status == 200:
                    break
            except OSError:
                time.sleep(0.2)
        # the first worker may answer /healthz before the master has forked the second (seen under load): wait
        while True:
            workers = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
            if len(workers) >= 2 or time.monotonic() > t_end:
                break
            time.sleep(0.2)
        assert len(workers) == 2
        res = simulate(f"http://127.0.0.1:{port}", 8, concurrency=8, seed=5, max_seconds=120)
        assert res["completed"] == 8 and res["n_errors"] == 0, res["errors"]
        trials, parts = load_tables(pg)
        assert len(trials) == 8 * 3 and trials.groupby(["participant", "trial_index"]).size().max() == 1
        assert bool(parts["completed"].all()) and set(parts["age_bracket"]) <= {"18-24", "25-34", "35-44", "45-54",
                                                                               "55-64", "65+"}
        sid = trials["stimulus_id"].iloc[0]
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
        c.request("GET", f"/i/{sid}.webp")
        r = c.getresponse()
        r.read()
        assert r.status == 200 and r.getheader("Content-Type") == "image/webp"
        assert r.getheader("Last-Modified") is None and "immutable" in r.getheader("Cache-Control")
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(30)
