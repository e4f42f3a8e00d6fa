"""Participant pages and the trial API.

Flow: landing (Prolific PROLIFIC_PID/STUDY_ID/SESSION_ID or ?id=, or a form) ->
consent -> about you (age bracket, required: adults only; "under MIN_AGE" ends at /not-eligible) -> instructions -> task (practice,
then formal trials; JS) -> done (completion code / redirect).

Nothing sent before a click names the scene, method, mask or outline: the task
page gets opaque image URLs (``/i/<id>.webp``, static: :mod:`study_site.serving`); ``POST /api/trial`` hit-tests the
click against the mask on the server and only its response carries the reveal
URL (``/r/<rid>``), which is served only once that trial is stored.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import secrets
from pathlib import Path

from flask import (
    Blueprint,
    abort,
    current_app,
    jsonify,
    redirect,
    render_template,
    request,
    send_file,
    session,
    url_for,
)
from sqlalchemy import bindparam, func, select, update
from sqlalchemy.exc import IntegrityError

from study_site.assign import create_plan
from study_site.config import UNDER_MIN_AGE, age_brackets
from study_site.db import SHOWN_COLUMNS, Participant, PlanItem, Trial, lock_for_assignment, utcnow
from study_site.security import TOKEN_RE, check_csrf, hmac_id, valid_id

bp = Blueprint("study", __name__)

STAGE_ENDPOINT = {
    "consent": "study.consent",
    "declined": "study.declined",
    "ineligible": "study.ineligible",
    "about": "study.about",
    "instructions": "study.instructions",
    "task": "study.task",
    "done": "study.done",
}
STEPS = [("consent", "Consent"), ("about", "About you"), ("instructions", "Instructions"), ("task", "Task")]


def st():
    return current_app.extensions["camo_study"]


def _cfg(key):
    return current_app.config[key]


# ---------------------------------------------------------------------------
# participant helpers
# ---------------------------------------------------------------------------


def stage_of(p: Participant) -> str:
    if p.completed_at is not None:
        return "done"
    if p.age_bracket == UNDER_MIN_AGE:
        return "ineligible"
    if p.consent_at is None:
        return "declined" if p.declined_at is not None else "consent"
    if p.demographics_at is None:
        return "about"
    if p.instructions_at is None:
        return "instructions"
    return "task"


def session_token() -> str | None:
    tok = session.get("p")
    return tok if isinstance(tok, str) and TOKEN_RE.match(tok) else None


def current_participant(s) -> Participant | None:
    tok = session_token()
    if tok is None:
        return None
    return s.scalar(select(Participant).where(Participant.token == tok))


def load_participant() -> Participant | None:
    with st().db.read() as s:
        return current_participant(s)


def require_stage(expected: str):
    """(participant, None) when the participant is at ``expected``, else (p, redirect response)."""
    p = load_participant()
    if p is None:
        return None, redirect(url_for("study.landing"))
    stage = stage_of(p)
    if stage != expected:
        return p, redirect(url_for(STAGE_ENDPOINT[stage]))
    return p, None


def _step_context(current: str) -> dict:
    return {"steps": STEPS, "current_step": current}


# ---------------------------------------------------------------------------
# landing
# ---------------------------------------------------------------------------


@bp.get("/")
def landing():
    args = request.args
    raw, source = args.get("PROLIFIC_PID"), "prolific"
    if raw is None:
        raw, source = (args.get("id") or args.get("participant_id")), "generic"
    if raw is not None:
        if not valid_id(raw):
            abort(400, description="The participant id in this link is not valid. Please check the link.")
        study_id = args.get("STUDY_ID")
        sess_id = args.get("SESSION_ID")
        for v in (study_id, sess_id):
            if v is not None and not valid_id(v):
                abort(400, description="The study link is not valid. Please check the link.")
        return _enter(raw.strip(), source, study_id, sess_id)
    p = load_participant()
    if p is not None:
        return redirect(url_for(STAGE_ENDPOINT[stage_of(p)]))
    return render_template("landing.html", error=None)


@bp.post("/")
def landing_post():
    check_csrf()
    raw = (request.form.get("participant_id") or "").strip()
    if not raw:
        if not _cfg("ALLOW_ANONYMOUS"):
            return render_template("landing.html", error="Please enter your participant ID."), 400
        return _enter(secrets.token_urlsafe(16), "anonymous", None, None)
    if not valid_id(raw):
        return (
            render_template(
                "landing.html",
                error="That ID is not valid: use up to 128 letters, digits or . _ - @ : + characters.",
            ),
            400,
        )
    return _enter(raw, "generic", None, None)


def _enter(raw_id: str, source: str, study_id: str | None, sess_id: str | None):
    state = st()
    key = state.id_key
    h = hmac_id(key, raw_id)
    now = utcnow()
    for _attempt in range(3):
        try:
            with state.db.write() as s, s.begin():
                p = s.scalar(select(Participant).where(Participant.pid_hmac == h))
                if p is None:
                    if not state.new_participant_limiter.allow("all"):
                        abort(429, description="Too many new participants right now; please try again in a minute.")
                    p = Participant(
                        token=secrets.token_urlsafe(24),
                        pid_hmac=h,
                        id_source=source,
                        study_id=study_id,
                        session_hmac=hmac_id(key, sess_id) if sess_id else None,
                        seed=secrets.randbits(48),
                        time_limit_s=float(_cfg("TRIAL_TIME_LIMIT_S")),
                        created_at=now,
                        last_seen_at=now,
                    )
                    s.add(p)
                else:
                    if p.consent_at is None and p.declined_at is not None:
                        p.declined_at = None  # came back: ask for consent again
                    p.last_seen_at = now
                token, completed = p.token, p.completed_at is not None
            break
        except IntegrityError:  # the same id arrived twice at once (other process); read it again
            continue
    else:
        abort(409, description="Please reload the page.")
    csrf = session.get("csrf")
    session.clear()
    if csrf:
        session["csrf"] = csrf
    session.permanent = True
    session["p"] = token
    if completed:
        session["returning"] = True
        return redirect(url_for("study.done"))
    return redirect(url_for("study.consent"))  # require_stage sends them on to where they were


# ---------------------------------------------------------------------------
# consent, demographics, instructions
# ---------------------------------------------------------------------------


@bp.route("/consent", methods=["GET", "POST"])
def consent():
    p, r = require_stage("consent")
    if r is not None:
        return r
    if request.method == "POST":
        check_csrf()
        answer = request.form.get("consent")
        if answer not in ("yes", "no"):
            abort(400, description="Please choose whether you agree to take part.")
        with st().db.write() as s, s.begin():
            q = s.get(Participant, p.id)
            if answer == "yes":
                q.consent_at = utcnow()
            else:
                q.declined_at = utcnow()
        return redirect(url_for("study.about" if answer == "yes" else "study.declined"))
    return render_template("consent.html", paragraphs=st().consent_paragraphs, **_step_context("consent"))


@bp.get("/declined")
def declined():
    p, r = require_stage("declined")
    if r is not None:
        return r
    return render_template("declined.html")


@bp.route("/about-you", methods=["GET", "POST"])
def about():
    p, r = require_stage("about")
    if r is not None:
        return r
    min_age = int(_cfg("MIN_AGE"))
    if request.method == "POST":
        check_csrf()
        age = request.form.get("age") or None
        if age is None:  # required: the study takes adults only
            return render_template("about.html", brackets=age_brackets(min_age), min_age=min_age,
                                   error="Please choose your age bracket.", **_step_context("about")), 400
        if age != UNDER_MIN_AGE and age not in dict(age_brackets(min_age)):
            abort(400, description="Unknown age bracket.")
        with st().db.write() as s, s.begin():
            q = s.get(Participant, p.id)
            q.age_bracket = age
            q.demographics_at = utcnow()
        return redirect(url_for("study.ineligible" if age == UNDER_MIN_AGE else "study.instructions"))
    return render_template("about.html", brackets=age_brackets(min_age), min_age=min_age, error=None,
                           **_step_context("about"))


@bp.get("/not-eligible")
def ineligible():
    p, r = require_stage("ineligible")
    if r is not None:
        return r
    return render_template("ineligible.html", min_age=int(_cfg("MIN_AGE")))


@bp.route("/instructions", methods=["GET", "POST"])
def instructions():
    p, r = require_stage("instructions")
    if r is not None:
        return r
    state = st()
    n_formal = len(state.stimuli.formal_pool())
    if request.method == "POST":
        check_csrf()
        now = utcnow()
        with state.assign_lock, state.db.write() as s, s.begin():
            lock_for_assignment(s)
            q = s.get(Participant, p.id)
            if q.instructions_at is None:
                has_plan = s.scalar(select(func.count()).where(PlanItem.participant_id == q.id))
                if not has_plan:
                    create_plan(s, q, state.stimuli, int(_cfg("PRACTICE_TRIALS")), float(_cfg("ASSIGNMENT_HOLD_S")), now)
                q.instructions_at = now
                q.last_seen_at = now
        return redirect(url_for("study.task"))
    return render_template(
        "instructions.html",
        n_practice=int(_cfg("PRACTICE_TRIALS")),
        n_formal=n_formal,
        limit_s=_fmt_seconds(p.time_limit_s),
        **_step_context("instructions"),
    )


def _fmt_seconds(x: float) -> str:
    return f"{x:g}"


# ---------------------------------------------------------------------------
# task page and API
# ---------------------------------------------------------------------------


@bp.get("/task")
def task():
    p, r = require_stage("task")
    if r is not None:
        return r
    return render_template("task.html", **_step_context("task"))


def _api_participant(s) -> Participant:
    """The session's participant (ORM), or abort 401 / 409 like :func:`_api_row`."""
    return _api_row(current_participant(s))


@bp.get("/api/state")
def api_state():
    with st().db.read() as s:
        p = _api_participant(s)
        plan = s.scalars(select(PlanItem).where(PlanItem.participant_id == p.id).order_by(PlanItem.idx)).all()
        answered = set(s.scalars(select(Trial.trial_index).where(Trial.participant_id == p.id)))
    n_practice = sum(1 for it in plan if it.practice)
    nxt = next((it.idx for it in plan if it.idx not in answered), len(plan))
    return jsonify(
        key=hashlib.sha256(p.token.encode()).hexdigest()[:16],
        total=len(plan),
        practice=n_practice,
        time_limit_ms=int(round(p.time_limit_s * 1000)),
        next=nxt,
        display={
            "height_share": float(_cfg("DISPLAY_HEIGHT_SHARE")),
            "max_width_share": float(_cfg("DISPLAY_MAX_WIDTH_SHARE")),
            "min_viewport_w": int(_cfg("MIN_VIEWPORT_W")),
            "min_viewport_h": int(_cfg("MIN_VIEWPORT_H")),
        },
        trials=[
            {
                "index": it.idx,
                "practice": it.practice,
                **_image_urls(it.stimulus_id),
                "w": it.width,
                "h": it.height,
                "started": it.started_at is not None,
            }
            for it in plan
            if it.idx not in answered
        ],
    )


def _image_urls(sid: str) -> dict[str, str]:
    """``src`` (lossless WebP) and ``fallback`` (PNG) of a stimulus, served statically (:mod:`study_site.serving`)."""
    stim = st().stimuli.by_id.get(sid)
    webp, png = st().stimuli.image_names(stim) if stim is not None else (f"{sid}.png", f"{sid}.png")
    return {"src": f"{request.script_root}/i/{webp}", "fallback": f"{request.script_root}/i/{png}"}


# ---------------------------------------------------------------------------
# the hot paths (/api/start, /api/trial): prebuilt Core statements, one read and one short write each.
# Profiled (docs/study.md): building ORM statements per request (coercion, cache keys) cost more CPU than the
# database; a prebuilt statement memoises its cache key, and one joined read replaces four ORM queries.
# ---------------------------------------------------------------------------

_P, _I, _T = Participant.__table__, PlanItem.__table__, Trial.__table__
_STAGE_COLS = (_P.c.id, _P.c.time_limit_s, _P.c.last_seen_at, _P.c.completed_at, _P.c.consent_at, _P.c.declined_at,
               _P.c.demographics_at, _P.c.instructions_at, _P.c.age_bracket)
_N_DONE = select(func.count()).select_from(_T).where(_T.c.participant_id == _P.c.id).scalar_subquery()
#: /api/start: the participant (stage fields), whether the trial exists, how many trials are answered
START_READ = (
    select(*_STAGE_COLS, _N_DONE.label("n_done"), _I.c.idx.label("item_idx"))
    .select_from(_P.outerjoin(_I, (_I.c.participant_id == _P.c.id) & (_I.c.idx == bindparam("idx"))))
    .where(_P.c.token == bindparam("token"))
)
#: /api/start: the first start wins, later ones only count
START_WRITE = (
    update(_I)
    .where(_I.c.participant_id == bindparam("b_pid"), _I.c.idx == bindparam("b_idx"))
    .values(started_at=func.coalesce(_I.c.started_at, bindparam("b_now")), starts=func.coalesce(_I.c.starts, 0) + 1)
    .returning(_I.c.started_at, _I.c.starts)
)
_ITEM_COLS = [_I.c.started_at, _I.c.starts, _I.c.width, _I.c.height, _I.c.reveal_id, _I.c.idx.label("item_idx")] + [
    _I.c[c] for c in SHOWN_COLUMNS]
_TRIAL_COLS = ("id", "client_trial_id", "trial_index", "hit", "timed_out", "late", "too_fast", "clock_mismatch")
_I2 = _I.alias("i2")
_TOTAL = select(func.count()).select_from(_I2).where(_I2.c.participant_id == _P.c.id).scalar_subquery()
#: /api/trial: the participant, the plan item, the plan's length and a stored answer to this trial (if any)
TRIAL_READ = (
    select(*_STAGE_COLS, *_ITEM_COLS, _TOTAL.label("total"), *[_T.c[c].label(f"t_{c}") for c in _TRIAL_COLS])
    .select_from(
        _P.outerjoin(_I, (_I.c.participant_id == _P.c.id) & (_I.c.idx == bindparam("idx")))
        .outerjoin(_T, (_T.c.participant_id == _P.c.id) & (_T.c.trial_index == bindparam("idx")))
    )
    .where(_P.c.token == bindparam("token"))
)
TRIAL_COUNT = select(func.count()).select_from(_T).where(_T.c.participant_id == bindparam("pid"))
TRIAL_STORED = select(*[_T.c[c] for c in _TRIAL_COLS]).where(
    _T.c.participant_id == bindparam("pid"), _T.c.trial_index == bindparam("idx"))
TOUCH = update(_P).where(_P.c.id == bindparam("b_pid")).values(last_seen_at=bindparam("b_now"))
#: a participant's last_seen_at (what holds their cells, ASSIGNMENT_HOLD_S) is refreshed at most this often
TOUCH_EVERY_S = 60.0


def _api_row(row):
    """The participant (a row or an ORM object) of an API call, or abort 401 (no session) / 409 (not in the task)."""
    if row is None:
        abort(401, description="no study session; open the study link again")
    stage = stage_of(row)
    if stage != "task":
        resp = jsonify(error=f"not in the task ({stage})", redirect=url_for(STAGE_ENDPOINT[stage]))
        resp.status_code = 409
        abort(resp)
    return row


def _elapsed_ms(started_at, now) -> float:
    return max(0.0, (now - started_at).total_seconds() * 1000.0)


@bp.post("/api/start")
def api_start():
    """The trial's image is about to be shown: start its server-side clock (once; a reload keeps it).

    Answer: ``elapsed_ms`` since the first start and ``remaining_ms`` of the time limit (0: the trial is
    over; the page then sends a timeout).
    """
    check_csrf()
    body = _json_body()
    if not isinstance(body, dict) or set(body) - {"trial_index"}:
        abort(400, description="expected {\"trial_index\": N}")
    idx = body.get("trial_index")
    if isinstance(idx, bool) or not isinstance(idx, int) or not 0 <= idx < 10_000:
        abort(400, description="trial_index must be a small non-negative integer")
    state = st()
    tok = session_token()
    if tok is None:
        abort(401, description="no study session; open the study link again")
    with state.db.read_conn() as c:  # checks outside the (on SQLite: serialised) write
        p = _api_row(c.execute(START_READ, {"token": tok, "idx": idx}).first())
    if p.item_idx is None:
        abort(400, description="no such trial")
    if idx != p.n_done:
        abort(409, description=f"trial {idx} is not the next one (next is {p.n_done})")
    limit_s = p.time_limit_s
    now = utcnow()
    with state.db.write_conn(light=True) as c:  # one statement
        started_at, starts = c.execute(START_WRITE, {"b_pid": p.id, "b_idx": idx, "b_now": now}).one()
    elapsed = _elapsed_ms(started_at, now)
    limit_ms = limit_s * 1000.0
    return jsonify(
        ok=True,
        trial_index=idx,
        starts=starts,
        time_limit_ms=int(round(limit_ms)),
        elapsed_ms=round(elapsed, 1),
        remaining_ms=round(max(0.0, limit_ms - elapsed), 1),
    )


MAX_ABS_NUMBER = 1e12  # larger JSON numbers are rejected before any arithmetic (no OverflowError)


def _num(body: dict, key: str, required: bool = True, lo: float = -math.inf, hi: float = math.inf):
    v = body.get(key)
    if v is None:
        if required:
            abort(400, description=f"{key} is required")
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        abort(400, description=f"{key} must be a finite number")
    if isinstance(v, int):
        if not -MAX_ABS_NUMBER <= v <= MAX_ABS_NUMBER:  # exact integer comparison: 10**400 never becomes a float
            abort(400, description=f"{key} is out of range")
        v = float(v)
    if not math.isfinite(v):
        abort(400, description=f"{key} must be a finite number")
    if not lo <= v <= hi:
        abort(400, description=f"{key} is out of range")
    return v


def _json_body():
    """The request's JSON body, or abort 400 (bad JSON, deep nesting) / 413 (over MAX_CONTENT_LENGTH)."""
    raw = request.get_data(cache=False)
    try:
        return json.loads(raw)
    except (ValueError, UnicodeDecodeError, RecursionError):
        abort(400, description="body is not valid JSON")


TRIAL_FIELDS = {
    "trial_index", "client_trial_id", "timed_out", "x", "y", "rt_ms", "display_w", "display_h",
    "viewport_w", "viewport_h", "dpr",
}


def _parse_trial(body) -> dict:
    if not isinstance(body, dict):
        abort(400, description="expected a JSON object")
    unknown = set(body) - TRIAL_FIELDS
    if unknown:
        abort(400, description=f"unknown fields: {', '.join(sorted(map(str, unknown)))[:200]}")
    idx = body.get("trial_index")
    if isinstance(idx, bool) or not isinstance(idx, int) or not 0 <= idx < 10_000:
        abort(400, description="trial_index must be a small non-negative integer")
    cid = body.get("client_trial_id")
    if not isinstance(cid, str) or not TOKEN_RE.match(cid):
        abort(400, description="client_trial_id must be 8-64 characters [A-Za-z0-9_-]")
    timed_out = body.get("timed_out")
    if not isinstance(timed_out, bool):
        abort(400, description="timed_out must be true or false")
    out = {
        "trial_index": idx,
        "client_trial_id": cid,
        "timed_out": timed_out,
        "rt_ms": _num(body, "rt_ms", True, 0.0, 3_600_000.0),
        "display_w": _num(body, "display_w", False, 0.0, 100_000.0),
        "display_h": _num(body, "display_h", False, 0.0, 100_000.0),
        "viewport_w": _num(body, "viewport_w", False, 0.0, 100_000.0),
        "viewport_h": _num(body, "viewport_h", False, 0.0, 100_000.0),
        "dpr": _num(body, "dpr", False, 0.05, 20.0),
        "x": None,
        "y": None,
    }
    if not timed_out:
        out["x"] = _num(body, "x", True, 0.0, 1e6)
        out["y"] = _num(body, "y", True, 0.0, 1e6)
    elif body.get("x") is not None or body.get("y") is not None:
        abort(400, description="a timed-out trial has no click position")
    return out


def _trial_answer(stored: dict, reveal_id: str, total: int, ack: str, duplicate: bool):
    return jsonify(
        ok=True,
        ack=ack,
        stored_client_trial_id=stored["client_trial_id"],
        duplicate=duplicate,
        trial_index=stored["trial_index"],
        hit=bool(stored["hit"]),
        timed_out=bool(stored["timed_out"]),
        late=bool(stored["late"]),
        too_fast=bool(stored["too_fast"]),
        clock_mismatch=bool(stored["clock_mismatch"]),
        reveal=url_for("study.reveal", rid=reveal_id),
        next=stored["trial_index"] + 1,
        done=stored["trial_index"] + 1 >= total,
    )


@bp.post("/api/trial")
def api_trial():
    """Store one answer, judged on the server's clock of that trial (``server_rt_ms``: from the arrival of the
    trial's first ``/api/start`` to the arrival of this answer; it includes one network round trip and the
    page's two paint frames, so it is at least the page's honest ``rt_ms``).

    * a retry of a stored trial returns the stored answer (idempotent; no re-judging);
    * the trial must have been started (``/api/start``), else 409;
    * ``rt_ms`` may not exceed the server's time by more than ``CLOCK_TOLERANCE_MS`` (400: impossible);
    * ``rt_ms`` more than ``CLOCK_TOLERANCE_MS`` *below* the server's time is stored with
      ``clock_mismatch = true``; the trial is judged and reported on the server's time like any other;
    * a timeout before the time limit (page or server clock) is 400;
    * a click after the limit (``rt_ms`` > limit, or arriving after limit + ``DEADLINE_GRACE_S`` on the
      server) is stored as a timeout with ``late = true`` (not a hit, whatever it clicked);
    * a server time below ``RT_FLOOR_MS`` is stored with ``too_fast = true`` (the analysis excludes it).
    """
    check_csrf()
    data = _parse_trial(_json_body())
    state = st()
    idx = data["trial_index"]
    now = utcnow()
    tok = session_token()
    if tok is None:
        abort(401, description="no study session; open the study link again")
    with state.db.read_conn() as c:
        row = _api_row(c.execute(TRIAL_READ, {"token": tok, "idx": idx}).first())
    if row.item_idx is None:
        abort(400, description="no such trial")
    if row.t_id is not None:  # a retry (lost acknowledgement) or a second answer: the first one stands
        stored = {c: getattr(row, f"t_{c}") for c in _TRIAL_COLS}
        return _trial_answer(stored, row.reveal_id, row.total, data["client_trial_id"], True)
    if row.started_at is None:
        abort(409, description="trial not started (POST /api/start first)")
    limit_ms = row.time_limit_s * 1000.0
    server_ms = _elapsed_ms(row.started_at, now)
    rt = data["rt_ms"]
    tol = float(_cfg("CLOCK_TOLERANCE_MS"))
    if rt > server_ms + tol:
        abort(400, description="rt_ms exceeds the time since the trial started")
    clock_mismatch = rt < server_ms - tol
    late = False
    if data["timed_out"]:
        if rt < limit_ms - tol or server_ms < limit_ms - tol:
            abort(400, description="a timeout before the time limit")
    elif rt > limit_ms or server_ms > limit_ms + 1000.0 * float(_cfg("DEADLINE_GRACE_S")):
        late = True
    x = y = None
    hit = False
    if not data["timed_out"]:
        x, y = int(data["x"]), int(data["y"])
        if x >= row.width or y >= row.height:
            abort(400, description="click position outside the image")
        if not late:
            stim = state.stimuli.by_id.get(row.stimulus_id)
            if stim is None:
                abort(409, description="stimulus set changed since this session started")
            hit = state.stimuli.hit(stim, x, y, int(_cfg("HIT_TOLERANCE_PX")))
    too_fast = (not data["timed_out"]) and server_ms < float(_cfg("RT_FLOOR_MS"))
    values = dict(
        participant_id=row.id,
        trial_index=idx,
        client_trial_id=data["client_trial_id"],
        **{c: getattr(row, c) for c in SHOWN_COLUMNS},
        hit=hit,
        timed_out=data["timed_out"] or late,
        click_x=x,
        click_y=y,
        rt_ms=rt,
        time_limit_s=row.time_limit_s,
        display_w=data["display_w"],
        display_h=data["display_h"],
        viewport_w=data["viewport_w"],
        viewport_h=data["viewport_h"],
        dpr=data["dpr"],
        server_received_at=now,
        server_rt_ms=server_ms,
        late=late,
        too_fast=too_fast,
        clock_mismatch=clock_mismatch,
        starts=int(row.starts or 1),
    )
    touch = row.last_seen_at is None or (now - row.last_seen_at).total_seconds() > TOUCH_EVERY_S
    # the write holds SQLite's writer lock: as few statements as possible (count, insert, at most one update)
    with state.db.write_conn() as c:
        n_done = c.execute(TRIAL_COUNT, {"pid": row.id}).scalar()
        inserted = False
        if idx == n_done:
            inserted = state.db.insert_ignore_conn(c, Trial, values)
        elif idx > n_done:
            abort(409, description=f"trial {idx} answered out of order (next is {n_done})")
        if inserted:
            if touch:
                c.execute(TOUCH, {"b_pid": row.id, "b_now": now})
            stored = {k: values.get(k) for k in _TRIAL_COLS}
        else:  # answered meanwhile (another tab or a retry racing this one), or client_trial_id reused
            r = c.execute(TRIAL_STORED, {"pid": row.id, "idx": idx}).first()
            if r is None:
                abort(409, description="client_trial_id already used for another trial")
            stored = r._asdict()
    return _trial_answer(stored, row.reveal_id, row.total, data["client_trial_id"], not inserted)


@bp.post("/api/complete")
def api_complete():
    check_csrf()
    state = st()
    with state.db.write() as s, s.begin():
        p = current_participant(s)
        if p is None:
            abort(401, description="no study session; open the study link again")
        if p.completed_at is None:
            if stage_of(p) != "task":
                abort(409, description="not in the task")
            n_plan = s.scalar(select(func.count()).where(PlanItem.participant_id == p.id))
            n_done = s.scalar(select(func.count()).where(Trial.participant_id == p.id))
            if n_plan == 0 or n_done < n_plan:
                resp = jsonify(error="some trials are not stored yet", stored=n_done, total=n_plan)
                resp.status_code = 409
                abort(resp)
            p.completed_at = utcnow()
            p.completion_code = _cfg("COMPLETION_CODE") or secrets.token_hex(4).upper()
    return jsonify(ok=True, redirect=url_for("study.done"))


@bp.get("/r/<rid>")
def reveal(rid: str):
    if not TOKEN_RE.match(rid):
        abort(404)
    with st().db.read() as s:
        p = current_participant(s)
        if p is None:
            abort(404)
        answered = s.scalar(
            select(func.count())
            .select_from(PlanItem)
            .join(Trial, (Trial.participant_id == PlanItem.participant_id) & (Trial.trial_index == PlanItem.idx))
            .where(PlanItem.participant_id == p.id, PlanItem.reveal_id == rid)
        )
    stim = st().stimuli.by_reveal.get(rid)
    if not answered or stim is None:
        abort(404)
    # WebP to browsers that take it (Vary: Accept), else PNG; a content-hash ETag and no Last-Modified
    webp = st().stimuli.reveal_path(stim, ".webp")
    path = webp if "image/webp" in request.headers.get("Accept", "") and webp.is_file() else \
        st().stimuli.reveal_path(stim)
    f = _reveal_file(str(path))
    resp = send_file(f.path, mimetype=f.mimetype, etag=False, last_modified=None, conditional=False)
    resp.headers.pop("Last-Modified", None)
    resp.set_etag(f.etag.strip('"'))
    resp.cache_control.private = True
    resp.cache_control.max_age = 3600
    resp.vary.add("Accept")
    return resp.make_conditional(request)


@functools.lru_cache(maxsize=4096)
def _reveal_file(path: str):
    from study_site.serving import static_file

    return static_file(Path(path))


# ---------------------------------------------------------------------------
# completion
# ---------------------------------------------------------------------------


@bp.get("/done")
def done():
    p = load_participant()
    if p is None:
        return redirect(url_for("study.landing"))
    if p.completed_at is None:
        return redirect(url_for(STAGE_ENDPOINT[stage_of(p)]))
    returning = bool(session.pop("returning", False))
    url = _cfg("COMPLETION_URL")
    link = url.replace("{code}", p.completion_code or "") if url else None
    return render_template(
        "done.html",
        code=p.completion_code,
        link=link,
        redirect_s=_cfg("COMPLETION_REDIRECT_S") if link else None,
        returning=returning,
    )


@bp.get("/healthz")
def healthz():
    return jsonify(ok=True, time=utcnow().isoformat(timespec="seconds"))
