"""``camo grid``: run a benchmark grid (objects x scenes x methods x ablations x seeds), resumably.

::

    camo grid run GRID.toml --out DIR [--executor local|ray] [--workers N] [--ray-address ADDR]
                                      [--skip-failed] [--dry-run] [--quiet]
    camo grid status DIR [--json]

Every cell runs its run spec (filled from the grid's ``[optimize]`` options when the grid is loaded, as
``camo optimize`` fills one from its flags) then ``camo evaluate`` in a fresh worker process, into
``DIR/cells/<key>/`` (key: hash of the cell's resolved options). Finished cells (``DONE``) are never redone,
partial ones are resumed from their checkpoint (or restarted), failed ones are recorded (``ERROR``,
``error.log``) and retried by the next run unless ``--skip-failed``. At the end the finished cells' metrics are
merged into ``DIR/metrics.parquet`` / ``.csv`` and the Table II report is written to ``DIR/report/``.

Render threads per cell = max(1, cores // workers) (passed as ``--threads``), so cells never oversubscribe the
cores. The grid file format: :mod:`camo.grid.spec`. The cell folder: :mod:`camo.grid.cell`.
Executors: :mod:`camo.grid.executors` (Ray: ``pip install 'camo-toolkit[cluster]'``).

Nothing heavy is imported here, so ``camo --help`` stays fast.
"""

from __future__ import annotations

import os


def register(sub) -> None:
    from camo_base.ranges import Range

    grid = sub.add_parser("grid", help="run a benchmark grid of optimise + evaluate cells, resumably")
    gsub = grid.add_subparsers(dest="grid_command", metavar="SUBCOMMAND")
    gsub.required = True

    p = gsub.add_parser("run", help="run every unfinished cell of a grid file, then merge metrics and report")
    p.add_argument("grid", metavar="GRID", help="grid file (TOML): scenes, objects, methods, ablations, seeds, "
                   "[optimize], [evaluate]")
    p.add_argument("--out", required=True, help="output folder (cells/, metrics.parquet, report/); rerun to resume")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local process pool (default) or Ray (pip install 'camo-toolkit[cluster]')")
    p.add_argument("--workers", type=Range(int, 1, 1024).arg_type(), default=1,
                   help="cells run at once (default 1); each gets max(1, cores // workers) render threads")
    p.add_argument("--ray-address", metavar="ADDR",
                   help="Ray cluster to use (default: env RAY_ADDRESS; else a local Ray on 127.0.0.1)")
    p.add_argument("--skip-failed", action="store_true", help="do not retry cells that failed before")
    p.add_argument("--dry-run", action="store_true", help="list the cells and their state; run nothing")
    p.add_argument("--quiet", action="store_true", help="no progress bar or messages")
    p.set_defaults(func=_run)

    p = gsub.add_parser("status", help="print done / failed / partial / pending per cell of a grid output folder")
    p.add_argument("out", metavar="DIR", help="output folder of `camo grid run`")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_status)


def _run(args) -> int:
    from camo_base.errors import CamoError
    from camo.grid.runner import run_grid

    address = args.ray_address or (os.environ.get("RAY_ADDRESS") or None if args.executor == "ray" else None)
    if args.ray_address and args.executor != "ray":
        raise CamoError("--ray-address needs --executor ray")
    return run_grid(args.grid, args.out, executor=args.executor, workers=args.workers, ray_address=address,
                    skip_failed=args.skip_failed, dry_run=args.dry_run, progress=not args.quiet)


def _status(args) -> int:
    from camo.grid.runner import status

    return status(args.out, as_json=args.json)
