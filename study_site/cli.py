"""``camo study ...`` commands: build-stimuli, make-key, serve, report, power, simulate.

``register(subparsers)`` adds the ``study`` group to an argparse parser; each
subcommand stores its handler as ``func`` (``args.func(args) -> int``). Handlers
raise :class:`camo_base.errors.CamoError` for bad input. Standalone use:
``python -m study_site.cli study serve ...``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from camo_base.errors import CamoError
from camo_base.ranges import Range
from study_site.ranges import ADULT_AGE, CONFIG_RANGES, POWER_RANGES, SIMULATE_RANGES, STIMULI_RANGES


def register(subparsers) -> argparse.ArgumentParser:
    """Add ``study`` with ``build-stimuli``, ``serve`` and ``report`` to ``subparsers``."""
    p = subparsers.add_parser(
        "study",
        help="perceptual click-to-find study: stimuli, web server, analysis",
        description="Perceptual click-to-find study (GANmouflage protocol): build stimuli, serve, report.",
    )
    sub = p.add_subparsers(dest="study_command", metavar="COMMAND")
    sub.required = True

    b = sub.add_parser(
        "build-stimuli",
        help="render a stimulus set from evaluation directories",
        description="Render every evaluated run directory and asset again at study size with the object at a "
        "random, recorded position and size in the frame (see study_site/render_stimuli.py for the distribution); "
        "practice stimuli never share a scene with formal ones. 2D triplets cannot be rendered again: an "
        "evaluation holding them needs --copy.",
    )
    b.add_argument("eval_dirs", nargs="+", metavar="EVAL_DIR", help="output of `camo evaluate` (has renders.json)")
    b.add_argument("--out", required=True, metavar="STIMULI_DIR", help="new stimulus-set directory")
    b.add_argument(
        "--practice",
        nargs="+",
        default=[],
        metavar="EVAL_DIR",
        help="evaluation directories used only for practice trials (their scenes must not be formal scenes)",
    )
    b.add_argument(
        "--practice-scenes",
        default="",
        metavar="SCENE,...",
        help="scenes of the EVAL_DIRs used only for practice (taken out of the formal pool)",
    )
    b.add_argument(
        "--synthetic-practice",
        type=STIMULI_RANGES["synthetic_practice"].arg_type(),
        default=8,
        metavar="N",
        help="without --practice/--practice-scenes: N synthetic practice images (default 8; 0 = none)",
    )
    b.add_argument("--size", type=STIMULI_RANGES["size"].arg_type(), default=512, metavar="PX", help="stimulus width = height (default 512)")
    b.add_argument("--views", type=STIMULI_RANGES["views"].arg_type(), default=8, help="views per run (default 8)")
    b.add_argument("--spp", type=STIMULI_RANGES["spp"].arg_type(), default=64, help="samples per pixel (default 64)")
    b.add_argument("--seed", type=Range(int, 0, 2**63 - 1).arg_type(), default=0, help="placement and sampler seed (default 0)")
    b.add_argument(
        "--object-size",
        default="0.10,0.30",
        metavar="LO,HI",
        help="object extent as a fraction of the frame width, drawn uniformly (default 0.10,0.30)",
    )
    b.add_argument("--margin", type=STIMULI_RANGES["margin"].arg_type(), default=0.02, help="object kept this share of the frame inside (0.02)")
    b.add_argument("--threads", type=Range(int, 1, 4096).arg_type(), default=None, help="render threads (default: CAMO_THREADS or all cores)")
    b.add_argument(
        "--copy",
        action="store_true",
        help="copy the evaluation renders as they are instead (object where the evaluation had it: at the frame "
        "centre); needed for evaluations holding 2D triplets",
    )
    b.add_argument("--no-noise-match", action="store_true",
                   help="the same spp everywhere (default: more samples, up to 8x, where the render with the object is "
                   "noisier than the background, so noise does not give the object away)")
    from optimizer.rendering.planner import DENOISER, DENOISERS

    b.add_argument("--denoise", nargs="?", const=DENOISER, default="", choices=DENOISERS, metavar="VARIANT",
                   help="denoise the renders with and without the object alike by Open Image Denoise (after noise "
                   "matching) where the evaluation plan's pilot measures the noise at --spp above the denoiser's "
                   f"bias; VARIANT: {DENOISER} (first-hit albedo and normal, the flag alone) or oidn-through "
                   "(see-through features: keeps more of the ground seen through a see-through object); default: "
                   "off, as it smooths that ground (docs/evaluation.md)")
    b.add_argument("--observer-trials", type=Range(int, 0, 100_000).arg_type(), default=200, metavar="N",
                   help="simulated observer trials per stimulus for the predicted Table I and power (default 200; "
                   "0 = none; docs/observer.md)")
    b.add_argument("--force", action="store_true", help="overwrite an existing stimulus set (new ids!)")
    b.set_defaults(func=cmd_build_stimuli)

    k = sub.add_parser("make-key", help="write a new random key file (participant-id HMAC key, cookie key, admin token)")
    k.add_argument("path", metavar="FILE", help="new file (mode 0600); refuses to overwrite")
    k.set_defaults(func=cmd_make_key)

    s = sub.add_parser("serve", help="run the study web site")
    s.add_argument("--stimuli", required=True, metavar="STIMULI_DIR")
    s.add_argument("--db", required=True, metavar="URL", help="SQLAlchemy URL or a SQLite file path")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=Range(int, 1, 65535).arg_type(), default=5000)
    s.add_argument("--threads", type=Range(int, 1, 256).arg_type(), default=8,
                   help="threads per worker process (default 8)")
    s.add_argument(
        "--workers", type=Range(int, 1, 64).arg_type(), default=1,
        help="worker processes (default 1: waitress in this process); 2 or more: gunicorn with that many "
        "processes of --threads threads each (the production command; use a PostgreSQL --db)")
    s.add_argument(
        "--connections", type=Range(int, 10, 100_000).arg_type(), default=1000, help="open client connections accepted at once (waitress)"
    )
    s.add_argument(
        "--dev",
        action="store_true",
        help="development: werkzeug's server, and an id key kept in the database when none is given",
    )
    s.add_argument("--id-key-file", metavar="FILE", help="participant-id HMAC key (`camo study make-key FILE`)")
    s.add_argument("--secret-key-file", metavar="FILE",
                   help="cookie-signing key (`camo study make-key FILE`; another key than --id-key-file)")
    s.add_argument("--admin-token-file", metavar="FILE", help="admin token (enables /admin/)")
    s.add_argument("--time-limit", type=CONFIG_RANGES["TRIAL_TIME_LIMIT_S"].arg_type(), metavar="S", help="seconds per trial (default 40)")
    s.add_argument("--practice-trials", type=CONFIG_RANGES["PRACTICE_TRIALS"].arg_type(), metavar="N", help="practice trials (default 5)")
    # 10-17 parse, so that the config check refuses them with its reason (adults only)
    s.add_argument("--min-age", type=Range(int, 10, CONFIG_RANGES["MIN_AGE"].hi).arg_type(), metavar="YEARS",
                   help=f"youngest age bracket ({ADULT_AGE}-{CONFIG_RANGES['MIN_AGE'].hi}; default 18)")
    s.add_argument("--completion-code", metavar="CODE", help="study-wide completion code (Prolific)")
    s.add_argument("--completion-url", metavar="URL", help="e.g. https://app.prolific.com/submissions/complete?cc={code}")
    s.add_argument("--consent-file", metavar="FILE", help="plain-text consent statement")
    # (a config error names the key; camo shows it with the flag that sets it: "MIN_AGE (--min-age)")
    s.set_defaults(func=cmd_serve, setting_keys={key: dest for dest, key in SERVE_CONFIG.items()})

    r = sub.add_parser("report", help="Table I, Kaplan-Meier curves, pairwise tests, CSV/Parquet tables")
    r.add_argument("--db", required=True, metavar="URL", help="SQLAlchemy URL or a SQLite file path")
    r.add_argument("--out", required=True, metavar="DIR")
    r.add_argument("--bootstrap", type=Range(int, 0, 10_000_000).arg_type(), default=2000, metavar="N", help="bootstrap replicates (default 2000)")
    r.add_argument("--seed", type=Range(int, 0, 2**63 - 1).arg_type(), default=0)
    r.add_argument("--include-incomplete", action="store_true", help="also analyse unfinished sessions")
    r.add_argument(
        "--miss-censor", choices=("limit", "click"), default="limit", help="censor misses at the limit or at the click"
    )
    r.add_argument(
        "--stimuli",
        metavar="STIMULI_DIR",
        help="the study's stimulus set: adds centre-click and last-practice-location baseline hit rates",
    )
    r.set_defaults(func=cmd_report)

    w = sub.add_parser(
        "power",
        help="participants needed to separate each pair of methods (resampled through Table I's tests)",
        description="Power analysis: simulated studies of N participants drawn from predicted (the simulated "
        "observer on a stimulus set) or pilot outcomes, analysed with Table I's pairwise tests (Fisher and "
        "log-rank, Holm), vectorised over the replicates; see study_site/power.py and docs/observer.md.",
    )
    src = w.add_mutually_exclusive_group()
    src.add_argument("--predicted", nargs="+", metavar="STIMULI_DIR",
                     help="stimulus sets with the observer's predictions (written by `camo study build-stimuli`, "
                     "or `camo study predict`)")
    src.add_argument("--db", metavar="URL", help="a pilot study database (SQLAlchemy URL or SQLite path)")
    w.add_argument("--out", required=True, metavar="DIR")
    w.add_argument("--participants", default="10,20,30,40,60,80,100,150,200,300", metavar="N,...",
                   help="numbers of participants to simulate (default 10,20,30,40,60,80,100,150,200,300)")
    w.add_argument("--reps", type=POWER_RANGES["reps"].arg_type(), default=200, help="simulated studies per number (default 200)")
    w.add_argument("--alpha", type=POWER_RANGES["alpha"].arg_type(), default=0.05, help="significance level after Holm (default 0.05)")
    w.add_argument("--target", type=POWER_RANGES["target"].arg_type(), default=0.8, help="power wanted (default 0.8)")
    w.add_argument("--seed", type=Range(int, 0, 2**63 - 1).arg_type(), default=0)
    w.add_argument("--quiet", action="store_true", help="no progress bar")
    w.set_defaults(func=cmd_power)

    q = sub.add_parser(
        "predict",
        help="run the simulated observer on every stimulus of a set (predicted Table I, power)",
        description="The simulated observer (evaluation/observer.py) searches every stimulus of the set as the "
        "site shows it and writes predicted.parquet/.csv, predicted_trials.parquet, predicted_config.json and "
        "predicted_power/ next to manifest.json (build-stimuli does this already; use it to redo with other "
        "observer settings). See study_site/predict.py and docs/observer.md.",
    )
    q.add_argument("stimuli", metavar="STIMULI_DIR")
    q.add_argument("--trials", type=Range(int, 0, 100_000).arg_type(), default=200, metavar="N", help="simulated trials per stimulus (200)")
    q.add_argument("--seed", type=Range(int, 0, 2**63 - 1).arg_type(), default=0)
    q.add_argument("--observer", metavar="KEY=VALUE,...",
                   help="observer parameters (evaluation.observer.ObserverConfig), e.g. display_deg=14,criterion=4")
    q.add_argument("--time-limit", type=CONFIG_RANGES["TRIAL_TIME_LIMIT_S"].arg_type(), metavar="S", help="seconds per trial (default: the site's 40)")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(func=cmd_predict)

    u = sub.add_parser(
        "surfaces",
        help="add the object-free views' surface normals to a rendered stimulus set built without them",
        description="Render the world-space normals of every object-free view of a rendered stimulus set (one ray a "
        "pixel, from the manifest's cameras) into backgrounds/*_normals.npz: the simulated observer's surfaces (floor, "
        "walls), which `camo study build-stimuli` writes for new sets. Run `camo study predict` afterwards.",
    )
    u.add_argument("stimuli", metavar="STIMULI_DIR")
    u.add_argument("--force", action="store_true", help="render them again where they exist")
    u.add_argument("--threads", type=Range(int, 1, 4096).arg_type(), default=None, help="render threads (default: CAMO_THREADS or all cores)")
    u.set_defaults(func=cmd_surfaces)

    m = sub.add_parser(
        "simulate",
        help="drive simulated participants (the simulated observer) through a live study site over HTTP",
        description="N simulated participants take the study at --url (loopback only) as the page does: consent, "
        "practice and formal trials with the simulated observer's clicks and times on the server's clock, "
        "retries, completion. Rehearses the site, database and `camo study report`; doubles as a load "
        "generator. See study_site/simulate.py and docs/observer.md.",
    )
    m.add_argument("--url", required=True, help="the running study, e.g. http://127.0.0.1:5000")
    m.add_argument("--participants", type=SIMULATE_RANGES["participants"].arg_type(), default=100, help="simulated participants (default 100)")
    m.add_argument("--concurrency", type=SIMULATE_RANGES["concurrency"].arg_type(), default=20, help="participants at once (default 20)")
    m.add_argument("--seed", type=Range(int, 0, 2**63 - 1).arg_type(), default=0, help="participant ids sim-SEED-K and their random streams")
    m.add_argument("--observer", metavar="KEY=VALUE,...",
                   help="observer parameters (evaluation.observer.ObserverConfig), e.g. display_deg=14,criterion=4")
    m.add_argument("--ramp", type=SIMULATE_RANGES["ramp"].arg_type(), default=0.0, metavar="S", help="spread arrivals over S seconds")
    m.add_argument("--max-seconds", type=SIMULATE_RANGES["max_seconds"].arg_type(), default=3600.0, help="deadline of the whole run (default 3600)")
    m.add_argument("--json", metavar="FILE", help="also write the summary and every simulated trial as JSON")
    m.set_defaults(func=cmd_simulate)
    return p


def cmd_simulate(args) -> int:
    from study_site.simulate import parse_observer, simulate

    cfg = parse_observer(args.observer)
    res = simulate(args.url, args.participants, args.concurrency, args.seed, args.max_seconds, cfg, args.ramp,
                   log=lambda s: print(s, file=sys.stderr, flush=True))
    lat = res["trial_write_ms"]
    print(f"{res['completed']}/{res['participants']} participants completed in {res['wall_s']} s; "
          f"{res['trials']} trials stored ({res['formal_trials']} formal: {res['formal_hits']} found, "
          f"{res['formal_timeouts']} timeouts); trial write p50 {lat['p50']:.1f} ms, p90 {lat['p90']:.1f} ms, "
          f"p99 {lat['p99']:.1f} ms; retried: {', '.join(f'{k} {v}' for k, v in sorted(res['counts'].items()) if k.startswith(('http_', 'transport'))) or 'none'}")
    for e in res["errors"]:
        print(f"error: {e}", file=sys.stderr)
    if args.json:
        from camo_base.atomic import write_json

        write_json(args.json, res)
    if res["n_errors"] or res["completed"] < res["participants"]:
        raise CamoError(f"{res['participants'] - res['completed']} simulated participant(s) did not complete "
                        f"({res['n_errors']} error(s), {res['counts'].get('deadline_hit', 0)} at the deadline)")
    return 0


def cmd_power(args) -> int:
    from study_site.power import cells_from_pilot, cells_from_predicted, parse_participants, write_power

    if not args.predicted and not args.db:
        raise CamoError("power needs --predicted EVAL_DIR ... or --db PILOT_DB")
    ns = parse_participants(args.participants)
    if args.reps < 1 or args.reps > 100_000:
        raise CamoError("--reps must be 1-100000")
    if args.predicted:
        cells, source = cells_from_predicted(args.predicted), "predicted by the simulated observer on the stimuli"
    else:
        cells, source = cells_from_pilot(args.db), "pilot study"
    t0 = time.perf_counter()
    res = write_power(cells, args.out, ns, reps=args.reps, alpha=args.alpha, target=args.target, seed=args.seed,
                      source=source, progress=not args.quiet)
    print(f"{len(ns)} numbers of participants x {args.reps} simulated studies in {time.perf_counter() - t0:.1f} s")
    from study_site.power import TESTS

    for r in res["needed"].itertuples():
        n = f"{int(r.participants)}" if r.participants == r.participants else f"> {r.max_n}"
        print(f"{r.method_a} vs {r.method_b}, {TESTS[r.test]}: {n} participants for {100 * r.target:.0f} % power")
    print(f"wrote {args.out}/power.md, power.csv, power_needed.csv, power.png")
    return 0


def _pair(text: str, flag: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise CamoError(f"{flag} must be LO,HI (two numbers), not {text!r}") from None
    return lo, hi


def cmd_predict(args) -> int:
    from study_site.predict import predict_stimulus_set
    from study_site.simulate import parse_observer

    cfg = parse_observer(args.observer)
    views, _ = predict_stimulus_set(args.stimuli, n=args.trials, seed=args.seed, config=cfg,
                                    time_limit_s=args.time_limit, progress=not args.quiet)
    _print_predicted(views)
    from study_site.power import write_predicted_power

    write_predicted_power(args.stimuli, seed=args.seed, progress=not args.quiet)
    print(f"wrote {args.stimuli}/predicted.parquet, predicted_trials.parquet, predicted_power/")
    return 0


def cmd_surfaces(args) -> int:
    from study_site.render_stimuli import add_surfaces

    n = add_surfaces(args.stimuli, threads=args.threads, force=args.force)
    print(f"{args.stimuli}: {n} surface-normal files written")
    return 0


def _print_predicted(views) -> None:
    from evaluation.observer import predicted_table

    formal = views[~views["practice"].astype(bool)]
    t = predicted_table(formal.assign(method=formal["condition"]))
    for r in t.itertuples():
        print(f"predicted {r.method}: confusion {100 * r.confusion_rate:.1f} % (miss {100 * r.p_miss:.1f} %, "
              f"timeout {100 * r.p_timeout:.1f} %), mean time of finds {r.mean_time_found_s:.2f} s "
              f"({r.n_views} stimuli)")


def cmd_build_stimuli(args) -> int:
    from study_site.stimuli import build_stimuli, summarize

    scenes = [x for x in args.practice_scenes.split(",") if x.strip()]
    if args.synthetic_practice < 0 or args.synthetic_practice > 200:
        raise CamoError("--synthetic-practice must be 0-200")
    if not 0 <= args.observer_trials <= 100_000:
        raise CamoError("--observer-trials must be 0-100000")
    if args.copy:
        manifest = build_stimuli(args.eval_dirs, args.out, practice_dirs=args.practice, force=args.force,
                                 practice_scenes=scenes, synthetic_practice_n=args.synthetic_practice)
    else:
        from study_site.render_stimuli import render_stimuli

        manifest = render_stimuli(
            args.eval_dirs, args.out, practice_dirs=args.practice, practice_scenes=scenes, size=args.size,
            views=args.views, spp=args.spp, seed=args.seed, object_frac=_pair(args.object_size, "--object-size"),
            margin=args.margin, synthetic_practice_n=args.synthetic_practice, threads=args.threads, force=args.force,
            noise_match=not args.no_noise_match, denoise=args.denoise,
        )
    print(f"{args.out}: {summarize(manifest)}")
    if args.observer_trials > 0:
        from study_site.predict import predict_stimulus_set

        from study_site.power import write_predicted_power

        views, _ = predict_stimulus_set(args.out, n=args.observer_trials, seed=args.seed)
        _print_predicted(views)
        write_predicted_power(args.out, seed=args.seed)
    return 0


def cmd_make_key(args) -> int:
    import secrets

    path = args.path
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise CamoError(f"{path}: already exists (a new key would change every stored participant hash)") from None
    except OSError as exc:
        raise CamoError(f"{path}: {exc.strerror}") from None
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_hex(32) + "\n")
    print(f"wrote a new 256-bit key to {path} (mode 0600); keep it outside the database and never change it")
    return 0


#: The ``camo study serve`` flags (argparse dest) that set a study config key (:mod:`study_site.config`; the
#: environment's ``CAMO_STUDY_<KEY>`` otherwise).
SERVE_CONFIG = {
    "id_key_file": "ID_HMAC_KEY_FILE",
    "secret_key_file": "SECRET_KEY_FILE",
    "admin_token_file": "ADMIN_TOKEN_FILE",
    "time_limit": "TRIAL_TIME_LIMIT_S",
    "practice_trials": "PRACTICE_TRIALS",
    "min_age": "MIN_AGE",
    "completion_code": "COMPLETION_CODE",
    "completion_url": "COMPLETION_URL",
    "consent_file": "CONSENT_FILE",
}


def cmd_serve(args) -> int:
    from study_site import create_app
    from study_site.analysis import resolve_db_url
    from study_site.config import from_env

    if not 0 < args.port < 65536:
        raise CamoError(f"--port must be 1-65535, not {args.port}")
    if not 1 <= args.threads <= 256:
        raise CamoError("--threads must be 1-256")
    if not os.path.isdir(args.stimuli):
        raise CamoError(f"{args.stimuli}: no such stimulus directory")
    if not 10 <= args.connections <= 100_000:
        raise CamoError("--connections must be 10-100000")
    if not 1 <= args.workers <= 64:
        raise CamoError("--workers must be 1-64")
    if args.workers > 1 and args.dev:
        raise CamoError("--workers needs the production server (gunicorn), not --dev")
    cfg = from_env()
    cfg.update({"STIMULI_DIR": args.stimuli, "DATABASE_URL": resolve_db_url(args.db)})
    for flag, key in SERVE_CONFIG.items():
        v = getattr(args, flag)
        if v is not None:
            cfg[key] = v
    if args.dev:
        cfg["DEV"] = True
    app = create_app(cfg)  # every configuration error is a one-line refusal here, before any process starts
    if args.workers > 1:
        app.extensions["camo_study"].db.dispose()
        serve_gunicorn(cfg, args.host, args.port, args.workers, args.threads, args.connections)
        return 0
    serve_app(app, args.host, args.port, threads=args.threads, connections=args.connections, dev=args.dev)
    return 0


def serve_gunicorn(cfg: dict, host: str, port: int, workers: int, threads: int, connections: int = 1000) -> None:
    """The production server: gunicorn's master in this process, ``workers`` forked processes of ``threads``
    threads each (``gthread``), each building its own app (own database pool) from ``cfg``. The same as
    ``gunicorn -w WORKERS -k gthread --threads THREADS 'study_site.wsgi:app'`` with ``CAMO_STUDY_*`` variables."""
    try:
        from gunicorn.app.base import BaseApplication
    except ImportError:
        raise CamoError("--workers needs gunicorn: pip install gunicorn (or use --workers 1: waitress)") from None
    if str(cfg.get("DATABASE_URL", "")).startswith("sqlite"):
        print("note: several processes share one SQLite file (each commit waits for the others' locks); "
              "PostgreSQL is the database for --workers > 1", file=sys.stderr)

    class StudyServer(BaseApplication):
        def load_config(self):
            for k, v in {"bind": f"{host}:{port}", "workers": workers, "threads": threads, "worker_class": "gthread",
                         "worker_connections": connections, "keepalive": 60, "timeout": 60, "graceful_timeout": 10,
                         "accesslog": None, "errorlog": "-", "loglevel": "warning", "proc_name": "camo-study",
                         "preload_app": False}.items():
                self.cfg.set(k, v)

        def load(self):
            from study_site import create_app

            return create_app(cfg)

    print(f"study site on http://{host}:{port}/ (gunicorn, {workers} workers x {threads} threads)", file=sys.stderr,
          flush=True)
    StudyServer().run()


def serve_app(app, host: str, port: int, threads: int = 8, connections: int = 1000, dev: bool = False) -> None:
    """Serve with waitress when installed (production WSGI server), else werkzeug (threaded, no access log)."""
    try:
        if dev:
            raise ImportError
        import waitress
    except ImportError:
        waitress = None
    print(f"study site on http://{host}:{port}/ ({'waitress' if waitress else 'werkzeug'})", file=sys.stderr, flush=True)
    try:
        if waitress is not None:
            # waitress accepts only 100 connections by default; idle keep-alive connections of
            # participants would then block newcomers until channel_timeout.
            waitress.serve(
                app,
                host=host,
                port=port,
                threads=threads,
                connection_limit=connections,
                channel_timeout=60,
                ident="study",
                clear_untrusted_proxy_headers=True,
            )
        else:
            from werkzeug.serving import WSGIRequestHandler, make_server

            class QuietHandler(WSGIRequestHandler):
                def log_request(self, *a, **k):  # no access log: it would record IP addresses
                    pass

            make_server(host, port, app, threaded=True, request_handler=QuietHandler).serve_forever()
    except OSError as exc:
        raise CamoError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    except KeyboardInterrupt:
        pass


def cmd_report(args) -> int:
    from study_site.analysis import write_report

    if args.bootstrap < 0:
        raise CamoError("--bootstrap must be >= 0")
    res = write_report(
        args.db,
        args.out,
        n_boot=args.bootstrap,
        seed=args.seed,
        include_incomplete=args.include_incomplete,
        miss_censor=args.miss_censor,
        stimuli_dir=args.stimuli,
    )
    t = res["table"]
    for r in t.itertuples():
        print(
            f"{r.label} ({r.condition}): confusion {100 * r.confusion_rate:.2f}% (n={r.n_trials}), "
            f"mean/median time found {r.mean_time_found_s:.2f}/{r.median_time_found_s:.2f} s (server clock)"
        )
    b = res.get("baselines")
    if b is not None:
        a = b[b["condition"] == "all"].iloc[0]
        print(
            f"baselines over {a.n_trials} formal trials: centre click {100 * a.centre_click_hit_rate:.1f} %, "
            f"last-practice location {100 * a.last_practice_hit_rate:.1f} %, object area share "
            f"{100 * a.mean_area_share:.1f} %"
        )
    print(f"wrote {args.out}/table_i.md, table_i.csv, km.png, pairwise.csv, trials/participants .csv/.parquet")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="camo")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CamoError as exc:
        print(f"camo: error: {exc}", file=sys.stderr)
        return exc.exit_code


if __name__ == "__main__":
    sys.exit(main())
