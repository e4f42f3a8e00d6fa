"""Admin pages: progress per (scene x method) cell and CSV export, behind ``ADMIN_TOKEN``.

Authenticate with ``Authorization: Bearer <ADMIN_TOKEN>`` (scripts) or the login
form at ``/admin/login`` (browser; marks the session). Without ``ADMIN_TOKEN``
configured every admin URL answers 404. Without credentials an admin URL answers 401 (the login form,
``WWW-Authenticate: Bearer``), with a wrong token 403; never a redirect.
"""

from __future__ import annotations

import hmac
from datetime import timedelta

from flask import Blueprint, Response, abort, current_app, redirect, render_template, request, session, url_for
from sqlalchemy import func, select

from optimizer.assets.conditions import parse_id
from study_site.db import Participant, PlanItem, Trial, utcnow
from study_site.security import check_csrf

bp = Blueprint("admin", __name__, url_prefix="/admin")


def _token() -> str | None:
    return current_app.config.get("ADMIN_TOKEN") or None


def _auth_status() -> int:
    """200 when authenticated; 401 when no credentials were sent; 403 when a wrong token was sent."""
    tok = _token()
    if tok is None:
        abort(404)
    auth = request.headers.get("Authorization", "")
    if auth:
        ok = auth.startswith("Bearer ") and hmac.compare_digest(auth[7:].strip().encode(), tok.encode())
        return 200 if ok else 403
    if session.get("admin") == hmac.new(tok.encode(), b"admin", "sha256").hexdigest():
        return 200
    return 401


def _deny(code: int):
    """401 (login form, ``WWW-Authenticate: Bearer``) or 403; never a redirect."""
    resp = current_app.make_response(
        (render_template("admin_login.html", error=None if code == 401 else "Wrong token."), code)
    )
    if code == 401:
        resp.headers["WWW-Authenticate"] = 'Bearer realm="camo study admin"'
    return resp


@bp.route("/login", methods=["GET", "POST"])
def login():
    tok = _token()
    if tok is None:
        abort(404)
    error = None
    if request.method == "POST":
        check_csrf()
        sent = request.form.get("token", "")
        if hmac.compare_digest(sent.encode(), tok.encode()):
            session["admin"] = hmac.new(tok.encode(), b"admin", "sha256").hexdigest()
            return redirect(url_for("admin.progress"))
        error = "Wrong token."
    return render_template("admin_login.html", error=error), (403 if error else 200)


@bp.get("/")
def progress():
    code = _auth_status()
    if code != 200:
        return _deny(code)
    state = current_app.extensions["camo_study"]
    hold = timedelta(seconds=float(current_app.config["ASSIGNMENT_HOLD_S"]))
    now = utcnow()
    with state.db.read() as s:
        done = dict(
            ((sc, m), n)
            for sc, m, n in s.execute(
                select(Trial.scene, Trial.condition, func.count())
                .join(Participant, Participant.id == Trial.participant_id)
                .where(Trial.practice.is_(False), Participant.completed_at.is_not(None))
                .group_by(Trial.scene, Trial.condition)
            )
        )
        active = dict(
            ((sc, m), n)
            for sc, m, n in s.execute(
                select(PlanItem.scene, PlanItem.condition, func.count())
                .join(Participant, Participant.id == PlanItem.participant_id)
                .where(
                    PlanItem.practice.is_(False),
                    Participant.completed_at.is_(None),
                    Participant.last_seen_at >= now - hold,
                )
                .group_by(PlanItem.scene, PlanItem.condition)
            )
        )
        parts = s.execute(
            select(
                func.count(),
                func.count(Participant.consent_at),
                func.count(Participant.instructions_at),
                func.count(Participant.completed_at),
                func.count(Participant.declined_at),
            )
        ).one()
        n_trials = s.scalar(select(func.count()).select_from(Trial))
    pool = state.stimuli.formal_pool()
    scenes = sorted(pool)
    methods = sorted({m for sc in pool.values() for m in sc}, key=lambda c: parse_id(c).order)
    rows = [
        {
            "scene": sc,
            "cells": [
                (done.get((sc, m), 0), active.get((sc, m), 0)) if m in pool[sc] else None for m in methods
            ],
        }
        for sc in scenes
    ]
    totals = [sum(done.get((sc, m), 0) for sc in scenes) for m in methods]
    return render_template(
        "admin.html",
        rows=rows,
        methods=methods,
        labels=[parse_id(m).label for m in methods],
        totals=totals,
        participants=dict(zip(["started", "consented", "in_task", "completed", "declined"], parts)),
        n_trials=n_trials,
    )


@bp.get("/export/<name>.csv")
def export(name: str):
    code = _auth_status()
    if code != 200:
        abort(code, description="admin token required (Authorization: Bearer TOKEN)" if code == 401 else "wrong admin token")
    if name not in ("trials", "participants"):
        abort(404)
    from study_site.analysis import load_tables

    trials, participants = load_tables(current_app.extensions["camo_study"].db.engine)
    df = trials if name == "trials" else participants
    return Response(
        df.to_csv(index=False),
        mimetype="text/csv",
        headers={"Content-Disposition": f"attachment; filename={name}.csv", "Cache-Control": "no-store"},
    )
