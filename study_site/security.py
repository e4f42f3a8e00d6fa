"""Small security helpers: id hashing, CSRF tokens, rate limiting, input checks."""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import threading
import time

from flask import abort, request, session

ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.@:+-]{0,127}$")
TOKEN_RE = re.compile(r"^[A-Za-z0-9_-]{8,64}$")


def hmac_id(key: str, raw_id: str) -> str:
    """HMAC-SHA256 (hex) of a participant id under the server's id key; the raw id is never stored."""
    return hmac.new(key.encode("utf-8"), raw_id.strip().encode("utf-8"), hashlib.sha256).hexdigest()


def valid_id(raw: str | None) -> bool:
    return raw is not None and bool(ID_RE.match(raw.strip()))


# ---------------------------------------------------------------------------
# CSRF: one random token per browser session, compared in constant time
# ---------------------------------------------------------------------------


def csrf_token() -> str:
    tok = session.get("csrf")
    if not tok:
        tok = secrets.token_urlsafe(24)
        session["csrf"] = tok
    return tok


def check_csrf() -> None:
    """Abort 400 unless the request carries this session's CSRF token (form field or X-CSRF-Token header)."""
    sent = request.headers.get("X-CSRF-Token") or request.form.get("csrf_token") or ""
    tok = session.get("csrf") or ""
    if not tok or not sent or not hmac.compare_digest(str(sent).encode(), tok.encode()):
        abort(400, description="missing or invalid CSRF token; reload the page")


# ---------------------------------------------------------------------------
# rate limiting (in-process token buckets)
# ---------------------------------------------------------------------------


class RateLimiter:
    """Token bucket per key: ``rate`` requests/s sustained, bursts of ``burst``.

    In-process: with several server processes each enforces its own budget.
    """

    def __init__(self, rate: float, burst: float, max_keys: int = 100_000):
        self.rate = float(rate)
        self.burst = float(burst)
        self.max_keys = max_keys
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def allow(self, key: str, now: float | None = None) -> bool:
        if self.rate <= 0:
            return True
        now = time.monotonic() if now is None else now
        with self._lock:
            tokens, last = self._buckets.get(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - last) * self.rate)
            ok = tokens >= 1.0
            if ok:
                tokens -= 1.0
            self._buckets[key] = (tokens, now)
            if len(self._buckets) > self.max_keys:
                self._prune(now)
            return ok

    def _prune(self, now: float) -> None:
        full_after = self.burst / self.rate
        for k, (_, last) in list(self._buckets.items()):
            if now - last > full_after:
                del self._buckets[k]
