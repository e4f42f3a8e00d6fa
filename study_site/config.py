"""Configuration keys of the study site (``create_app(config)``; env vars ``CAMO_STUDY_<KEY>``)."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Mapping

from camo_base.errors import CamoError, SettingError
from study_site.ranges import ADULT_AGE, CONFIG_RANGES

DEFAULTS: dict[str, Any] = {
    # where things are
    "STIMULI_DIR": None,  # required: output of `camo study build-stimuli`
    "DATABASE_URL": None,  # default: sqlite:///<instance>/study.sqlite
    # secrets
    # signs the session cookie: from the environment or a file, never the database (anyone holding the data could
    # otherwise forge sessions). Required unless DEV.
    "SECRET_KEY": None,
    "SECRET_KEY_FILE": None,  # a file holding the cookie key (`camo study make-key FILE`)
    # key of the HMAC that replaces participant ids: from the environment or a file, never the database
    # (anyone holding the database could otherwise re-identify known ids). Required unless DEV.
    "ID_HMAC_KEY": None,
    "ID_HMAC_KEY_FILE": None,  # a file holding the key (`camo study make-key FILE`)
    "ADMIN_TOKEN": None,  # admin pages and CSV export; disabled (404) when unset
    "ADMIN_TOKEN_FILE": None,  # a file holding the admin token
    "DEV": False,  # development only: an id key and a cookie key generated and kept in the database are allowed
    # protocol
    "TRIAL_TIME_LIMIT_S": 40.0,
    "PRACTICE_TRIALS": 5,
    "HIT_TOLERANCE_PX": 0,  # a click within this many image pixels of the object counts as a hit
    # the deadline lives on the server (issued by POST /api/start when the trial is first shown):
    "DEADLINE_GRACE_S": 2.0,  # network allowance: answers arriving later than limit + grace are timeouts
    "RT_FLOOR_MS": 300.0,  # answers faster on the server's clock are stored but flagged too_fast; excluded
    # network allowance between the page's and the server's clock: a page claiming more time than the server
    # measured (+ this) is refused (400); one claiming less (- this) is stored with clock_mismatch = true and, like
    # every trial, judged and reported on the server's time
    "CLOCK_TOLERANCE_MS": 1000.0,
    # display: the image's height is this share of the viewport's height (capped by DISPLAY_MAX_WIDTH_SHARE
    # of its width); displayed size, viewport and device pixel ratio are stored with every trial
    "DISPLAY_HEIGHT_SHARE": 0.72,
    "DISPLAY_MAX_WIDTH_SHARE": 0.94,
    "MIN_VIEWPORT_W": 800,  # smaller windows are asked to enlarge before a trial starts
    "MIN_VIEWPORT_H": 600,
    "MIN_AGE": 18,  # adults only: participants state their age bracket (required); younger ones cannot take part
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
    "DEADLINE_GRACE_S": float,
    "RT_FLOOR_MS": float,
    "CLOCK_TOLERANCE_MS": float,
    "DISPLAY_HEIGHT_SHARE": float,
    "DISPLAY_MAX_WIDTH_SHARE": float,
    "MIN_VIEWPORT_W": int,
    "MIN_VIEWPORT_H": int,
    "MIN_AGE": int,
}
_BOOLS = {"ALLOW_ANONYMOUS", "SESSION_COOKIE_SECURE", "SESSION_COOKIE_HTTPONLY", "DEV"}

ENV_PREFIX = "CAMO_STUDY_"
#: The about-you answer of someone younger than MIN_AGE: stored, and the participation ends there.
UNDER_MIN_AGE = "under"


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
            if typ is float and not math.isfinite(cfg[key]):
                raise ValueError
        except (TypeError, ValueError, OverflowError):
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
    for key, rng in CONFIG_RANGES.items():
        if key == "MIN_AGE" and isinstance(cfg[key], int) and not rng.contains(cfg[key]):
            raise SettingError(f"{{0}} must be {ADULT_AGE}-99, not {cfg[key]}: the study takes adults only", key)
        if not rng.contains(cfg[key]):
            raise CamoError(f"config {key} must be {rng.describe()}, got {cfg[key]!r}")
    url = cfg.get("COMPLETION_URL")
    if url and not str(url).startswith(("https://", "http://")):
        raise CamoError("config COMPLETION_URL must be an http(s) URL")
    return cfg


def read_secret_file(path: str, what: str, min_len: int = 16) -> str:
    """The stripped contents of a secret file; CamoError (one line) when unreadable or too short."""
    p = Path(path)
    try:
        value = p.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise CamoError(f"{what} file {p}: {getattr(exc, 'strerror', None) or exc}") from None
    if len(value) < min_len:
        raise CamoError(f"{what} file {p}: shorter than {min_len} characters")
    return value


def age_brackets(min_age: int) -> list[tuple[str, str]]:
    """``[(value, label)]`` adult age brackets starting at ``min_age`` (>= 18): up to 24, then decades to 64, 65+.

    The about-you page offers these and ``UNDER_MIN_AGE`` ("Under 18"), which ends the participation.

    >>> age_brackets(18)[:2]
    [('18-24', '18\u201324'), ('25-34', '25\u201334')]
    """
    if min_age < ADULT_AGE:
        raise CamoError(f"age brackets start at {ADULT_AGE} or later (adults only), not {min_age}")
    edges = [e for e in (25, 35, 45, 55, 65) if e > min_age]
    out, lo = [], min_age
    for e in edges:
        out.append((f"{lo}-{e - 1}", f"{lo}\u2013{e - 1}"))
        lo = e
    out.append((f"{lo}+", f"{lo} or older"))
    return out
