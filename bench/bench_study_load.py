"""Load and crash benchmark of the study site on real stimuli (loopback only, bounded, stops by itself).

Realistic: a real stimulus set made by ``camo study build-stimuli`` (512-px renders; ``--make-stimuli DIR`` makes
one with the toolkit's own commands), participants who load every image first (the WebP the page loads) and then
search each image for a uniform ``--think`` time, and the server configurations compared **side by side in one
run** (``--configs``: ``camo study serve`` = waitress, one process; ``camo study serve --workers N`` = gunicorn,
the production command; each on SQLite -- a file, WAL, synchronous=FULL -- and on a throw-away PostgreSQL
cluster with its durable defaults), for every ``--think`` range (default 2-8 s and 0.5-2 s).

Per run: a fresh database and server; N participants (threads + http.client, arrivals spread over ``--ramp``
seconds) run whole sessions (landing, consent, about you, instructions, state, image preload, each trial as
``POST /api/start``, the search, ``POST /api/trial``; each also re-sends one acknowledged trial with the same and
a new client id), then completion. Printed: trial-write, start and image latencies (p50/p99, retries included),
trial writes per second, lost and duplicated trials, and the 1-minute load average when the run started
(the machine may be shared: compare the rows of one run, not absolute figures across runs). ``--crash`` adds a
phase per config in which the server's process group is killed with SIGKILL at ~35 % of the trials and
restarted on the same database; every acknowledged trial must be stored exactly once. ``--saturation 100,200,400``
adds runs of the last config and think range with more participants: where trial writes stop keeping up.

The clients run on the same machine as the server: on 2 cores they take CPU from it, so the figures are an upper
bound of the server's own latency (``--server-cpus``/``--client-cpus`` pin them apart with ``taskset``).

Usage: python bench/bench_study_load.py --make-stimuli /tmp/bench_stim   (once)
       python bench/bench_study_load.py --stimuli /tmp/bench_stim/stim [--participants 200] [--crash]
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


class Client(SiteClient):
    """One simulated participant with fake searches: retries (study_site.simulate.SiteClient) until answered."""

    max_backoff_s = 1.0

    def __init__(self, port: int, pid: str, deadline: float, stats: "Stats", think=(2.0, 8.0), limit_s=10.0):
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
            for t in state["trials"]:  # what the page does: the WebP (PNG only for a set built before WebP)
                t0 = time.perf_counter()
                st, data, _ = self.request("GET", t["src"])
                if st != 200:
                    raise RuntimeError(f"{self.pid}: image {t['src']} -> {st}")
                self.stats.image_latency(time.perf_counter() - t0, len(data))
        first = None
        for t in state["trials"]:
            t0 = time.perf_counter()
            st, j, _ = self.api("/api/start", {"trial_index": t["index"]})
            dt0 = time.perf_counter() - t0  # with retries (503, 429, transport errors)
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
            t0 = time.perf_counter()
            st, j, _ = self.api("/api/trial", body)
            dt = time.perf_counter() - t0  # with retries
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
        self.image_latencies: list[float] = []
        self.image_bytes = 0
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

    def image_latency(self, dt, n):
        with self.lock:
            self.image_latencies.append(dt)
            self.image_bytes += n

    def ack(self):
        with self.lock:
            self.acks += 1


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def start_server(stim: Path, db: str, port: int, threads: int, log, limit_s: float, cpus: str | None = None,
                 workers: int = 1):
    """``camo study serve`` in a subprocess (its own process group: a crash kills the master and its workers);
    ``workers`` > 1 is the production command (gunicorn)."""
    env = dict(os.environ)
    env.update(
        CAMO_STUDY_RATE_LIMIT_PER_S="200",
        CAMO_STUDY_RATE_LIMIT_BURST="400",
        CAMO_STUDY_NEW_PARTICIPANTS_PER_MIN="100000",
        CAMO_STUDY_ID_HMAC_KEY="bench-" + "0" * 58,
        CAMO_STUDY_SECRET_KEY="cookie-" + "1" * 57,
        CAMO_STUDY_TRIAL_TIME_LIMIT_S=str(limit_s),
        PYTHONPATH=str(ROOT) + os.pathsep + env.get("PYTHONPATH", ""),
    )
    cmd = [sys.executable, "-m", "study_site.cli", "study", "serve", "--stimuli", str(stim), "--db", str(db),
           "--host", HOST, "--port", str(port), "--threads", str(threads), "--workers", str(workers)]
    if cpus:
        cmd = ["taskset", "-c", cpus, *cmd]
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=log, cwd=str(ROOT), start_new_session=True)
    t_end = time.monotonic() + 90
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
    kill_server(proc)
    raise RuntimeError("server did not start within 90 s")


def kill_server(proc, sig=signal.SIGKILL) -> None:
    """``sig`` to the server's whole process group (gunicorn's master and workers), then wait for it."""
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


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


def summary(lat_s: list[float]) -> dict:
    ms = [x * 1000 for x in lat_s]
    return {"n": len(ms), "p50_ms": round(pct(ms, 50), 1), "p90_ms": round(pct(ms, 90), 1),
            "p99_ms": round(pct(ms, 99), 1), "max_ms": round(max(ms), 1) if ms else None}


def make_stimuli(out: Path) -> None:
    """A real stimulus set with the toolkit's own commands: mean-colour runs of gravel, meadow and panorama (and a
    transparent one of gravel), evaluated, then re-rendered by `camo study build-stimuli` at 512 px (6 views, 8 spp,
    synthetic practice). A few CPU-minutes; done once, then pass --stimuli OUT/stim."""
    cli = [sys.executable, "-m", "camo.cli"]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    runs = []
    for scene, method in (("gravel", "mean"), ("gravel", "transparent"), ("meadow", "mean"), ("panorama", "mean")):
        run = out / "runs" / f"{scene}_{method}"
        runs.append(str(run))
        subprocess.run([*cli, "optimize", scene, "--method", method, "--out", str(run), "--views", "4",
                        "--resolution", "64", "--map-resolution", "128", "--target-vertices", "3000",
                        "--target-spp", "8", "--quiet", "--overwrite"], check=True, env=env, cwd=str(ROOT))
    subprocess.run([*cli, "evaluate", *runs, "--out", str(out / "eval"), "--views", "2", "--spp", "4",
                    "--resolution", "64", "--metrics", "psnr", "--quiet"], check=True, env=env, cwd=str(ROOT))
    subprocess.run([*cli, "study", "build-stimuli", str(out / "eval"), "--out", str(out / "stim"), "--size", "512",
                    "--views", "6", "--spp", "8", "--force"], check=True, env=env, cwd=str(ROOT))


def stimulus_sizes(stim: Path) -> dict:
    """Mean bytes of the served images: WebP (what the page loads) and the PNG fallback."""
    webp = [p.stat().st_size for p in (stim / "images").glob("*.webp")]
    png = [p.stat().st_size for p in (stim / "images").glob("*.png")]
    return {"images": len(png), "mean_png_kb": round(statistics.fmean(png) / 1024, 1) if png else None,
            "mean_webp_kb": round(statistics.fmean(webp) / 1024, 1) if webp else None}


def one_run(label: str, cfg: dict, stim: Path, args, think, n: int, deadline: float, crash: bool, tmp: Path) -> dict:
    """Start a fresh database and server of ``cfg`` ({server, db, workers}), run ``n`` participants searching
    ``think`` seconds per trial; optionally a kill -9 phase. Returns the figures."""
    pg = None
    if cfg["db"] == "postgres":
        from study_site.testing import ThrowawayPostgres

        pg = ThrowawayPostgres(dbname="camo_study_bench", durable=True)
        db_url = pg.start()
    else:
        db_url = f"sqlite:///{tmp / f'{label}.sqlite'}"
    port = free_port()
    log = open(tmp / f"{label}.log", "wb")
    os.environ["CAMO_STUDY_PRACTICE_TRIALS"] = str(args.practice)

    def server():
        return start_server(stim, db_url, port, args.threads, log, args.trial_limit, args.server_cpus,
                            cfg["workers"])

    out = {"label": label, **cfg, "think_s": list(think), "participants": n, "loadavg_before": os.getloadavg()}
    proc = server()
    try:
        stats = Stats()
        t0 = time.monotonic()
        clients, errors = run_phase(label, port, n, not args.no_images, deadline, stats, 1, think, args.trial_limit,
                                    ramp_s=args.ramp)
        wall = time.monotonic() - t0
        v = verify(db_url, clients)
        out.update(wall_s=round(wall, 1), completed=stats.counts.get("completed", 0),
                   writes_per_s=round(len(stats.latencies) / wall, 1),
                   requests_per_s=round((len(stats.latencies) + len(stats.start_latencies)
                                         + len(stats.image_latencies)) / wall, 1),
                   trial=summary(stats.latencies), start=summary(stats.start_latencies),
                   image=summary(stats.image_latencies),
                   image_mb=round(stats.image_bytes / 2**20, 1), retried=stats.counts, errors=errors[:3],
                   loadavg_after=os.getloadavg(), **v)
        if crash:
            stats2 = Stats()
            expected = n * (args.practice + len(StimulusSetLite(stim).scenes))
            state = {"proc": proc, "killed_at_acks": None}

            def maybe_crash():
                if state["killed_at_acks"] is None and stats2.acks >= 0.35 * expected:
                    state["killed_at_acks"] = stats2.acks
                    kill_server(state["proc"])
                    time.sleep(0.5)
                    state["proc"] = server()

            clients2, errors2 = run_phase(label + "k", port, n, False, deadline, stats2, 2, think, args.trial_limit,
                                          maybe_crash, ramp_s=args.ramp)
            proc = state["proc"]
            v2 = verify(db_url, clients2)
            out["crash"] = {"killed_after_acks": state["killed_at_acks"], "completed": stats2.counts.get("completed", 0),
                            "errors": errors2[:3], "trial": summary(stats2.latencies), **v2}
    finally:
        kill_server(proc, signal.SIGTERM)
        log.close()
        if pg is not None:
            pg.stop()
    return out


class StimulusSetLite:
    """Formal scenes of a stimulus set (for the expected number of trials)."""

    def __init__(self, stim: Path):
        man = json.loads((stim / "manifest.json").read_text())
        self.scenes = sorted({s["scene"] for s in man["stimuli"] if not s["practice"]})


def parse_configs(text: str) -> list[dict]:
    out = []
    for item in text.split(","):
        server, _, rest = item.strip().partition(":")
        db, _, workers = rest.partition(":")
        if server not in ("serve", "gunicorn") or db not in ("sqlite", "postgres"):
            raise ValueError(item)
        w = int(workers) if workers else (1 if server == "serve" else 3)
        if (server == "serve") != (w == 1):
            raise ValueError(item)
        out.append({"server": "waitress" if server == "serve" else "gunicorn", "db": db, "workers": w})
    return out


def parse_range(text: str) -> tuple[float, float]:
    lo, hi = (float(x) for x in text.split(","))
    if not 0 <= lo <= hi <= 60:
        raise ValueError(text)
    return lo, hi


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stimuli", type=Path, help="a real stimulus set (camo study build-stimuli); see --make-stimuli")
    ap.add_argument("--make-stimuli", type=Path, metavar="DIR",
                    help="build a real 512-px stimulus set into DIR/stim with the toolkit's commands, then stop")
    ap.add_argument("--participants", type=int, default=200)
    ap.add_argument("--practice", type=int, default=5)
    ap.add_argument("--threads", type=int, default=8, help="threads per server process (default 8)")
    ap.add_argument("--configs", default="serve:sqlite,gunicorn:sqlite:3,serve:postgres,gunicorn:postgres:3",
                    help="server:db[:workers],... compared side by side in this run (server: serve = `camo study "
                         "serve` with waitress, gunicorn = `camo study serve --workers N`; db: sqlite or postgres)")
    ap.add_argument("--think", default="2,8;0.5,2", metavar="MIN,MAX;...",
                    help="search-time ranges in seconds, each run for every config (default '2,8;0.5,2')")
    ap.add_argument("--saturation", default="", metavar="N,...",
                    help="also run these numbers of participants with the last think range and the last config "
                         "(e.g. 100,200,400: where trial writes stop keeping up)")
    ap.add_argument("--no-images", action="store_true", help="skip the image preload requests")
    ap.add_argument("--trial-limit", type=float, default=10.0,
                    help="the study's time limit per trial in seconds (default 10: searches of 2-8 s never time out)")
    ap.add_argument("--server-cpus", help="taskset CPU list for the server, e.g. 0 (clients: --client-cpus)")
    ap.add_argument("--client-cpus", help="taskset CPU list for this client process, e.g. 1")
    ap.add_argument("--crash", action="store_true", help="also a kill -9 phase per config (every acknowledged trial "
                                                         "must be stored exactly once)")
    ap.add_argument("--ramp", type=float, default=10.0, metavar="S",
                    help="spread the participants' arrivals over S seconds (default 10)")
    ap.add_argument("--time-limit", type=float, default=1800.0, help="seconds for the whole benchmark")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    if args.make_stimuli:
        make_stimuli(args.make_stimuli)
        print(f"wrote {args.make_stimuli / 'stim'}: pass --stimuli {args.make_stimuli / 'stim'}")
        return 0
    if args.stimuli is None or not (args.stimuli / "manifest.json").is_file():
        ap.error("--stimuli STIM_DIR (a set made by `camo study build-stimuli`; --make-stimuli DIR makes one) is "
                 "required")
    if not 1 <= args.participants <= 1000:
        ap.error("--participants must be 1-1000")
    try:
        configs = parse_configs(args.configs)
        thinks = [parse_range(t) for t in args.think.split(";") if t.strip()]
        sat = [int(x) for x in args.saturation.split(",") if x.strip()]
    except ValueError as exc:
        ap.error(f"bad --configs/--think/--saturation item {exc}")
    if args.client_cpus:
        os.sched_setaffinity(0, {int(c) for c in args.client_cpus.split(",")})
    t_all = time.monotonic()
    deadline = t_all + args.time_limit
    sizes = stimulus_sizes(args.stimuli)
    print(f"stimuli {args.stimuli}: {sizes['images']} images, mean {sizes['mean_png_kb']} KB PNG, "
          f"{sizes['mean_webp_kb']} KB lossless WebP (served); {os.cpu_count()} CPUs")
    results: dict = {"stimuli": str(args.stimuli), **sizes, "cpus": os.cpu_count(), "runs": []}
    plan = [(cfg, think, args.participants) for think in thinks for cfg in configs]
    plan += [(configs[-1], thinks[-1], n) for n in sat]
    header = (f"{'config':<22} {'search s':>8} {'N':>4} {'load1':>5} {'wr/s':>6} {'trial p50/p99 ms':>17} "
              f"{'start p50/p99':>14} {'image p50/p99':>14} {'done':>5} {'lost':>4} {'dup':>3}")
    print(header)
    with tempfile.TemporaryDirectory(prefix="bench_study_") as tmp:
        for k, (cfg, think, n) in enumerate(plan):
            label = f"r{k}_{cfg['server']}_{cfg['db']}_{cfg['workers']}"
            r = one_run(label, cfg, args.stimuli, args, think, n, deadline, args.crash, Path(tmp))
            results["runs"].append(r)
            name = f"{cfg['server']}x{cfg['workers']}+{cfg['db']}"
            print(f"{name:<22} {think[0]:g}-{think[1]:g}".ljust(31) + f" {n:>4} {r['loadavg_before'][0]:>5.1f} "
                  f"{r['writes_per_s']:>6} {r['trial']['p50_ms']:>8}/{r['trial']['p99_ms']:<8} "
                  f"{r['start']['p50_ms']:>6}/{r['start']['p99_ms']:<7} {r['image']['p50_ms']:>6}/{r['image']['p99_ms']:<7} "
                  f"{r['completed']:>5} {r['lost']:>4} {r['duplicate_rows']:>3}", flush=True)
            if r["errors"]:
                print(f"   errors: {r['errors']}")
            if "crash" in r:
                c = r["crash"]
                print(f"   kill -9 after {c['killed_after_acks']} acks: completed {c['completed']}/{n}, lost "
                      f"{c['lost']}, duplicated {c['duplicate_rows']}, trial p99 incl. outage {c['trial']['p99_ms']} ms")
    results["total_s"] = round(time.monotonic() - t_all, 1)
    print(f"load average (1 min) before/after each run is in the JSON; now {os.getloadavg()} on {os.cpu_count()} "
          f"CPUs; total {results['total_s']} s")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    ok = all(r["lost"] == 0 and r["duplicate_rows"] == 0 and (r.get("crash") is None or
                                                               (r["crash"]["lost"] == 0 and r["crash"]["duplicate_rows"] == 0))
             for r in results["runs"])
    print("OK" if ok else "FAILED (lost or duplicated trials)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
