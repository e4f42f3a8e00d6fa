"""``camo evaluate`` and ``camo report``: argument parsing (the work is in :mod:`evaluation.evaluate` and
:mod:`evaluation.report`). ``camo evaluate``'s setting flags are the options of :mod:`evaluation.settings` (one
flag per option, its type, range and help from there); the flags given become a plain ``{option: value}`` mapping
and :meth:`evaluation.settings.EvalSettings.from_options` makes the settings of it, as a grid's ``[evaluate]`` table
does. Library errors name settings; ``camo`` shows them as these flags. Nothing heavy is imported here, so ``camo
--help`` stays fast."""

from __future__ import annotations

from typing import Any

from camo_base.helptext import Deferred
from evaluation.ranges import RANGES
from evaluation.settings import OPTIONS

def _metrics_help() -> str:
    from evaluation.metrics.registry import metrics_help

    return metrics_help()


def register(sub) -> None:
    p = sub.add_parser("evaluate", help="render jittered novel views of run directories and external assets, score "
                       "them and given image triplets (Table II)")
    p.add_argument("run_dirs", nargs="*", metavar="RUN_DIR", help="output of `camo optimize`")
    p.add_argument("--asset", action="append", default=[], metavar="FILE",
                   help="a glTF/GLB or OBJ+MTL result of any method, placed in --scene (repeatable)")
    p.add_argument("--triplets", action="append", default=[], metavar="DIR",
                   help="a folder of <view>_obj / _bg / _mask images (optional _depth) of a 2D method (repeatable)")
    p.add_argument("--inputs", metavar="LIST.toml", help="many inputs: [[run]], [[asset]], [[triplets]] tables")
    p.add_argument("--scene", help="for --asset: built-in scene (e.g. meadow, split:chair), scene pack .toml or a run "
                   "directory (its scene and cameras); for --triplets: the scene label")
    p.add_argument("--method", help="method label of --asset / --triplets (a run directory's comes from its "
                   "config.toml)")
    p.add_argument("--seconds", type=RANGES["seconds"].arg_type(), help="what producing --asset / --triplets cost, in seconds (report column)")
    p.add_argument("--placement", default="auto", choices=("auto", "scene", "pack"),
                   help="--asset coordinates: scene = already in scene coordinates (camo's result.glb/obj), pack = "
                   "normalised and posed by the scene's [object] (size, rotation, translation); auto (default): "
                   "scene for files camo wrote, else pack")
    p.add_argument("--out", required=True, help="evaluation directory (metrics, renders, report)")
    for opt in OPTIONS.values():
        if opt.kind is bool:
            p.add_argument(opt.flag, action="store_true", help=opt.help)
            continue
        kw: dict[str, Any] = {"help": opt.help, "metavar": opt.metavar, "default": opt.default}
        if opt.name == "metrics":
            kw["help"] = Deferred(_metrics_help)  # (the registry imports torch: only for --help)
        if opt.metric is not None:
            kw["help"] = f"= {OPTIONS['weights'].flag} {opt.metric}=PATH: {opt.help}"
        if opt.range is not None:
            kw["type"] = opt.range.arg_type()
        if opt.choices is not None:
            kw["choices"] = opt.choices
        if opt.const is not None:
            kw.update(nargs="?", const=opt.const)
        p.add_argument(opt.flag, **kw)
    p.set_defaults(func=run_evaluate)  # (camo.cli shows each setting an error names as its flag)

    p = sub.add_parser("report", help="merge evaluation directories into one Table II report")
    p.add_argument("eval_dirs", nargs="+", metavar="EVAL_DIR", help="output of `camo evaluate`")
    p.add_argument("--out", required=True, help="report folder (report.md, report.html, grids/)")
    p.add_argument("--stimuli", nargs="+", default=[], metavar="STIMULI_DIR",
                   help="stimulus sets built from these evaluations (`camo study build-stimuli`): adds the simulated "
                   "observer's predicted Table I on them, its agreement with the metrics and the predicted power "
                   "curve (docs/observer.md)")
    p.add_argument("--video", action="append", default=[], metavar="FILE",
                   help="a `camo video` turntable to show and link as the path-traced reference (repeatable)")
    p.add_argument("--no-viewer", action="store_true",
                   help="no interactive 3D viewer section (it renders each scene's environment panorama once)")
    p.add_argument("--env-width", type=RANGES["env_width"].arg_type(), default=1024,
                   help="width of the viewer's environment panorama "
                   "(default 1024)")
    p.set_defaults(func=run_report)


def input_specs(args) -> list:
    """The inputs named on the command line (RUN_DIRs, --asset, --triplets, --inputs), in that order."""
    from camo_base.errors import CamoError

    from evaluation.inputs import InputSpec, read_input_list

    if (args.asset or args.triplets) and not args.method:
        raise CamoError("--asset / --triplets need --method LABEL (the method's name in the report)")
    if args.asset and not args.scene:
        raise CamoError("--asset needs --scene (a built-in scene, a scene pack .toml or a run directory)")
    if args.seconds is not None and not (args.asset or args.triplets):
        raise CamoError("--seconds applies to --asset / --triplets (a run's seconds come from its summary.json)")
    specs = [InputSpec("run", d) for d in args.run_dirs]
    specs += [InputSpec("asset", a, method=args.method, scene=args.scene, seconds=args.seconds,
                        placement=args.placement) for a in args.asset]
    specs += [InputSpec("triplets", t, method=args.method, scene=args.scene, seconds=args.seconds)
              for t in args.triplets]
    if args.inputs:
        specs += read_input_list(args.inputs)
    if not specs:
        raise CamoError("evaluate needs at least one input: RUN_DIR, --asset FILE, --triplets DIR or --inputs "
                        "LIST.toml")
    return specs


def settings_of(args):
    """The :class:`evaluation.settings.EvalSettings` of ``camo evaluate`` arguments: the setting flags' values as a
    mapping (:meth:`~evaluation.settings.EvalSettings.from_options`, as a grid's ``[evaluate]`` table)."""
    from evaluation.settings import EvalSettings

    return EvalSettings.from_options({name: getattr(args, name) for name in OPTIONS})


def run_evaluate(args) -> int:
    from evaluation.evaluate import evaluate

    evaluate(input_specs(args), args.out, settings_of(args))
    print(f"wrote {args.out}")
    return 0


def run_report(args) -> int:
    from evaluation.report import write_report

    import sys

    from evaluation.viewer import report_sections

    sections = report_sections(args.eval_dirs, args.video, not args.no_viewer, args.env_width,
                               say=lambda m: print(m, file=sys.stderr))
    paths = write_report(args.eval_dirs, args.out, sections, stimuli_dirs=args.stimuli)
    print(f"wrote {paths['md']}")
    return 0
