"""Configuration keys of the study site (``create_app(config)``; env vars ``CAMO_STUDY_<KEY>``)."""

from __future__ import annotations

import os
from typing import Any, Mapping

from optimizer.errors import CamoError

DEFAULTS: dict[str, Any] = {
    # where things are
    "STIMULI_DIR": None,  # required: output of `camo study build-stimuli`
    "DATABASE_URL": None,  # default: sqlite:///<instance>/study.sqlite
    # secrets (generated once and kept in the database when not given)
    "SECRET_KEY": None,  # signs the session cookie
    "ID_HMAC_KEY": None,  # key of the HMAC that replaces participant ids; set it in production
    "ADMIN_TOKEN": None,  # admin pages and CSV export; disabled (404) when unset
    # protocol
    "TRIAL_TIME_LIMIT_S": 40.0,
    "PRACTICE_TRIALS": 5,
    "HIT_TOLERANCE_PX": 0,  # a click within this many image pixels of the object counts as a hit
    "ASSIGNMENT_HOLD_S": 3600.0,  # an unfinished participant's cells count as filled for this long
    "ALLOW_ANONYMOUS": True,  # landing page offers "start" without an id (a random id is made)
    # completion
    "COMPLETION_CODE": None,  # study-wide code (Prolific); default: a random code per participant
    "COMPLETION_URL": None,  # e.g. https://app.prolific.com/submissions/complete?cc={code}
    "COMPLETION_REDIRECT_S": None,  # seconds before redirecting to COMPLETION_URL automatically
    # texts
    "STUDY_TITLE": "Find the hidden object",
    "RESEARCHER_CONTACT": None,  # shown on the consent page
    "ESTIMATED_MINUTES": 10,
    "CONSENT_FILE": None,  # plain-text consent statement (paragraphs separated by blank lines)
    # protection
    "MAX_CONTENT_LENGTH": 16 * 1024,
    "MAX_FORM_MEMORY_SIZE": 16 * 1024,
    "RATE_LIMIT_PER_S": 5.0,  # per browser session, API and form POSTs
    "RATE_LIMIT_BURST": 30,
    "NEW_PARTICIPANTS_PER_MIN": 600.0,  # whole server
    "SESSION_COOKIE_SECURE": False,  # set True behind HTTPS
    "SESSION_COOKIE_HTTPONLY": True,
    "SESSION_COOKIE_SAMESITE": "Lax",
    "SESSION_COOKIE_NAME": "camo_study",
    # SQLite
    "SQLITE_BUSY_TIMEOUT_MS": 30000,
    "SQLITE_SYNCHRONOUS": "FULL",
    "DB_POOL_SIZE": 16,
}

_TYPES = {
    "TRIAL_TIME_LIMIT_S": float,
    "PRACTICE_TRIALS": int,
    "HIT_TOLERANCE_PX": int,
    "ASSIGNMENT_HOLD_S": float,
    "ESTIMATED_MINUTES": int,
    "COMPLETION_REDIRECT_S": float,
    "MAX_CONTENT_LENGTH": int,
    "MAX_FORM_MEMORY_SIZE": int,
    "RATE_LIMIT_PER_S": float,
    "RATE_LIMIT_BURST": float,
    "NEW_PARTICIPANTS_PER_MIN": float,
    "SQLITE_BUSY_TIMEOUT_MS": int,
    "DB_POOL_SIZE": int,
}
_BOOLS = {"ALLOW_ANONYMOUS", "SESSION_COOKIE_SECURE", "SESSION_COOKIE_HTTPONLY"}

ENV_PREFIX = "CAMO_STUDY_"


def from_env(environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Config values from ``CAMO_STUDY_<KEY>`` environment variables (typed)."""
    environ = os.environ if environ is None else environ
    out: dict[str, Any] = {}
    for key in DEFAULTS:
        raw = environ.get(ENV_PREFIX + key)
        if raw is None or raw == "":
            continue
        out[key] = raw
    return out


def resolve(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """Defaults overlaid with ``config``; values converted to their types; CamoError on bad values."""
    cfg = dict(DEFAULTS)
    cfg.update(config or {})
    for key, typ in _TYPES.items():
        if cfg.get(key) is None:
            continue
        try:
            cfg[key] = typ(cfg[key])
        except (TypeError, ValueError):
            raise CamoError(f"config {key}: expected a number, got {cfg[key]!r}") from None
    for key in _BOOLS:
        v = cfg.get(key)
        if isinstance(v, str):
            if v.lower() in ("1", "true", "yes", "on"):
                cfg[key] = True
            elif v.lower() in ("0", "false", "no", "off"):
                cfg[key] = False
            else:
                raise CamoError(f"config {key}: expected true/false, got {v!r}")
    if not cfg.get("STIMULI_DIR"):
        raise CamoError("config STIMULI_DIR is required (a directory made by `camo study build-stimuli`)")
    if not 1.0 <= cfg["TRIAL_TIME_LIMIT_S"] <= 600.0:
        raise CamoError("config TRIAL_TIME_LIMIT_S must be between 1 and 600 seconds")
    if not 0 <= cfg["PRACTICE_TRIALS"] <= 50:
        raise CamoError("config PRACTICE_TRIALS must be between 0 and 50")
    url = cfg.get("COMPLETION_URL")
    if url and not str(url).startswith(("https://", "http://")):
        raise CamoError("config COMPLETION_URL must be an http(s) URL")
    return cfg
