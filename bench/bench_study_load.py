"""Load and crash benchmark of the study site (loopback only, bounded, stops by itself).

1. Builds a small fake stimulus set, starts ``camo study serve`` (waitress when installed,
   else werkzeug threaded) in a subprocess on 127.0.0.1 with a SQLite database, or with
   ``--db postgres`` a throw-away PostgreSQL cluster (initdb + pg_ctl in a temporary folder,
   unix socket, PostgreSQL's durable defaults: fsync and synchronous_commit on).
2. Load phase: N concurrent simulated participants (threads + http.client) run full sessions
   (landing, consent, about, instructions, state, image preload, every trial, completion).
   Each trial is ``POST /api/start`` (the server's clock), a search of ``--think`` seconds
   (a timeout at ``--trial-limit``), then ``POST /api/trial``. Prints p50/p90/p99 latency of
   trial writes (and of starts) and lost / duplicated trial counts; each client also re-sends
   one acknowledged trial (same and new client id) to exercise idempotency.
3. Crash phase: another N participants; when ~35% of their trials are acknowledged the server
   is killed with SIGKILL and restarted on the same database and port; clients retry until
   acknowledged. Verifies that every acknowledged trial is in the database exactly once.

The clients run on the same machine as the server: on 2 cores they take CPU from it, so the
figures are an upper bound of the server's own latency (``--server-cpus``/``--client-cpus``
pin them apart with ``taskset``).

Usage: python bench/bench_study_load.py [--participants 200] [--db sqlite|postgres] [--time-limit 300]
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from study_site.simulate import CSRF_RE, Deadline, SiteClient  # noqa: E402

HOST = "127.0.0.1"  # loopback only


class _SkipCrash(Exception):
    pass


class Client(SiteClient):
    """One simulated participant with fake searches: retries (study_site.simulate.SiteClient) until answered."""

    max_backoff_s = 1.0

    def __init__(self, port: int, pid: str, deadline: float, stats: "Stats", think=(0.0, 0.03), limit_s=5.0):
        super().__init__(HOST, port, deadline, stats)
        self.pid, self.think, self.limit_s = pid, think, limit_s
        self.acked: dict[int, str] = {}  # trial index -> client_trial_id acknowledged

    def session(self, images: bool, rng: random.Random):
        st, _, _ = self.request("GET", f"/?PROLIFIC_PID={self.pid}&STUDY_ID=bench&SESSION_ID=s{self.pid}")
        if st != 302:
            raise RuntimeError(f"{self.pid}: landing -> {st}")
        st, html, _ = self.request("GET", "/consent")
        self.csrf = CSRF_RE.search(html.decode()).group(1)
        self.form("/consent", {"consent": "yes"})
        self.form("/about-you", {"age": rng.choice(["18-24", "25-34", "35-44"])})
        self.form("/instructions", {})
        st, data, _ = self.request("GET", "/api/state")
        state = json.loads(data)
        if images:
            for t in state["trials"]:
                self.request("GET", t["src"])
        first = None
        for t in state["trials"]:
            st, j, dt0 = self.api("/api/start", {"trial_index": t["index"]})
            if st != 200:
                self.stats.add("unexpected_start_answers")
                raise RuntimeError(f"{self.pid}: start {t['index']} -> {st} {j}")
            self.stats.start_latency(dt0)
            t_shown = time.monotonic() - j["elapsed_ms"] / 1000.0
            search = rng.uniform(*self.think)  # search time; a timeout at the limit
            timed_out = search >= self.limit_s
            time.sleep(min(search, self.limit_s))
            rt = (time.monotonic() - t_shown) * 1000.0
            body = {"trial_index": t["index"], "client_trial_id": f"{self.pid}-{t['index']}-{rng.getrandbits(40):x}",
                    "timed_out": timed_out, "rt_ms": max(rt, self.limit_s * 1000.0) if timed_out else rt}
            if not timed_out:
                body.update(x=rng.randrange(t["w"]), y=rng.randrange(t["h"]))
            st, j, dt = self.api("/api/trial", body)
            if st != 200 or j.get("stored_client_trial_id") != body["client_trial_id"]:
                self.stats.add("unexpected_trial_answers")
                raise RuntimeError(f"{self.pid}: trial {t['index']} -> {st} {j}")
            self.stats.trial_latency(dt)
            self.acked[t["index"]] = body["client_trial_id"]
            self.stats.ack()
            if first is None:
                first = body
                # idempotency: the same answer again (lost ack) and a new client id for the same trial
                st2, j2, _ = self.api("/api/trial", body)
                st3, j3, _ = self.api("/api/trial", dict(body, client_trial_id=body["client_trial_id"] + "b"))
                if not (st2 == st3 == 200 and j2["duplicate"] and j3["duplicate"]
                        and j3["stored_client_trial_id"] == body["client_trial_id"]):
                    self.stats.add("idempotency_failures")
        st, j, _ = self.api("/api/complete", {})
        if st != 200:
            raise RuntimeError(f"{self.pid}: complete -> {st} {j}")
        self.stats.add("completed")


class Stats:
    def __init__(self):
        self.lock = threading.Lock()
        self.latencies: list[float] = []
        self.start_latencies: list[float] = []
        self.counts: dict[str, int] = {}
        self.acks = 0

    def add(self, key, n=1):
        with self.lock:
            self.counts[key] = self.counts.get(key, 0) + n

    def trial_latency(self, dt):
        with self.lock:
            self.latencies.append(dt)

    def start_latency(self, dt):
        with self.lock:
            self.start_latencies.append(dt)

    def ack(self):
        with self.lock:
            self.acks += 1


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def start_server(stim: Path, db: str, port: int, threads: int, log, limit_s: float, cpus: str | None = None):
    env = dict(os.environ)
    env.update(
        CAMO_STUDY_RATE_LIMIT_PER_S="200",
        CAMO_STUDY_RATE_LIMIT_BURST="400",
        CAMO_STUDY_NEW_PARTICIPANTS_PER_MIN="100000",
        CAMO_STUDY_ID_HMAC_KEY="bench-" + "0" * 58,
        CAMO_STUDY_TRIAL_TIME_LIMIT_S=str(limit_s),
        PYTHONPATH=str(ROOT) + os.pathsep + env.get("PYTHONPATH", ""),
    )
    cmd = [sys.executable, "-m", "study_site.cli", "study", "serve", "--stimuli", str(stim), "--db", str(db),
           "--host", HOST, "--port", str(port), "--threads", str(threads)]
    if cpus:
        cmd = ["taskset", "-c", cpus, *cmd]
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=log, cwd=str(ROOT))
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}")
        try:
            c = http.client.HTTPConnection(HOST, port, timeout=2)
            c.request("GET", "/healthz")
            if c.getresponse().status == 200:
                return proc
        except OSError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("server did not start within 60 s")


def run_phase(name, port, n, images, deadline, stats, seed, think, limit_s, on_progress=None, ramp_s=0.0):
    clients = [Client(port, f"{name}{i:04d}", deadline, stats, think, limit_s) for i in range(n)]
    errors: list[str] = []

    def work(c, k):
        time.sleep(ramp_s * k / max(1, n))  # arrivals spread over ramp_s seconds (0: all at once)
        try:
            c.session(images, random.Random(seed * 100003 + k))
        except Deadline:
            stats.add("deadline_hit")
        except Exception as exc:  # noqa: BLE001 - recorded and reported
            errors.append(f"{c.pid}: {exc}")

    threads = [threading.Thread(target=work, args=(c, k), daemon=True) for k, c in enumerate(clients)]
    for t in threads:
        t.start()
    while any(t.is_alive() for t in threads):
        if on_progress:
            on_progress()
        time.sleep(0.05)
    return clients, errors


def verify(url: str, clients) -> dict:
    """Every acknowledged trial is in the database with the acknowledged client id, exactly once."""
    from sqlalchemy import create_engine, text

    eng = create_engine(url)
    with eng.connect() as con:
        rows = con.execute(text("SELECT client_trial_id, participant_id, trial_index FROM trials")).all()
        dup_keys = con.execute(text(
            "SELECT COUNT(*) FROM (SELECT participant_id, trial_index FROM trials GROUP BY 1, 2 HAVING COUNT(*) > 1) d"
        )).scalar()
        integrity = (con.execute(text("PRAGMA integrity_check")).scalar() if eng.dialect.name == "sqlite"
                     else "n/a (postgresql)")
    eng.dispose()
    stored = {cid for cid, _, _ in rows}
    acked = {cid for c in clients for cid in c.acked.values()}
    pids = {c.pid for c in clients}
    return {
        "acked": len(acked),
        "lost": len(acked - stored),
        "duplicate_rows": dup_keys,
        "stored_but_not_acked": len([cid for cid in stored if cid.rsplit("-", 2)[0] in pids and cid not in acked]),
        "integrity": integrity,
    }


def pct(xs, q):
    if not xs:
        return float("nan")
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q / 100 * (len(xs) - 1))))]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--participants", type=int, default=200)
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--practice", type=int, default=5)
    ap.add_argument("--threads", type=int, default=16, help="server worker threads")
    ap.add_argument("--no-images", action="store_true", help="skip the image preload requests")
    ap.add_argument(
        "--think",
        default="2,6",
        metavar="MIN,MAX",
        help="seconds between a participant's trials, uniform (default 2,6: search time plus looking at the "
        "reveal; 0,0.03 makes it a saturation test)",
    )
    ap.add_argument("--trial-limit", type=float, default=5.0,
                    help="the study's time limit per trial in seconds (default 5: searches of --think 2-6 s time "
                         "out ~25%% of the time)")
    ap.add_argument("--db", choices=("sqlite", "postgres"), default="sqlite",
                    help="sqlite (a file, WAL, synchronous=FULL) or postgres (a throw-away local cluster)")
    ap.add_argument("--server-cpus", help="taskset CPU list for the server, e.g. 0 (clients: --client-cpus)")
    ap.add_argument("--client-cpus", help="taskset CPU list for this client process, e.g. 1")
    ap.add_argument("--no-crash", action="store_true", help="skip the kill -9 phase")
    ap.add_argument("--ramp", type=float, default=0.0, metavar="S",
                    help="spread the participants' arrivals over S seconds (default 0: all 200 arrive at once, "
                         "landing, consent and image preload in the same second)")
    ap.add_argument("--nice", type=int, default=None, metavar="N",
                    help="run this client, the server and a --db postgres cluster at scheduling priority N "
                         "(e.g. -10, needs root): an estimate of the server alone on a machine busy with other "
                         "jobs")
    ap.add_argument("--time-limit", type=float, default=300.0, help="seconds for the whole benchmark")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    if not 1 <= args.participants <= 1000 or not 1 <= args.scenes <= 50:
        ap.error("--participants must be 1-1000 and --scenes 1-50")
    try:
        think = tuple(float(x) for x in args.think.split(","))
        assert len(think) == 2 and 0 <= think[0] <= think[1] <= 60
    except (ValueError, AssertionError):
        ap.error("--think must be MIN,MAX seconds, 0 <= MIN <= MAX <= 60")
    if args.nice is not None:  # inherited by the server subprocess and the PostgreSQL cluster
        try:
            os.setpriority(os.PRIO_PROCESS, 0, args.nice)
        except PermissionError:
            ap.error("--nice below 0 needs root")
    if args.client_cpus:
        os.sched_setaffinity(0, {int(c) for c in args.client_cpus.split(",")})
    t_all = time.monotonic()
    deadline = t_all + args.time_limit

    from study_site.stimuli import build_stimuli
    from study_site.testing import make_fake_eval_dir

    results: dict = {"participants": args.participants, "scenes": args.scenes, "practice": args.practice,
                     "think_s": think, "db": args.db, "trial_limit_s": args.trial_limit, "cpus": os.cpu_count(),
                     "nice": args.nice, "ramp_s": args.ramp, "loadavg_before": os.getloadavg()}
    pg = None
    if args.db == "postgres":
        from study_site.testing import ThrowawayPostgres

        pg = ThrowawayPostgres(dbname="camo_study_bench", durable=True)
        db_url = pg.start()
    with tempfile.TemporaryDirectory(prefix="bench_study_") as tmp:
        tmp = Path(tmp)
        scenes = tuple(f"scene{i:02d}" for i in range(args.scenes))
        make_fake_eval_dir(tmp / "eval", scenes=scenes, methods=("ours", "random", "gan"), views=2, size=(256, 192))
        build_stimuli([tmp / "eval"], tmp / "stim", log=lambda m: None)
        if pg is None:
            db_url = f"sqlite:///{tmp / 'study.sqlite'}"
        port = free_port()
        log = open(tmp / "server.log", "wb")
        os.environ["CAMO_STUDY_PRACTICE_TRIALS"] = str(args.practice)

        def server():
            return start_server(tmp / "stim", db_url, port, args.threads, log, args.trial_limit, args.server_cpus)

        proc = server()
        server_kind = "waitress" if b"waitress" in (tmp / "server.log").read_bytes() else "werkzeug"
        results["server"] = server_kind
        try:
            # ---- load phase ---------------------------------------------------------------
            stats = Stats()
            t0 = time.monotonic()
            phase_deadline = min(deadline, t0 + args.time_limit * 0.5)
            clients, errors = run_phase(
                "load", port, args.participants, not args.no_images, phase_deadline, stats, 1, think, args.trial_limit,
                ramp_s=args.ramp,
            )
            wall = time.monotonic() - t0
            v = verify(db_url, clients)
            lat = [x * 1000 for x in stats.latencies]
            slat = [x * 1000 for x in stats.start_latencies]
            results["load"] = {
                "wall_s": round(wall, 2),
                "completed": stats.counts.get("completed", 0),
                "trial_writes": len(lat),
                "writes_per_s": round(len(lat) / wall, 1),
                "p50_ms": round(pct(lat, 50), 2),
                "p90_ms": round(pct(lat, 90), 2),
                "p99_ms": round(pct(lat, 99), 2),
                "max_ms": round(max(lat), 2) if lat else None,
                "mean_ms": round(statistics.fmean(lat), 2) if lat else None,
                "start_p50_ms": round(pct(slat, 50), 2),
                "start_p99_ms": round(pct(slat, 99), 2),
                "counts": stats.counts,
                "errors": errors[:5],
                **v,
            }
            print(f"[load] {args.participants} concurrent participants x {args.practice + args.scenes} trials, "
                  f"arrivals over {args.ramp:g} s, search {think[0]:g}-{think[1]:g} s (limit {args.trial_limit:g} s), "
                  f"server={server_kind}, "
                  f"db={args.db}, wall {wall:.1f} s, completed {results['load']['completed']}")
            print(f"[load] trial starts: n={len(slat)}, p50 {results['load']['start_p50_ms']} ms, "
                  f"p99 {results['load']['start_p99_ms']} ms")
            print(f"[load] trial writes: n={len(lat)} ({results['load']['writes_per_s']}/s), "
                  f"p50 {results['load']['p50_ms']} ms, p90 {results['load']['p90_ms']} ms, "
                  f"p99 {results['load']['p99_ms']} ms, max {results['load']['max_ms']} ms")
            print(f"[load] acknowledged {v['acked']}, lost {v['lost']}, duplicated rows {v['duplicate_rows']}, "
                  f"idempotency failures {stats.counts.get('idempotency_failures', 0)}, "
                  f"errors {len(errors)}, integrity {v['integrity']}")

            # ---- crash phase --------------------------------------------------------------
            if args.no_crash:
                raise _SkipCrash()
            stats2 = Stats()
            expected = args.participants * (args.practice + args.scenes)
            state = {"proc": proc, "killed_at_acks": None, "restart_s": None}

            def maybe_crash():
                if state["killed_at_acks"] is None and stats2.acks >= 0.35 * expected:
                    state["killed_at_acks"] = stats2.acks
                    state["proc"].send_signal(signal.SIGKILL)
                    state["proc"].wait()
                    t_r = time.monotonic()
                    time.sleep(0.5)
                    state["proc"] = server()
                    state["restart_s"] = round(time.monotonic() - t_r, 2)

            t0 = time.monotonic()
            clients2, errors2 = run_phase(
                "crash", port, args.participants, False, deadline, stats2, 2, think, args.trial_limit, maybe_crash,
                ramp_s=args.ramp,
            )
            wall2 = time.monotonic() - t0
            proc = state["proc"]
            v2 = verify(db_url, clients2)
            lat2 = [x * 1000 for x in stats2.latencies]
            results["crash"] = {
                "wall_s": round(wall2, 2),
                "killed_after_acks": state["killed_at_acks"],
                "down_and_restart_s": state["restart_s"],
                "completed": stats2.counts.get("completed", 0),
                "counts": stats2.counts,
                "errors": errors2[:5],
                "p50_ms": round(pct(lat2, 50), 2),
                "p99_ms": round(pct(lat2, 99), 2),
                **v2,
            }
            print(f"[crash] SIGKILL after {state['killed_at_acks']} of {expected} acknowledged trials, "
                  f"back up after {state['restart_s']} s; completed {results['crash']['completed']}/{args.participants}, "
                  f"transport errors {stats2.counts.get('transport_errors', 0)}")
            print(f"[crash] acknowledged {v2['acked']}, lost {v2['lost']}, duplicated rows {v2['duplicate_rows']}, "
                  f"committed-but-unacknowledged {v2['stored_but_not_acked']}, errors {len(errors2)}, "
                  f"integrity {v2['integrity']}")
            print(f"[crash] trial writes incl. the outage: p50 {results['crash']['p50_ms']} ms, "
                  f"p99 {results['crash']['p99_ms']} ms")
        except _SkipCrash:
            pass
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
            log.close()
            if pg is not None:
                pg.stop()
    results["total_s"] = round(time.monotonic() - t_all, 1)
    results["loadavg_after"] = os.getloadavg()
    print(f"load average (1, 5, 15 min) before {results['loadavg_before']}, after {results['loadavg_after']} "
          f"on {os.cpu_count()} CPUs{'' if args.nice is None else f'; ran at nice {args.nice}'}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    ok = (
        results["load"]["lost"] == 0
        and results["load"]["duplicate_rows"] == 0
        and (args.no_crash or (results.get("crash", {}).get("lost", 1) == 0
                               and results["crash"]["duplicate_rows"] == 0))
    )
    print(f"total {results['total_s']} s: {'OK' if ok else 'FAILED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
