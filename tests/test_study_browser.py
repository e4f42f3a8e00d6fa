"""Whole participant sessions in a real headless Chromium against the study app on 127.0.0.1.

Set STUDY_SHOTS_DIR=/tmp/study_shots to also save screenshots of every page.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"{CHROMIUM} is not installed (Debian package chromium)"),
]

LIMIT_S = 2.0
N_PRACTICE = 5
SCENES = ("scn_harbour_h1", "scn_meadow_m2", "scn_atrium_a3")
METHODS = ("mth_ours_o1", "mth_noise_n2")
SIZE = (480, 320)
SHOTS = os.environ.get("STUDY_SHOTS_DIR")


class Recorder:
    """WSGI middleware that keeps every request line and response body the browser gets."""

    def __init__(self, app):
        self.app = app
        self.log: list[tuple[float, str, str, int, bytes]] = []
        self.lock = threading.Lock()

    def __call__(self, environ, start_response):
        status = {}

        def sr(s, headers, exc_info=None):
            status["code"] = int(s.split()[0])
            return start_response(s, headers, exc_info)

        chunks = list(self.app(environ, sr))
        url = environ.get("PATH_INFO", "") + ("?" + environ["QUERY_STRING"] if environ.get("QUERY_STRING") else "")
        with self.lock:
            self.log.append((time.monotonic(), environ["REQUEST_METHOD"], url, status.get("code", 0), b"".join(chunks)))
        return chunks


def _serve_site(root, limit_s=LIMIT_S, n_practice=N_PRACTICE):
    from werkzeug.serving import WSGIRequestHandler, make_server

    from study_site import create_app
    from study_site.stimuli import build_stimuli
    from study_site.testing import make_fake_eval_dir, mask_rects

    make_fake_eval_dir(root / "eval", scenes=SCENES, methods=METHODS, views=2, size=SIZE, seed=3)
    build_stimuli([root / "eval"], root / "stim", log=lambda m: None)
    app = create_app(
        {
            "STIMULI_DIR": str(root / "stim"),
            "DATABASE_URL": f"sqlite:///{root / 'study.sqlite'}",
            "TRIAL_TIME_LIMIT_S": limit_s,
            "PRACTICE_TRIALS": n_practice,
            "COMPLETION_CODE": "C0DE1234",
            "ID_HMAC_KEY": "b" * 64, "SECRET_KEY": "s" * 64,
        }
    )
    rec = Recorder(app)

    class QuietHandler(WSGIRequestHandler):
        def log_request(self, *a, **k):
            pass

    srv = make_server("127.0.0.1", 0, rec, threaded=True, request_handler=QuietHandler)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    manifest = json.loads((root / "stim" / "manifest.json").read_text())
    site = {
        "base": f"http://127.0.0.1:{srv.server_port}",
        "app": app,
        "rec": rec,
        "rects": mask_rects(root / "stim"),
        "manifest": manifest,
        "stim_dir": root / "stim",
    }

    def close():
        srv.shutdown()
        th.join(5)
        app.extensions["camo_study"].db.dispose()

    return site, close


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    s, close = _serve_site(tmp_path_factory.mktemp("browser_study"))
    yield s
    close()


@pytest.fixture(scope="module")
def slow_site(tmp_path_factory):
    """6 s per trial, one practice trial: room for a reload in the middle of a trial."""
    s, close = _serve_site(tmp_path_factory.mktemp("browser_reload"), limit_s=6.0, n_practice=1)
    yield s
    close()


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright  # dev dependency: a missing one is an error, not a skip

    with sync_playwright() as pw:
        b = pw.chromium.launch(
            executable_path=CHROMIUM,
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--no-first-run"],
        )
        yield b
        b.close()


def shot(page, name):
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(SHOTS) / f"{name}.png"))


class Participant:
    """Drives one browser page through the study; remembers what it clicked."""

    def __init__(self, site, context, pid):
        self.site, self.page, self.pid = site, context.new_page(), pid
        self.page.set_default_timeout(15_000)
        self.clicks: dict[int, dict] = {}  # plan index -> what was done
        self.seen: list[str] = []  # stimulus ids in the order shown

    def start(self, shots=False):
        p = self.page
        p.goto(f"{self.site['base']}/?PROLIFIC_PID={self.pid}&STUDY_ID=STUDY9&SESSION_ID=S{self.pid}")
        p.wait_for_url("**/consent")
        if shots:
            shot(p, "02_consent")
        p.click("#agree")
        p.wait_for_url("**/about-you")
        p.check("input[value='18-24']")
        if shots:
            shot(p, "03_about_you")
        p.click("#continue")
        p.wait_for_url("**/instructions")
        if shots:
            shot(p, "04_instructions")
        p.click("#start")
        p.wait_for_url("**/task")

    def press_panel(self, expect_text=None, shot_name=None):
        p = self.page
        p.wait_for_selector("#task[data-phase='panel'] #panel-button:visible")
        if expect_text:
            assert expect_text in p.inner_text("#panel-text")
        if shot_name:
            shot(p, shot_name)
        p.click("#panel-button")

    def trial(self, index, action, shot_name=None, limit_s=LIMIT_S):
        """Answer the trial on screen: 'hit', 'miss' or 'timeout'; wait for the reveal."""
        p = self.page
        p.wait_for_selector("#task[data-phase='trial'] #stage img.stim")
        src = p.get_attribute("#stage img.stim", "src")
        sid = src.rsplit("/", 1)[1].split(".")[0]
        self.seen.append(sid)
        if shot_name:
            shot(p, shot_name + "_trial")
        x0, y0, x1, y1 = self.site["rects"][sid]
        if action == "hit":
            x, y = (x0 + x1) // 2, (y0 + y1) // 2
        else:
            x, y = (x1 + 15) % SIZE[0], (y1 + 15) % SIZE[1]
            if x0 <= x < x1 and y0 <= y < y1:
                x, y = 2, 2
        if action != "timeout":
            box = p.locator("#stage img.stim").bounding_box()
            p.mouse.click(box["x"] + (x + 0.5) * box["width"] / SIZE[0], box["y"] + (y + 0.5) * box["height"] / SIZE[1])
        self.clicks[index] = {"sid": sid, "action": action, "x": x, "y": y}
        p.wait_for_selector("#task[data-phase='reveal'] #next:visible", timeout=limit_s * 1000 + 10_000)
        status = p.inner_text("#status")
        assert {"hit": "Found it", "miss": "Not quite", "timeout": "Time is up"}[action] in status, status
        if shot_name:
            shot(p, shot_name + "_reveal")
        p.click("#next")

    def done(self, shots=False):
        self.page.wait_for_url("**/done")
        assert self.page.inner_text("#completion-code") == "C0DE1234"
        if shots:
            shot(self.page, "10_done")


def _db_trials(site, pid):
    from study_site.analysis import load_tables
    from study_site.security import hmac_id

    trials, parts = load_tables(site["app"].extensions["camo_study"].db.engine)
    h = hmac_id(site["app"].extensions["camo_study"].id_key, pid)
    part = parts[parts["pid_hmac"] == h]
    assert len(part) == 1
    return trials[trials["participant"] == part.iloc[0]["participant"]].sort_values("trial_index"), part.iloc[0]


def _check_rows(site, who: Participant, reloaded=()):
    rows, part = _db_trials(site, who.pid)
    n = N_PRACTICE + len(SCENES)
    assert rows["trial_index"].tolist() == list(range(n)) and bool(part["completed"])
    assert rows["practice"].tolist() == [True] * N_PRACTICE + [False] * len(SCENES)
    assert rows["client_trial_id"].is_unique and sorted(rows.loc[~rows.practice, "scene"]) == sorted(SCENES)
    assert rows["stimulus_id"].tolist() == who.seen  # shown in plan order, nothing re-shown
    for r in rows.itertuples():
        c = who.clicks[r.trial_index]
        assert r.stimulus_id == c["sid"]
        if c["action"] == "timeout":
            assert r.timed_out and not r.hit and r.click_x != r.click_x  # NaN
            assert LIMIT_S * 1000 - 50 <= r.rt_ms <= LIMIT_S * 1000 + 1500
        else:
            assert not r.timed_out and r.hit == (c["action"] == "hit")
            assert abs(r.click_x - c["x"]) <= 1 and abs(r.click_y - c["y"]) <= 1
            assert 0 < r.rt_ms < LIMIT_S * 1000
        # displayed at the configured share of the viewport; viewport and device pixel ratio recorded
        assert r.display_h == pytest.approx(0.72 * r.viewport_h, abs=1.0)
        assert r.display_w == pytest.approx(r.display_h * SIZE[0] / SIZE[1], abs=1.5) and r.dpr == 1.0
        assert r.starts == (2 if r.trial_index in reloaded else 1) and not r.late
        assert r.rt_ms <= r.server_rt_ms + 50  # the page's clock never runs ahead of the server's
    return rows


def test_full_session_with_reload_and_leak_scan(site, browser):
    ctx = browser.new_context(viewport={"width": 1280, "height": 800})
    rec = site["rec"]
    t_start = time.monotonic()
    if SHOTS:
        pg = ctx.new_page()
        pg.goto(site["base"] + "/")
        shot(pg, "01_landing")
        pg.close()
    who = Participant(site, ctx, "BROWSER_PID_1")
    who.start(shots=True)
    who.press_panel("Practice first", shot_name="05_task_ready")
    # practice: hit, miss, timeout, hit, hit
    plan = ["hit", "miss", "timeout", "hit", "hit"]
    for i, action in enumerate(plan):
        who.trial(i, action, shot_name={0: "06_practice_hit", 1: "07_practice_miss"}.get(i))
    who.press_panel("Practice complete", shot_name="08_practice_complete")
    who.trial(N_PRACTICE, "hit", shot_name="09_formal")
    # reload in the middle: resumes at the next unanswered trial
    who.page.reload()
    who.press_panel("Welcome back")
    who.trial(N_PRACTICE + 1, "miss")
    who.trial(N_PRACTICE + 2, "hit")
    who.done(shots=True)
    _check_rows(site, who, reloaded=(N_PRACTICE + 1,))  # #next had started that trial before the reload

    # malformed, forged and oversized requests from the participant's browser get 4xx
    codes = who.page.evaluate(
        """async () => {
          const tok = 'x';
          const post = (body, headers) => fetch('/api/trial', {method: 'POST', body,
              headers: Object.assign({'Content-Type': 'application/json'}, headers || {})}).then(r => r.status);
          return [
            await post('{"trial_index": 0', {'X-CSRF-Token': tok}),
            await post(JSON.stringify({trial_index: 0}), {}),
            await post('{"pad": "' + 'x'.repeat(100000) + '"}', {'X-CSRF-Token': tok}),
            await fetch('/api/complete', {method: 'POST'}).then(r => r.status),
            await fetch('/i/../../manifest.json').then(r => r.status),
          ];
        }"""
    )
    assert all(400 <= c < 500 for c in codes), codes
    assert codes[2] == 413

    # a second attempt with the same Prolific id is refused
    again = ctx.browser.new_context().new_page()
    again.goto(f"{site['base']}/?PROLIFIC_PID=BROWSER_PID_1")
    assert "already taken part" in again.inner_text("h1")
    again.context.close()

    # leak scan: nothing the browser received before a click names scene/method/run/object, nor reveals
    # (reveal ids appear first in the /api/trial answer to a click; masks are never served)
    man = site["manifest"]["stimuli"]
    names = {s[k] for s in man for k in ("scene", "method", "run", "object") if not s["practice"]}
    names |= {s["scene"] for s in man if s["practice"]}  # synthetic practice: method "practice" is a UI word
    reveal_ids = {s["reveal_id"] for s in man}
    mask_bytes = {p.read_bytes() for p in (site["stim_dir"] / "masks").glob("*.png")}
    reveal_bytes = {p.read_bytes() for p in (site["stim_dir"] / "reveal").glob("*.png")}
    first_seen: dict[str, str] = {}
    entries = [e for e in rec.log if e[0] >= t_start]
    assert len(entries) > 30
    for _, method, url, status, body in entries:
        text = body.decode("latin-1")
        for name in names:
            assert name not in url and name not in text, (name, url)
        assert b"manifest" not in body and "mask" not in url and "outline" not in url
        assert body not in mask_bytes
        if url.startswith("/i/"):
            assert body not in reveal_bytes
        for rid in reveal_ids:
            if rid in url or rid in text:
                first_seen.setdefault(rid, f"{method} {url}")
    assert first_seen and all(v == "POST /api/trial" for v in first_seen.values()), first_seen
    ctx.close()


def test_two_participants_at_once(site, browser):
    a_ctx = browser.new_context(viewport={"width": 1024, "height": 700})
    b_ctx = browser.new_context(viewport={"width": 1024, "height": 700})
    a = Participant(site, a_ctx, "PAIR_A")
    b = Participant(site, b_ctx, "PAIR_B")
    a.start()
    b.start()
    a.press_panel()
    b.press_panel()
    n = N_PRACTICE + len(SCENES)
    for i in range(n):  # interleaved: both sessions are open and answering at the same time
        if i == N_PRACTICE:
            a.press_panel("Practice complete")
            b.press_panel("Practice complete")
        a.trial(i, "hit" if i % 2 else "miss")
        b.trial(i, "miss" if i % 3 else "hit")
    a.done()
    b.done()
    rows_a = _check_rows(site, a)
    rows_b = _check_rows(site, b)
    assert not set(rows_a.client_trial_id) & set(rows_b.client_trial_id)
    a_ctx.close()
    b_ctx.close()


def test_reload_mid_trial_keeps_the_deadline(slow_site, browser):
    """A reload 2 s into a trial shows the same image with the time that was left: the stored reaction time
    counts from the first showing; a reload after the deadline ends the trial as timed out."""
    site = slow_site
    ctx = browser.new_context(viewport={"width": 1280, "height": 800})
    who = Participant(site, ctx, "RELOADER_1")
    who.start()
    who.press_panel("Practice first")
    p = who.page
    p.wait_for_selector("#task[data-phase='trial'] #stage img.stim")
    first_src = p.get_attribute("#stage img.stim", "src")
    time.sleep(2.0)
    p.reload()
    who.press_panel("continues with the time that was left")
    p.wait_for_selector("#task[data-phase='trial'] #stage img.stim")
    assert p.get_attribute("#stage img.stim", "src") == first_src  # the same image
    # the time bar starts from the remaining share, not from full
    bar = p.evaluate("() => parseFloat(document.getElementById('timer-fill').style.width)")
    assert bar == 0 or bar < 80
    who.seen.append(first_src.rsplit("/", 1)[1].split(".")[0])
    x0, y0, x1, y1 = site["rects"][first_src.rsplit("/", 1)[1].split(".")[0]]
    box = p.locator("#stage img.stim").bounding_box()
    p.mouse.click(box["x"] + ((x0 + x1) / 2 + 0.5) * box["width"] / SIZE[0],
                  box["y"] + ((y0 + y1) / 2 + 0.5) * box["height"] / SIZE[1])
    p.wait_for_selector("#task[data-phase='reveal'] #next:visible")
    assert "Found it" in p.inner_text("#status")
    rows, _ = _db_trials(site, "RELOADER_1")
    r = rows.iloc[0]
    assert r.starts == 2 and r.hit and 2000 <= r.rt_ms <= 6000 and r.server_rt_ms >= 2000
    assert r.rt_ms <= r.server_rt_ms + 50  # the page's clock does not run ahead of the server's
    # next trial (formal): reload and stay away past the 6 s deadline -> stored as a timeout on return
    p.click("#next")
    who.press_panel("Practice complete")
    p.wait_for_selector("#task[data-phase='trial'] #stage img.stim")
    p.goto("about:blank")
    time.sleep(6.5)
    p.goto(site["base"] + "/task")
    who.press_panel("Welcome back")
    p.wait_for_selector("#task[data-phase='reveal'] #next:visible", timeout=10_000)
    assert "Time is up" in p.inner_text("#status")
    rows, _ = _db_trials(site, "RELOADER_1")
    r = rows.iloc[1]
    assert r.timed_out and not r.hit and r.starts == 2 and r.server_rt_ms >= 6000
    ctx.close()


def test_adults_only_in_the_browser(site, browser):
    """The age question is required (the browser will not submit without an answer) and "Under 18" ends the
    participation on the not-eligible page."""
    ctx = browser.new_context(viewport={"width": 1280, "height": 800})
    p = ctx.new_page()
    p.goto(f"{site['base']}/?PROLIFIC_PID=MINOR_1")
    p.wait_for_url("**/consent")
    assert "Adults only" in p.inner_text("#adult-note")
    p.click("#agree")
    p.wait_for_url("**/about-you")
    p.click("#continue")  # nothing chosen: the form is not sent
    assert p.url.endswith("/about-you")
    assert p.evaluate("() => document.querySelector('input[name=age]').validity.valueMissing")
    shot(p, "03b_about_you_required")
    p.check("input[value='under']")
    p.click("#continue")
    p.wait_for_url("**/not-eligible")
    assert "adults aged 18 or older" in p.inner_text("#ineligible")
    shot(p, "11_not_eligible")
    p.goto(f"{site['base']}/task")
    assert p.url.endswith("/not-eligible")
    ctx.close()
