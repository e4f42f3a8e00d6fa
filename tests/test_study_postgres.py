"""The study app on PostgreSQL (opt-in): set CAMO_TEST_POSTGRES_URL to a *throw-away* database whose
name contains "test", e.g. postgresql+psycopg://postgres@/camo_study_test?host=/tmp/pgsock. Its study
tables are dropped and recreated."""

from __future__ import annotations

import os
import re
import threading
from collections import Counter

import pytest

URL = os.environ.get("CAMO_TEST_POSTGRES_URL", "")


def _db_name(url: str) -> str:
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).database or ""
    except Exception:  # noqa: BLE001
        return ""


pytestmark = pytest.mark.skipif(
    not URL or "test" not in _db_name(URL),
    reason="set CAMO_TEST_POSTGRES_URL to a throw-away PostgreSQL database named *test*",
)


def _to_task(client, pid):
    client.get(f"/?PROLIFIC_PID={pid}")
    tok = re.search(r'name="csrf_token" value="([^"]+)"', client.get("/consent").text).group(1)
    client.post("/consent", data={"csrf_token": tok, "consent": "yes"})
    client.post("/about-you", data={"csrf_token": tok, "age": "30-40"})
    assert client.post("/instructions", data={"csrf_token": tok}).status_code == 302
    return tok


def test_postgres_concurrent_sessions_and_report(tmp_path):
    pytest.importorskip("psycopg")
    from study_site import create_app
    from study_site.analysis import write_report
    from study_site.db import Base, make_engine
    from study_site.stimuli import build_stimuli
    from study_site.testing import make_fake_eval_dir

    eng = make_engine(URL)
    Base.metadata.drop_all(eng)
    eng.dispose()
    make_fake_eval_dir(tmp_path / "ev", scenes=("pa", "pb"), methods=("m1", "m2", "m3"), views=1, size=(40, 30))
    build_stimuli([tmp_path / "ev"], tmp_path / "stim", log=lambda m: None)
    app = create_app({"STIMULI_DIR": str(tmp_path / "stim"), "DATABASE_URL": URL, "PRACTICE_TRIALS": 1,
                      "RATE_LIMIT_PER_S": 0})
    errors = []

    def participant(i):
        try:
            c = app.test_client()
            tok = _to_task(c, f"PG_{i}")
            st = c.get("/api/state").get_json()
            for t in st["trials"]:
                body = {"trial_index": t["index"], "client_trial_id": f"pg{i:03d}t{t['index']:02d}",
                        "timed_out": False, "rt_ms": 1000.0 + i, "x": 1, "y": 1}
                for _ in range(2):  # a retry of the same answer is ignored
                    r = c.post("/api/trial", json=body, headers={"X-CSRF-Token": tok})
                    assert r.status_code == 200, r.text
            assert c.post("/api/complete", json={}, headers={"X-CSRF-Token": tok}).status_code == 200
        except Exception as exc:  # noqa: BLE001
            errors.append(repr(exc))

    threads = [threading.Thread(target=participant, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, errors
    res = write_report(URL, tmp_path / "rep", n_boot=100)
    trials = res["trials"]
    assert len(trials) == 6 * 3 and trials.groupby(["participant", "trial_index"]).size().max() == 1
    cells = Counter(zip(trials.loc[~trials.practice, "scene"], trials.loc[~trials.practice, "method"]))
    assert set(cells.values()) == {2}  # 6 participants over 3 methods per scene, least-filled first
    app.extensions["camo_study"].db.dispose()
