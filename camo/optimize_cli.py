"""``camo optimize``: argument parsing for an optimisation run (the work is in :mod:`optimizer.optimise.run`)."""

from __future__ import annotations

import dataclasses

import math

from camo_base.errors import CamoError

#: Iteration cap of a stage under --time-budget when no iteration count is given (the budget ends it first).
UNCAPPED = 100_000

METHODS = ("ours", "transparent", "mean", "random", "greedy", "diffusion2d", "ganmouflage", "ganmouflage-paper")


def register(sub) -> None:
    p = sub.add_parser("optimize", help="optimise an object's appearance to hide it in a scene")
    p.add_argument("scene", help="built-in scene name (ENV or ENV:OBJECT) or a scene pack .toml")
    p.add_argument("--out", required=True, help="run directory (must be new or empty unless --resume/--overwrite)")
    p.add_argument("--method", default="ours", help=f"method: {', '.join(METHODS)}")
    p.add_argument("--preset", choices=("fast", "paper"), default="fast",
                   help="fast (default): least-squares albedo warm start, transmittance start 0.75, proximal L1 step on "
                        "the displacement, 20 + 4 iterations; paper: the paper's schedule exactly (grey start, constant rates 1e-2 / 1e-1, "
                        "50 + 20 iterations, silhouette term on every view). Explicit flags override either")
    p.add_argument("--time-budget", type=float, metavar="SECONDS",
                   help="stop when warm start + Stage 1 + Stage 2 iterations have taken this long (Stage 1 gets 80 %%; "
                        "without --iterations / --stage2-iterations the iteration caps are lifted)")
    p.add_argument("--warm-start", choices=("on", "off"),
                   help="least-squares albedo start (fast: on unless --init sets albedo; paper: off)")
    p.add_argument("--lr-schedule", choices=("cosine", "constant"), help="learning-rate schedule (both presets: constant)")
    p.add_argument("--lr-maps", type=float, help="Adam rate of the BSDF maps (paper: 1e-2)")
    p.add_argument("--lr-displacement", type=float, help="Adam rate of the normalised displacement (paper: 1e-1, fast: 5e-2)")
    p.add_argument("--snapshot-every", type=int, default=0, metavar="N",
                   help="save the parameters every N iterations to snapshots/ (bench/bench_convergence.py scores them)")
    p.add_argument("--iterations", type=int, help="Stage 1 iterations (paper: 50, fast: 20)")
    p.add_argument("--resolution", type=int, help="render width = height in pixels (default: the pack's)")
    p.add_argument("--spp", type=int, help="samples per pixel per training render (default 4)")
    p.add_argument("--target-spp", type=int, help="samples per pixel of background targets and final renders (default 64)")
    p.add_argument("--views", type=int, help="number of orbit views (default: the pack's, 16)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ablate", default="", help="comma list: pose,displacement,bsdf,transmittance,inpainting")
    p.add_argument("--init", default="", metavar="KEY=VALUE,...",
                   help="initial material values, overriding the scene pack's [material]: albedo (grey, or R/G/B), "
                        "metallic, roughness, transmittance in [0, 1] (paper: 0.5, 0, 0, 0.5)")
    p.add_argument("--loss", choices=("gated", "mse"), default="gated", help="luminance-gated (Eq. 9) or plain MSE")
    p.add_argument("--map-resolution", type=int, help="BSDF map resolution (paper: 800)")
    p.add_argument("--displacement-resolution", type=int, help="displacement map resolution (default 256)")
    p.add_argument("--displacement-bound", type=float, help="displacement amplitude bound, fraction of object size (default 0.02)")
    p.add_argument("--target-vertices", type=int, help="remeshing target (paper: ~30,000)")
    p.add_argument("--domain", choices=("object+shadow", "frame"), help="loss pixel domain (default object+shadow)")
    p.add_argument("--stages", default="1,2", help="stages to run: 1 (background matching), 2 (synthesis); default 1,2")
    p.add_argument("--stage2-iterations", type=int, help="Stage 2 iterations (paper: 20, fast: 4)")
    p.add_argument("--stage2-backend", choices=("patch", "diffusers"), help="Stage 2 inpainter (default: patch, offline)")
    p.add_argument("--stage2-strength", type=float, help="Stage 2 noise strength t_start in (0, 1] (default 0.5)")
    p.add_argument("--stage2-fixed-displacement", action="store_true",
                   help="Stage 2 refines the BSDF maps only and keeps Stage 1's displacement (default: refines both, "
                        "as the paper; from roughness 0 under the sun, fixed gave fewer glints in novel views, docs/results)")
    p.add_argument("--sdxl-path", help="local SDXL inpainting pipeline folder (diffusers backend)")
    p.add_argument("--controlnet-path", help="local depth ControlNet folder (diffusers backend)")
    p.add_argument("--silhouette-every", type=int,
                   help="projective training: the silhouette gradient on a random 1/N of the views per step, "
                        "weighted N (default 4; 1 = every view)")
    p.add_argument("--checkpoint-every", type=int, default=10)
    p.add_argument("--no-planner", action="store_true", help="always full path tracing (max_depth 12, projective on)")
    p.add_argument("--shadow-gradients", action="store_true", help="let shadow boundaries drive the pose (~35x cost)")
    p.add_argument("--threads", type=int, help="CPU threads for the LLVM backend")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing run directory's files")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_optimize)


def _positive(name: str, value, minimum=1):
    if value is not None and value < minimum:
        raise CamoError(f"--{name} must be >= {minimum}, got {value}")
    return value


def parse_init(text: str) -> dict:
    """``--init``: ``"roughness=0.5,albedo=0.4/0.3/0.2"`` -> MaterialSpec field values; one-line errors."""
    out: dict = {}
    for item in (x.strip() for x in text.split(",")):
        if not item:
            continue
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or key not in ("albedo", "metallic", "roughness", "transmittance"):
            raise CamoError(f"--init takes KEY=VALUE with KEY one of albedo, metallic, roughness, transmittance; got {item!r}")
        if key in out:
            raise CamoError(f"--init sets {key} twice")
        try:
            nums = [float(v) for v in val.split("/")]
        except ValueError:
            raise CamoError(f"--init {key} must be a number in [0, 1]{' or R/G/B' if key == 'albedo' else ''}, got {val!r}") from None
        if len(nums) not in ((1, 3) if key == "albedo" else (1,)) or not all(0.0 <= v <= 1.0 for v in nums):
            raise CamoError(f"--init {key} must be {'a grey or R/G/B values' if key == 'albedo' else 'a number'} in [0, 1], got {val!r}")
        out[key] = tuple(nums * 3 if len(nums) == 1 else nums) if key == "albedo" else nums[0]
    return out


def config_from_args(args):
    from camo.cli import load_scene_arg, parse_ablate
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.optimise.run import RunConfig, appearance_for
    from optimizer.optimise.stage1 import Stage1Config
    from optimizer.optimise.stage2 import Stage2Config

    if args.method not in METHODS:
        raise CamoError(f"unknown --method {args.method!r}; choose one of: {', '.join(METHODS)}")
    for name in ("iterations", "spp", "target_spp", "map_resolution", "displacement_resolution", "checkpoint_every",
                 "stage2_iterations", "silhouette_every"):
        _positive(name.replace("_", "-"), getattr(args, name))
    _positive("target-vertices", args.target_vertices, 100)
    if args.displacement_bound is not None and not (0.0 <= args.displacement_bound <= 0.5):
        raise CamoError(f"--displacement-bound must be in [0, 0.5], got {args.displacement_bound}")
    pack = load_scene_arg(args.scene, args)
    if args.target_vertices:
        pack.object = dataclasses.replace(pack.object, target_vertices=args.target_vertices)
    ablate = parse_ablate(args.ablate)
    init = parse_init(args.init)
    for key, part in (("transmittance", "transmittance"), ("transmittance", "bsdf"), ("metallic", "bsdf"), ("roughness", "bsdf")):
        if key in init and part in ablate:
            raise CamoError(f"--init {key} conflicts with --ablate {part} (the ablation fixes it)")
    from optimizer.optimise.schedule import PRESETS

    preset = PRESETS[args.preset]
    # the preset's starting material (every method: a baseline's loss domain and targets stay those of `ours`;
    # painted baselines set their own maps)
    start = {k: v for k, v in preset["material"].items() if k not in init}
    if init or start:
        pack.material = dataclasses.replace(pack.material, **start, **init)
    app = appearance_for(ablate, dataclasses.replace(AppearanceConfig(), **preset["appearance"]))
    for name in ("lr_maps", "lr_displacement"):
        value = getattr(args, name)
        if value is not None:
            if not (math.isfinite(value) and 0.0 < value <= 10.0):
                raise CamoError(f"--{name.replace('_', '-')} must be in (0, 10], got {value}")
            app = dataclasses.replace(app, **{name: value})
    if args.time_budget is not None and not (math.isfinite(args.time_budget) and args.time_budget > 0):
        raise CamoError(f"--time-budget must be a positive number of seconds, got {args.time_budget}")
    if args.snapshot_every < 0:
        raise CamoError(f"--snapshot-every must be >= 0, got {args.snapshot_every}")
    if args.map_resolution:
        app = dataclasses.replace(app, map_resolution=args.map_resolution)
    if args.displacement_resolution:
        app = dataclasses.replace(app, displacement_resolution=args.displacement_resolution)
    if args.displacement_bound is not None:
        app = dataclasses.replace(app, displacement_bound=args.displacement_bound)
    if "transmittance" in ablate or "bsdf" in ablate:
        pack.material = dataclasses.replace(pack.material, transmittance=0.0)
    s1 = Stage1Config(seed=args.seed, loss=args.loss, **preset["stage1"])
    if args.time_budget and args.iterations is None:
        s1 = dataclasses.replace(s1, iterations=UNCAPPED)
    if args.warm_start:
        s1 = dataclasses.replace(s1, warm_start=args.warm_start == "on")
    elif "albedo" in init:  # an explicit starting albedo is kept (the warm start would replace it)
        s1 = dataclasses.replace(s1, warm_start=False)
    if args.lr_schedule:
        s1 = dataclasses.replace(s1, lr_schedule=args.lr_schedule)
    for name in ("iterations", "spp", "target_spp", "domain", "silhouette_every"):
        if getattr(args, name) is not None:
            s1 = dataclasses.replace(s1, **{name: getattr(args, name)})
    try:
        stages = tuple(sorted({int(x) for x in args.stages.split(",") if x.strip()}))
    except ValueError:
        raise CamoError(f"--stages must be a comma list of 1 and 2, got {args.stages!r}") from None
    if not stages or set(stages) - {1, 2} or 1 not in stages:
        raise CamoError(f"--stages must include 1 and may include 2, got {args.stages!r}")
    if "inpainting" in ablate:
        stages = (1,)
    s2 = Stage2Config(**preset["stage2"])
    if args.time_budget and args.stage2_iterations is None:
        s2 = dataclasses.replace(s2, iterations=UNCAPPED)
    if args.stage2_iterations:
        s2 = dataclasses.replace(s2, iterations=args.stage2_iterations)
    if args.stage2_backend:
        s2 = dataclasses.replace(s2, backend=args.stage2_backend)
    if args.stage2_strength is not None:
        if not (0.0 < args.stage2_strength <= 1.0):
            raise CamoError(f"--stage2-strength must be in (0, 1], got {args.stage2_strength}")
        s2 = dataclasses.replace(s2, strength=args.stage2_strength)
    s2 = dataclasses.replace(s2, sdxl_path=args.sdxl_path, controlnet_path=args.controlnet_path,
                             displacement=not args.stage2_fixed_displacement)
    if 2 in stages and s2.backend == "diffusers" and not (args.sdxl_path and args.controlnet_path):
        raise CamoError("--stage2-backend diffusers needs --sdxl-path and --controlnet-path (local folders; nothing is downloaded)")
    cfg = RunConfig(scene=args.scene, method=args.method, stages=stages, ablate=tuple(sorted(ablate)),
                    checkpoint_every=args.checkpoint_every, planner=not args.no_planner,
                    shadow_gradients=args.shadow_gradients, threads=args.threads, preset=args.preset,
                    time_budget=args.time_budget, snapshot_every=args.snapshot_every,
                    rough_start=args.preset == "fast" and "roughness" not in init,
                    stage1=s1, stage2=s2, appearance=app)
    return pack, cfg


def run_optimize(args) -> int:
    from optimizer.optimise.run import optimize

    pack, cfg = config_from_args(args)
    if args.method != "ours":
        from optimizer.optimise.baselines import run_from_args

        print(f"wrote {run_from_args(args, pack, cfg)}")
        return 0
    out = optimize(pack, cfg, args.out, resume=args.resume, overwrite=args.overwrite, progress=not args.quiet)
    print(f"wrote {out}")
    return 0
