"""``camo optimize``: its flags are the run options of :mod:`optimizer.optimise.options` (one flag per option, its
type, choices and range from there), plus the execution flags (where and how the run executes: ``--out``,
``--resume``, ...). The flags given become a plain ``{option: value}`` mapping, and
:meth:`optimizer.optimise.spec.RunSpec.from_options` makes the run spec of it; the work is
:func:`optimizer.optimise.run.run`. An option the chosen method does not read is an error (one line, exit 2), never
ignored. Options default to "absent" (None); what an absent option means is the spec's default, the preset's or
the pack's value. Library errors name options and spec fields; :func:`flag_names` shows them as flags.
"""

from __future__ import annotations

from typing import Any

from camo_base.errors import CamoError


def _method_help() -> str:
    from optimizer.optimise.methods import method_help

    return f"the method (default ours): {method_help()}"


def register(sub) -> None:
    from camo_base.helptext import Deferred
    from camo_base.ranges import Range
    from optimizer.optimise.options import OPTIONS, RANGES
    from optimizer.optimise.presets import presets_help

    p = sub.add_parser("optimize", help="optimise an object's appearance to hide it in a scene")
    p.add_argument("scene", nargs="?",
                   help="built-in scene name (ENV or ENV:OBJECT) or a scene pack .toml (or give --spec instead)")
    p.add_argument("--spec", metavar="CONFIG",
                   help="run the spec a run directory recorded (its config.toml, or the directory): the same run "
                        "again, in --out; only --seed may change it (a replicate), every other spec option is refused")
    p.add_argument("--out", required=True,
                   help="run directory (must be new or empty unless --resume/--overwrite; written in a staging "
                        "folder beside it and moved into place only when the run finished)")
    for opt in OPTIONS.values():
        if opt.name == "scene":
            continue
        kw: dict[str, Any] = {"help": opt.help, "metavar": opt.metavar}
        if opt.name == "method":  # (the registry imports every baseline: only when --help shows it)
            kw["help"] = Deferred(_method_help)
        elif opt.name == "preset":
            kw["help"] = f"the defaults the settings start from; explicit flags override them. {presets_help()}"
        if opt.kind is bool:
            p.add_argument(opt.flag, action="store_true", help=opt.help)
            continue
        if opt.range is not None:
            kw["type"] = opt.range.arg_type()
        if opt.choices is not None:
            kw["choices"] = opt.choices
            kw.pop("metavar")
        p.add_argument(opt.flag, **kw)
    p.add_argument("--threads", type=Range.arg_type(RANGES["threads"]), help="CPU threads for the LLVM backend")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its checkpoint (or its unfinished staging folder)")
    p.add_argument("--accept-versions", action="store_true",
                   help="with --resume: continue a run recorded by another spec_version or major version of camo or "
                        "Mitsuba (refused otherwise; the versions of each attempt are appended to config.toml)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing run directory (the old one stays until the new run finished)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_optimize, setting_names=lambda name, args: flag_names(name, args.method))


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def flag_names(name: str, method: str | None = None) -> str:
    """How ``camo optimize`` calls a setting a library error names: the flag of the option (or execution argument)
    that gives it (:func:`optimizer.optimise.spec.option_name`), anything else as it is."""
    from optimizer.optimise.spec import option_name

    opt = option_name(name, method)
    return flag(opt) if opt else name


def given_options(args) -> dict[str, Any]:
    """The run options given on the command line, ``{name: value}`` (absent: None, or False for a switch)."""
    from optimizer.optimise.options import OPTIONS

    out = {}
    for name in OPTIONS:
        v = getattr(args, name, None)
        if v is not None and v is not False:  # (not `in (None, False)`: 0 == False, and --iterations 0 is given)
            out[name] = v
    return out


def spec_of(args):
    """The run spec of ``camo optimize`` arguments: from the flags, or from ``--spec`` (then only ``--seed``)."""
    from optimizer.optimise.spec import RunSpec, spec_from_file

    if args.spec is None:
        if args.scene is None:
            raise CamoError("give a SCENE (built-in name or scene pack) or --spec CONFIG")
        return RunSpec.from_options(given_options(args))
    if args.scene is not None:
        raise CamoError("give a SCENE or --spec CONFIG, not both (the spec names its scene)")
    other = sorted(flag(d) for d in given_options(args) if d not in ("seed", "scene"))
    if other:
        raise CamoError(f"--spec runs the recorded spec as written; {other[0]} would change it (edit a copy of the "
                        "config.toml instead, or give the scene and flags)")
    return spec_from_file(args.spec, args.seed, field="spec")


def run_optimize(args) -> int:
    from optimizer.optimise.run import run

    spec = spec_of(args)
    out = run(spec, args.out, resume=args.resume, overwrite=args.overwrite, progress=not args.quiet,
              threads=args.threads, accept_versions=args.accept_versions)
    print(f"wrote {out}")
    return 0
