"""``camo evaluate`` and ``camo report``: argument parsing (the work is in :mod:`evaluation.evaluate` and
:mod:`evaluation.report`). Nothing heavy is imported here, so ``camo --help`` stays fast."""

from __future__ import annotations

from typing import Any, Mapping

from camo_base.helptext import Deferred
from evaluation.ranges import RANGES

#: = evaluation.views.DEFAULT_JITTER (the paper's +-0.25 at radius 4); repeated here so that building the
#: parser imports neither numpy nor the evaluation modules.
DEFAULT_JITTER = 0.25

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
    p.add_argument("--views", type=RANGES["views"].arg_type(), help="evaluation views per run (default: the number of training views; "
                   "more repeats the jitter)")
    p.add_argument("--jitter", type=RANGES["jitter"].arg_type(), default=DEFAULT_JITTER,
                   help=f"camera offset bound per axis at radius 4, scaled with the radius (default {DEFAULT_JITTER}; "
                   "must be > 0)")
    p.add_argument("--spp", type=RANGES["spp"].arg_type(), default=64, help="samples per pixel of the evaluation renders (default 64)")
    p.add_argument("--resolution", type=RANGES["resolution"].arg_type(), help="image width = height in pixels (default: the run's)")
    p.add_argument("--metrics", help=Deferred(_metrics_help))  # (the registry imports torch: only for --help)
    p.add_argument("--seed", type=RANGES["seed"].arg_type(), default=0, help="camera jitter and sampler seed (same for every run)")
    p.add_argument("--weights", metavar="NAME=PATH[,NAME=PATH]",
                   help="weights of learned metrics other than the installed ones, per metric (what a path may be: "
                   "docs/evaluation.md), e.g. lpips=DIR_OR_TRUNK,sifid=INCEPTION.pth,dreamsim=DIR")
    for flag, (metric, what) in WEIGHTS_FLAGS.items():
        p.add_argument(f"--{flag}", metavar="PATH", help=f"= --weights {metric}=PATH: {what}")
    p.add_argument("--threads", type=RANGES["threads"].arg_type(), help="CPU threads for the LLVM backend")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run_evaluate, setting_names=lambda name, args: "--" + name.replace("_", "-")
                   if name in SETTINGS or name in ("metrics", "weights") else name)

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


#: ``camo evaluate`` options that are :class:`evaluation.evaluate.EvalSettings` fields of the same name.
SETTINGS = ("views", "jitter", "spp", "resolution", "seed", "threads")

#: Short flags for ``--weights NAME=PATH`` of the built-in learned metrics (kept for existing command lines and
#: grids): flag -> (metric, what the path is). A new metric needs none: ``--weights`` takes any metric whose
#: record has ``from_path`` (:class:`evaluation.metrics._common.Metric`).
WEIGHTS_FLAGS = {
    "lpips-weights": ("lpips", "an AlexNet trunk (torchvision layout, .pth or .safetensors), or a folder with the "
                      "trunk and the v0.1 heads (alex.pth, or the files `camo data fetch "
                      "data_manifests/lpips_weights.toml` lands)"),
    "inception-weights": ("sifid", "Inception v3 state dict for SIFID"),
    "dreamsim-weights": ("dreamsim", "DreamSim weights folder (its cache_dir)"),
}


def parse_weights(values: Mapping[str, Any]) -> dict[str, str]:
    """``{metric: path}`` of ``--weights NAME=PATH[,NAME=PATH]`` and the short flags (:data:`WEIGHTS_FLAGS`);
    CamoError (one line) for an item without ``=`` or a metric given twice. The paths are checked by the metrics
    (:func:`evaluation.evaluate.weights_of`)."""
    from camo_base.errors import CamoError

    out: dict[str, str] = {}

    def put(name: str, path: str, where: str) -> None:
        if not name or not path:
            raise CamoError(f"{where}: expected NAME=PATH, e.g. lpips=/path/to/weights")
        if name in out:
            raise CamoError(f"{where}: weights for {name} given twice")
        out[name] = path

    for item in (values.get("weights") or "").split(","):
        if item.strip():
            name, _, path = item.strip().partition("=")
            put(name.strip(), path.strip(), f"--weights {item.strip()}")
    for flag, (metric, _) in WEIGHTS_FLAGS.items():
        if values.get(flag.replace("-", "_")):
            put(metric, str(values[flag.replace("-", "_")]), f"--{flag}")
    return out


def evaluation_settings(values: Mapping[str, Any]):
    """The :class:`evaluation.evaluate.EvalSettings` of ``camo evaluate`` option values (``{dest: value}``, as the
    parser or a grid's ``[evaluate]`` table gives them; absent ones take the flags' defaults)."""
    from evaluation.evaluate import EvalSettings, parse_metrics

    kw = {k: values[k] for k in SETTINGS if values.get(k) is not None}
    return EvalSettings(**kw, metrics=parse_metrics(values.get("metrics")), weights=parse_weights(values),
                        progress=not values.get("quiet", False))


def run_evaluate(args) -> int:
    from evaluation.evaluate import evaluate

    evaluate(input_specs(args), args.out, evaluation_settings(vars(args)))
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
