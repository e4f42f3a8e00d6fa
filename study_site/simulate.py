"""Simulated participants through the live study site (``camo study simulate``).

Each simulated participant is an HTTP client of the real site (loopback only): the landing link with a
``PROLIFIC_PID`` (``sim-<seed>-<k>``), consent, the age bracket (required), instructions, ``/api/state``, then
every trial -- practice and formal -- as the page runs it: the image is downloaded from its opaque URL, the
simulated observer (:mod:`evaluation.observer`, one simulated search with the participant's own random stream)
decides where and when to click from **the image alone**, ``POST /api/start`` starts the server's clock, the
client waits until the observer's reaction time has passed on that clock, and ``POST /api/trial`` sends the click
(or, when the observer finds nothing within the site's time limit, a timeout once the limit has passed). The
server hit-tests the click against the mask, exactly as for a person. Transport errors, 429 and 5xx answers are
retried with backoff (the stored answer is idempotent), until a global deadline. Then ``POST /api/complete``.

So the whole pipeline (site, database, ``camo study report``, the Table I notebook) is rehearsed with data shaped
like a real study's, and the trial-write latencies it records make it a load generator as well
(``bench/bench_study_load.py`` is the crash/load benchmark with fake searches).

Bounded: at most ``concurrency`` participants at once, a deadline for the whole run, and each participant's
requests retried only until then. The observer's search model runs once per stimulus image (cached; its noise
is drawn per participant and trial).
"""

from __future__ import annotations

import dataclasses
import http.client
import io
import ipaddress
import json
import random
import re
import threading
import time
import urllib.parse
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from camo_base.errors import CamoError, SettingError
from study_site.ranges import SIMULATE_RANGES

CSRF_RE = re.compile(r'name="csrf_token" value="([^"]+)"')
COOKIE = "camo_study"
#: What the simulated browser reports (the site stores it with every trial): a 1280 x 800 window, the image at
#: the site's display share of its height.
VIEWPORT = (1280, 800)


class Deadline(Exception):
    """The run's deadline passed."""


def check_loopback(url: str) -> tuple[str, int]:
    """``(host, port)`` of an ``http://`` URL on the loopback interface; CamoError otherwise."""
    u = urllib.parse.urlsplit(url)
    if u.scheme != "http" or not u.hostname:
        raise SettingError.of("url", f" must be http://127.0.0.1:PORT (loopback), not {url!r}")
    host = u.hostname
    try:
        loop = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loop = False
    if not loop:
        raise SettingError.of("url", f" {url}: simulated participants only go to the loopback interface (127.0.0.1, ::1, "
                        "localhost)")
    try:
        port = u.port or 80
    except ValueError:
        raise SettingError.of("url", f" {url}: bad port") from None
    return host, port


@dataclass
class SimStats:
    lock: threading.Lock = field(default_factory=threading.Lock)
    trial_ms: list[float] = field(default_factory=list)
    start_ms: list[float] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)

    def add(self, key: str, n: int = 1) -> None:
        with self.lock:
            self.counts[key] = self.counts.get(key, 0) + n

    def lat(self, which: str, ms: float) -> None:
        with self.lock:
            (self.trial_ms if which == "trial" else self.start_ms).append(ms)


class ObserverCache:
    """One :class:`evaluation.observer.Cells` per stimulus image (thread-safe; the map is computed once), at the
    display size the site gives that image (:func:`study_site.predict.display_deg`)."""

    def __init__(self, config):
        self.config = config
        self.lock = threading.Lock()
        self.cells: dict[str, Any] = {}
        self.busy: dict[str, threading.Lock] = {}

    def get(self, key: str, png: bytes):
        from PIL import Image

        from evaluation.observer import make_cells

        with self.lock:
            if key in self.cells:
                return self.cells[key]
            lk = self.busy.setdefault(key, threading.Lock())
        with lk:
            with self.lock:
                if key in self.cells:
                    return self.cells[key]
            with Image.open(io.BytesIO(png)) as im:
                img = np.asarray(im.convert("RGB"))
            from study_site.predict import REFERENCE_DEG, display_deg

            deg = display_deg(img.shape[1], img.shape[0]) * self.config.display_deg / REFERENCE_DEG
            c = make_cells(img, dataclasses.replace(self.config, display_deg=deg))
            with self.lock:
                self.cells[key] = c
            return c


class SiteClient:
    """A browser of the study site: its own session cookie, CSRF token and keep-alive connection.

    ``stats.add(key)`` counts what was retried (``http_<status>``, ``transport_errors``); the backoff doubles from
    50 ms up to :attr:`max_backoff_s`, randomised, until ``deadline`` (``time.monotonic()``) raises
    :class:`Deadline`. Used by :class:`Participant` and ``bench/bench_study_load.py``."""

    max_backoff_s = 2.0

    def __init__(self, host: str, port: int, deadline: float, stats):
        self.host, self.port, self.deadline, self.stats = host, port, deadline, stats
        self.conn: http.client.HTTPConnection | None = None
        self.cookie = ""
        self.csrf = ""

    def request(self, method: str, path: str, body=None, headers=None):
        """``(status, body bytes, seconds)`` of the first answer that is not a transport error, 429 or 5xx."""
        delay = 0.05
        while True:
            if time.monotonic() > self.deadline:
                raise Deadline()
            h = {"Cookie": f"{COOKIE}={self.cookie}"} if self.cookie else {}
            h.update(headers or {})
            t0 = time.perf_counter()
            try:
                if self.conn is None:
                    self.conn = http.client.HTTPConnection(self.host, self.port, timeout=30)
                self.conn.request(method, path, body=body, headers=h)
                r = self.conn.getresponse()
                data = r.read()
                for k, v in r.getheaders():
                    if k.lower() == "set-cookie" and v.startswith(COOKIE + "="):
                        self.cookie = v.split(";", 1)[0].split("=", 1)[1]
                if r.status not in (429, 500, 502, 503, 504):
                    return r.status, data, time.perf_counter() - t0
                self.stats.add(f"http_{r.status}")
            except (OSError, http.client.HTTPException):
                self.stats.add("transport_errors")
                if self.conn is not None:
                    self.conn.close()
                self.conn = None
            time.sleep(delay * (1 + random.random()))
            delay = min(delay * 2, self.max_backoff_s)

    def form(self, path: str, fields: dict[str, str]) -> None:
        body = urllib.parse.urlencode(dict(fields, csrf_token=self.csrf))
        st, _, _ = self.request("POST", path, body, {"Content-Type": "application/x-www-form-urlencoded"})
        if st != 302:
            raise RuntimeError(f"POST {path} -> {st}")

    def api(self, path: str, obj: dict) -> tuple[int, dict, float]:
        st, data, dt = self.request("POST", path, json.dumps(obj),
                                    {"Content-Type": "application/json", "X-CSRF-Token": self.csrf})
        try:
            j = json.loads(data) if data[:1] == b"{" else {}
        except ValueError:
            j = {}
        return st, j, dt


class Participant(SiteClient):
    """One simulated participant: the simulated observer searching each stimulus, with its own random stream."""

    def __init__(self, host: str, port: int, pid: str, seed: int, deadline: float, stats: SimStats,
                 cache: ObserverCache):
        super().__init__(host, port, deadline, stats)
        self.pid, self.seed, self.cache = pid, seed, cache
        self.rng = np.random.default_rng(seed)

    def run(self) -> list[dict[str, Any]]:
        """The whole session; returns what the observer did in each trial."""
        q = urllib.parse.urlencode({"PROLIFIC_PID": self.pid, "STUDY_ID": "simulated", "SESSION_ID": f"s-{self.pid}"})
        st, _, _ = self.request("GET", f"/?{q}")
        if st != 302:
            raise RuntimeError(f"landing -> {st}")
        st, page, _ = self.request("GET", "/consent")
        m = CSRF_RE.search(page.decode("utf-8", "replace"))
        if st != 200 or m is None:
            raise RuntimeError(f"consent page -> {st} (this id already took part: the simulation's seed names its "
                               "ids, choose another; or not a camo study site)")
        self.csrf = m.group(1)
        self.form("/consent", {"consent": "yes"})
        ages = ["18-24", "25-34", "35-44", "45-54", "55-64", "65+"]  # required; adults only
        self.form("/about-you", {"age": ages[int(self.rng.integers(len(ages)))]})
        self.form("/instructions", {})
        st, data, _ = self.request("GET", "/api/state")
        if st != 200:
            raise RuntimeError(f"/api/state -> {st}")
        state = json.loads(data)
        limit_s = state["time_limit_ms"] / 1000.0
        cfg = dataclasses.replace(self.cache.config, time_limit_s=limit_s)
        disp_h = VIEWPORT[1] * float(state.get("display", {}).get("height_share", 0.72))
        done = []
        for t in state["trials"]:
            done.append(self.trial(t, cfg, disp_h))
        st, j, _ = self.api("/api/complete", {})
        if st != 200:
            raise RuntimeError(f"complete -> {st} {j}")
        self.stats.add("completed")
        return done

    def trial(self, t: dict, cfg, disp_h: float) -> dict[str, Any]:
        from evaluation.observer import simulate_search

        st, png, _ = self.request("GET", t["src"])
        if st != 200:
            raise RuntimeError(f"image {t['src']} -> {st}")
        cells = self.cache.get(t["src"], png)
        res = simulate_search(None, n=1, seed=int(self.rng.integers(2**62)), config=cfg, cells=cells)
        clicked, rt_s = bool(res.clicked[0]), float(res.rt_s[0])
        st, j, dt = self.api("/api/start", {"trial_index": t["index"]})
        if st != 200:
            raise RuntimeError(f"start {t['index']} -> {st} {j}")
        self.stats.lat("start", dt * 1000)
        shown = time.monotonic() - j["elapsed_ms"] / 1000.0  # the server's clock of this trial
        limit_s = j["time_limit_ms"] / 1000.0
        wait_until = shown + (rt_s if clicked else limit_s + 0.05)
        if wait_until > self.deadline:
            raise Deadline()
        time.sleep(max(0.0, wait_until - time.monotonic()))
        rt_ms = (time.monotonic() - shown) * 1000.0
        scale = disp_h / t["h"]
        body: dict[str, Any] = {"trial_index": t["index"], "client_trial_id": f"sim{self.seed:x}x{t['index']}x"
                                f"{int(self.rng.integers(2**40)):x}", "timed_out": not clicked,
                                "rt_ms": round(rt_ms, 1) if clicked else round(max(rt_ms, limit_s * 1000.0), 1),
                                "display_w": round(t["w"] * scale, 1), "display_h": round(disp_h, 1),
                                "viewport_w": float(VIEWPORT[0]), "viewport_h": float(VIEWPORT[1]), "dpr": 1.0}
        if clicked:
            body.update(x=int(res.click_x[0]), y=int(res.click_y[0]))
        st, j, dt = self.api("/api/trial", body)
        if st != 200 or j.get("stored_client_trial_id") is None:
            raise RuntimeError(f"trial {t['index']} -> {st} {j}")
        self.stats.lat("trial", dt * 1000)
        self.stats.add("trials")
        if j.get("duplicate"):
            self.stats.add("duplicates")
        return {"index": t["index"], "practice": t["practice"], "clicked": clicked, "rt_s": rt_s,
                "hit": bool(j.get("hit")), "timed_out": bool(j.get("timed_out"))}


def _pct(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


def simulate(url: str, participants: int, concurrency: int = 20, seed: int = 0, max_seconds: float = 3600.0,
             observer_config=None, ramp_s: float = 0.0, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Drive ``participants`` simulated participants through the study at ``url`` (loopback). Returns counts,
    latencies (ms) and the observer's per-trial record."""
    from evaluation.observer import ObserverConfig

    host, port = check_loopback(url)
    for name, value in (("participants", participants), ("concurrency", concurrency), ("max_seconds", max_seconds),
                        ("ramp", ramp_s)):
        SIMULATE_RANGES[name].check(value, name)
    cfg = observer_config or ObserverConfig()
    cfg.validate()
    try:
        c = http.client.HTTPConnection(host, port, timeout=5)
        c.request("GET", "/healthz")
        ok = c.getresponse().status == 200
        c.close()
    except OSError as exc:
        raise CamoError(f"{url}: no study site answers ({exc.strerror or exc})") from None
    if not ok:
        raise CamoError(f"{url}: /healthz did not answer 200 (is it a camo study site?)")
    say = log or (lambda s: None)
    stats = SimStats()
    cache = ObserverCache(cfg)
    t0 = time.monotonic()
    deadline = t0 + max_seconds
    records: list[dict[str, Any]] = []
    rec_lock = threading.Lock()

    def one(k: int) -> None:
        time.sleep(ramp_s * k / max(1, participants))
        pid = f"sim-{seed}-{k:05d}"
        p = Participant(host, port, pid, seed * 1_000_003 + k, deadline, stats, cache)
        try:
            out = p.run()
            with rec_lock:
                records.extend({"participant": pid, **r} for r in out)
        except Deadline:
            stats.add("deadline_hit")
        except Exception as exc:  # noqa: BLE001 - recorded, reported, and the others go on
            with stats.lock:
                stats.errors.append(f"{pid}: {str(exc)[:200]}")
        finally:
            if p.conn is not None:
                p.conn.close()
        n = stats.counts.get("completed", 0)
        if n and n % max(1, participants // 10) == 0:
            say(f"{n}/{participants} participants completed ({time.monotonic() - t0:.0f} s)")

    with ThreadPoolExecutor(max_workers=concurrency) as ex:
        list(ex.map(one, range(participants)))
    wall = time.monotonic() - t0
    formal = [r for r in records if not r["practice"]]
    return {
        "participants": participants, "completed": stats.counts.get("completed", 0), "wall_s": round(wall, 1),
        "trials": stats.counts.get("trials", 0), "formal_trials": len(formal),
        "formal_hits": sum(r["hit"] for r in formal), "formal_timeouts": sum(r["timed_out"] for r in formal),
        "trial_write_ms": {"p50": _pct(stats.trial_ms, 50), "p90": _pct(stats.trial_ms, 90),
                           "p99": _pct(stats.trial_ms, 99)},
        "start_ms": {"p50": _pct(stats.start_ms, 50), "p99": _pct(stats.start_ms, 99)},
        "counts": dict(stats.counts), "errors": stats.errors[:10], "n_errors": len(stats.errors),
        "stimuli_seen": len(cache.cells), "records": records,
    }


def parse_observer(text: str | None):
    """``--observer KEY=VALUE,...`` -> an :class:`evaluation.observer.ObserverConfig` (CamoError on bad keys)."""
    from evaluation.observer import ObserverConfig

    if not text:
        return ObserverConfig()
    fields = {f.name: f for f in dataclasses.fields(ObserverConfig)}
    kw: dict[str, Any] = {}
    for item in text.split(","):
        if not item.strip():
            continue
        if "=" not in item:
            raise SettingError.of("observer", f" expects KEY=VALUE,..., not {item!r}")
        k, v = (x.strip() for x in item.split("=", 1))
        tuples = ("centre_sigmas_deg", "object_deg")
        if k not in fields or k in tuples:
            known = ", ".join(n for n in fields if n not in tuples)
            raise SettingError.of("observer", f": unknown key {k!r}; known: {known}")
        if isinstance(fields[k].default, str):  # start, saliency_model, shadow_*, surround, decision
            kw[k] = v
            continue
        try:
            kw[k] = float(v)
        except ValueError:
            raise SettingError.of("observer", f" {k}: not a number: {v!r}") from None
    cfg = ObserverConfig(**kw)
    cfg.validate()
    return cfg
