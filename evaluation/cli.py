"""``camo evaluate`` and ``camo report``: argument parsing (the work is in :mod:`evaluation.evaluate` and
:mod:`evaluation.report`). Nothing heavy is imported here, so ``camo --help`` stays fast."""

from __future__ import annotations

#: = evaluation.views.DEFAULT_JITTER (the paper's +-0.25 at radius 4); repeated here so that building the
#: parser imports neither numpy nor the evaluation modules.
DEFAULT_JITTER = 0.25


def register(sub) -> None:
    p = sub.add_parser("evaluate", help="render jittered novel views of run directories and score them (Table II)")
    p.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="output of `camo optimize`")
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
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run_evaluate)

    p = sub.add_parser("report", help="merge evaluation directories into one Table II report")
    p.add_argument("eval_dirs", nargs="+", metavar="EVAL_DIR", help="output of `camo evaluate`")
    p.add_argument("--out", required=True, help="report folder (report.md, report.html, grids/)")
    p.set_defaults(func=run_report)


def run_evaluate(args) -> int:
    from .evaluate import EvalSettings, evaluate, parse_metrics

    settings = EvalSettings(views=args.views, jitter=args.jitter, spp=args.spp, resolution=args.resolution,
                            metrics=parse_metrics(args.metrics), seed=args.seed, lpips_weights=args.lpips_weights,
                            inception_weights=args.inception_weights, dreamsim_weights=args.dreamsim_weights,
                            threads=args.threads, progress=not args.quiet)
    evaluate(args.run_dirs, args.out, settings)
    print(f"wrote {args.out}")
    return 0


def run_report(args) -> int:
    from .report import write_report

    paths = write_report(args.eval_dirs, args.out)
    print(f"wrote {paths['md']}")
    return 0
