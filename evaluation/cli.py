"""``camo evaluate`` and ``camo report``: argument parsing (the work is in :mod:`evaluation.evaluate` and
:mod:`evaluation.report`). Nothing heavy is imported here, so ``camo --help`` stays fast."""

from __future__ import annotations

#: = evaluation.views.DEFAULT_JITTER (the paper's +-0.25 at radius 4); repeated here so that building the
#: parser imports neither numpy nor the evaluation modules.
DEFAULT_JITTER = 0.25


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
    p.add_argument("--seconds", type=float, help="what producing --asset / --triplets cost, in seconds (report column)")
    p.add_argument("--placement", default="auto", choices=("auto", "scene", "pack"),
                   help="--asset coordinates: scene = already in scene coordinates (camo's result.glb/obj), pack = "
                   "normalised and posed by the scene's [object] (size, rotation, translation); auto (default): "
                   "scene for files camo wrote, else pack")
    p.add_argument("--out", required=True, help="evaluation directory (metrics, renders, report)")
    p.add_argument("--views", type=int, help="evaluation views per run (default: the number of training views; "
                   "more repeats the jitter)")
    p.add_argument("--jitter", type=float, default=DEFAULT_JITTER,
                   help=f"camera offset bound per axis at radius 4, scaled with the radius (default {DEFAULT_JITTER}; "
                   "must be > 0)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel of the evaluation renders (default 64)")
    p.add_argument("--resolution", type=int, help="image width = height in pixels (default: the run's)")
    p.add_argument("--metrics", help="comma list of metrics (default: psnr,ssim,lpips_proxy,sifid_proxy, plus "
                   "lpips/sifid/dreamsim when their weights are given or found)")
    p.add_argument("--seed", type=int, default=0, help="camera jitter and sampler seed (same for every run)")
    p.add_argument("--lpips-weights", metavar="PATH",
                   help="AlexNet trunk (torchvision .pth), or a folder with it and LPIPS v0.1 alex.pth")
    p.add_argument("--inception-weights", metavar="PATH", help="Inception v3 state dict for SIFID")
    p.add_argument("--dreamsim-weights", metavar="PATH", help="DreamSim weights folder (its cache_dir)")
    p.add_argument("--threads", type=int, help="CPU threads for the LLVM backend")
    p.add_argument("--observer-trials", type=int, default=100, metavar="N",
                   help="simulated observer trials per view for the report's predicted Table I (default 100; 0 = "
                   "none; docs/observer.md)")
    p.add_argument("--observer-saliency", metavar="FILE",
                   help="the observer's map from a local TorchScript saliency / camouflaged-object-detection network "
                   "instead of the weight-free one (never downloaded)")
    p.add_argument("--no-planner", action="store_true",
                   help="full path tracing of every full frame (max_depth 12) instead of the measured plan (a pilot "
                   "per scene picks the depth; only the region each object can change is rendered)")
    p.add_argument("--no-noise-match", action="store_true",
                   help="the same spp everywhere (default: pixels where the render with the object is noisier than "
                   "the background get more samples, up to 8x, so noise does not give the object away)")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run_evaluate)

    p = sub.add_parser("report", help="merge evaluation directories into one Table II report")
    p.add_argument("eval_dirs", nargs="+", metavar="EVAL_DIR", help="output of `camo evaluate`")
    p.add_argument("--out", required=True, help="report folder (report.md, report.html, grids/)")
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


def run_evaluate(args) -> int:
    from evaluation.evaluate import EvalSettings, evaluate, parse_metrics
    from evaluation.inputs import finite_seconds

    if args.seconds is not None:
        finite_seconds(args.seconds, "--seconds")

    settings = EvalSettings(views=args.views, jitter=args.jitter, spp=args.spp, resolution=args.resolution,
                            metrics=parse_metrics(args.metrics), seed=args.seed, lpips_weights=args.lpips_weights,
                            inception_weights=args.inception_weights, dreamsim_weights=args.dreamsim_weights,
                            threads=args.threads, progress=not args.quiet, observer_trials=args.observer_trials,
                            observer_saliency=args.observer_saliency, planner=not args.no_planner,
                            noise_match=not args.no_noise_match)
    evaluate(input_specs(args), args.out, settings)
    print(f"wrote {args.out}")
    return 0


def run_report(args) -> int:
    from evaluation.report import write_report

    paths = write_report(args.eval_dirs, args.out)
    print(f"wrote {paths['md']}")
    return 0
