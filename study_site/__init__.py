"""Perceptual click-to-find study (GANmouflage protocol, paper Sec. IV-D).

``create_app(config)`` is the Flask application factory (as in Flask's
``flaskr`` tutorial). ``config`` keys are listed in :mod:`study_site.config`;
``STIMULI_DIR`` is required, ``DATABASE_URL`` defaults to a SQLite file in the
instance folder. Pieces: :mod:`.stimuli` (stimulus sets), :mod:`.db` (storage),
:mod:`.assign` (trial plans), :mod:`.views` (participant pages and API),
:mod:`.admin` (progress, export), :mod:`.analysis` (Table I), :mod:`.cli`.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any, Mapping

from camo_base.errors import CamoError

log = logging.getLogger("study_site")


@dataclass
class StudyState:
    """Per-app objects, kept in ``app.extensions['camo_study']``."""

    db: Any
    stimuli: Any
    id_key: str
    limiter: Any
    new_participant_limiter: Any
    consent_paragraphs: list[str]
    assign_lock: Any = field(default_factory=threading.Lock)


def _consent_paragraphs(path: str | None) -> list[str]:
    if not path:
        return []
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CamoError(f"CONSENT_FILE {p}: {exc.strerror}") from None
    return [" ".join(par.split()) for par in text.split("\n\n") if par.strip()]


MISSING_ID_KEY = (
    "ID_HMAC_KEY is not set: make a key file outside the database with `camo study make-key /path/id_hmac.key` "
    "and pass --id-key-file /path/id_hmac.key (or set CAMO_STUDY_ID_HMAC_KEY_FILE); --dev keeps a key in the "
    "database (development only)"
)


MISSING_SECRET_KEY = (
    "SECRET_KEY (the cookie-signing key) is not set: make a key file outside the database with `camo study make-key "
    "/path/cookie.key` and pass --secret-key-file /path/cookie.key (or set CAMO_STUDY_SECRET_KEY_FILE); --dev keeps a "
    "key in the database (development only)"
)


def id_key_of(cfg: Mapping[str, Any], db) -> str:
    """The participant-id HMAC key: configured (env/file), or in DEV mode one kept in the database."""
    if cfg.get("ID_HMAC_KEY"):
        return str(cfg["ID_HMAC_KEY"])
    log.warning("DEV mode: ID_HMAC_KEY not configured; using a key kept in the database (not for real studies)")
    return db.setting("id_hmac_key")


def create_app(config: Mapping[str, Any] | None = None):
    """Build the study app. ``config`` overrides :data:`study_site.config.DEFAULTS`."""
    from flask import Flask, jsonify, render_template, request
    from sqlalchemy.exc import OperationalError
    from werkzeug.exceptions import HTTPException

    from study_site import admin, views
    from study_site.config import age_brackets, read_secret_file, resolve
    from study_site.db import Database
    from study_site.security import RateLimiter, csrf_token
    from study_site.stimuli import StimulusSet

    cfg = resolve(config)
    app = Flask(__name__, instance_relative_config=True)
    if cfg["ADMIN_TOKEN_FILE"] and not cfg["ADMIN_TOKEN"]:
        cfg["ADMIN_TOKEN"] = read_secret_file(cfg["ADMIN_TOKEN_FILE"], "ADMIN_TOKEN")
    if cfg["ID_HMAC_KEY_FILE"] and not cfg["ID_HMAC_KEY"]:
        cfg["ID_HMAC_KEY"] = read_secret_file(cfg["ID_HMAC_KEY_FILE"], "ID_HMAC_KEY", min_len=32)
    if not cfg["ID_HMAC_KEY"] and not cfg["DEV"]:
        raise CamoError(MISSING_ID_KEY)
    if cfg["ID_HMAC_KEY"] and len(str(cfg["ID_HMAC_KEY"])) < 32:
        raise CamoError("ID_HMAC_KEY must be at least 32 characters (`camo study make-key FILE` makes one)")
    if cfg["SECRET_KEY_FILE"] and not cfg["SECRET_KEY"]:
        cfg["SECRET_KEY"] = read_secret_file(cfg["SECRET_KEY_FILE"], "SECRET_KEY", min_len=32)
    if not cfg["SECRET_KEY"] and not cfg["DEV"]:
        raise CamoError(MISSING_SECRET_KEY)
    if cfg["SECRET_KEY"] and len(str(cfg["SECRET_KEY"])) < 32:
        raise CamoError("SECRET_KEY must be at least 32 characters (`camo study make-key FILE` makes one)")
    if cfg["SECRET_KEY"] and cfg["ID_HMAC_KEY"] and str(cfg["SECRET_KEY"]) == str(cfg["ID_HMAC_KEY"]):
        raise CamoError("SECRET_KEY and ID_HMAC_KEY must be different keys (make two with `camo study make-key`)")
    stimuli = StimulusSet(cfg["STIMULI_DIR"])
    if cfg["PRACTICE_TRIALS"] > 0 and not stimuli.practice_pool():
        raise CamoError(
            f"{cfg['STIMULI_DIR']}: the stimulus set has no practice stimuli; rebuild it (build-stimuli makes a "
            "synthetic practice set by default) or set PRACTICE_TRIALS=0"
        )
    url = cfg["DATABASE_URL"]
    if not url:
        Path(app.instance_path).mkdir(parents=True, exist_ok=True)
        url = f"sqlite:///{Path(app.instance_path) / 'study.sqlite'}"
    db = Database(
        url,
        busy_timeout_ms=cfg["SQLITE_BUSY_TIMEOUT_MS"],
        synchronous=cfg["SQLITE_SYNCHRONOUS"],
        pool_size=cfg["DB_POOL_SIZE"],
    )
    cfg["DATABASE_URL"] = url
    if not cfg["SECRET_KEY"]:  # DEV only (refused above otherwise)
        log.warning("DEV mode: SECRET_KEY not configured; using a cookie key kept in the database (not for real studies)")
        cfg["SECRET_KEY"] = db.setting("secret_key")
    id_key = id_key_of(cfg, db)
    db.setting("assign_lock", lambda: "1")
    db.put_setting("clock_tolerance_ms", f"{cfg['CLOCK_TOLERANCE_MS']:g}")  # stated in Table I
    app.config.from_mapping(cfg)
    app.config["PERMANENT_SESSION_LIFETIME"] = timedelta(days=2)
    # a study takes minutes: no new signed cookie on every API call (saves signing + compressing per request)
    app.config["SESSION_REFRESH_EACH_REQUEST"] = False
    app.config["TEMPLATES_AUTO_RELOAD"] = False
    app.extensions["camo_study"] = StudyState(
        db=db,
        stimuli=stimuli,
        id_key=id_key,
        limiter=RateLimiter(cfg["RATE_LIMIT_PER_S"], cfg["RATE_LIMIT_BURST"]),
        new_participant_limiter=RateLimiter(
            cfg["NEW_PARTICIPANTS_PER_MIN"] / 60.0, max(1.0, cfg["NEW_PARTICIPANTS_PER_MIN"])
        ),
        consent_paragraphs=_consent_paragraphs(cfg["CONSENT_FILE"]),
    )
    app.jinja_env.globals["age_brackets"] = age_brackets(cfg["MIN_AGE"])
    # stimulus images: static, immutable, content-hash ETags, before Flask (study_site.serving)
    from study_site.serving import StaticStimuli

    app.wsgi_app = StaticStimuli(app.wsgi_app, stimuli.static_files())
    app.register_blueprint(views.bp)
    app.register_blueprint(admin.bp)
    app.jinja_env.globals["csrf_token"] = csrf_token

    @app.before_request
    def _limits():
        from flask import abort, session

        if request.content_length is not None and request.content_length > app.config["MAX_CONTENT_LENGTH"]:
            abort(413)
        if request.method == "POST" or request.path.startswith("/api/"):
            key = session.get("p") or session.get("csrf") or "no-session"
            if not app.extensions["camo_study"].limiter.allow(str(key)):
                abort(429, description="too many requests; slow down")

    @app.after_request
    def _headers(resp):
        h = resp.headers
        h.setdefault(
            "Content-Security-Policy",
            "default-src 'self'; img-src 'self' blob: data:; script-src 'self'; style-src 'self'; "
            "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'",
        )
        h.setdefault("X-Content-Type-Options", "nosniff")
        h.setdefault("Referrer-Policy", "no-referrer")
        h.setdefault("X-Frame-Options", "DENY")
        if not resp.mimetype.startswith("image/") and not request.path.startswith("/static/"):
            h["Cache-Control"] = "no-store"
        if resp.status_code == 429:
            h.setdefault("Retry-After", "1")
        return resp

    @app.errorhandler(HTTPException)
    def _http_error(e: HTTPException):
        if request.path.startswith(("/api/", "/admin/export")):
            resp = jsonify(error=e.description, status=e.code)
            resp.status_code = e.code or 400
            return resp
        return render_template("error.html", code=e.code, name=e.name, message=e.description), e.code

    @app.errorhandler(OperationalError)
    def _db_unavailable(e: OperationalError):
        # locked/unreachable database: tell the client to retry (the task page does, until acknowledged)
        log.warning("database unavailable on %s %s: %s", request.method, request.path, e.orig)
        if request.path.startswith("/api/"):
            resp = jsonify(error="database busy, retry", status=503)
        else:
            resp = app.make_response(
                (render_template("error.html", code=503, name="Busy", message="Please try again in a moment."), 503)
            )
        resp.status_code = 503
        resp.headers["Retry-After"] = "1"
        return resp

    @app.errorhandler(Exception)
    def _server_error(e: Exception):
        log.exception("unhandled error on %s %s", request.method, request.path)
        if request.path.startswith("/api/"):
            resp = jsonify(error="internal error", status=500)
            resp.status_code = 500
            return resp
        return (
            render_template("error.html", code=500, name="Server error", message="Something went wrong."),
            500,
        )

    return app
