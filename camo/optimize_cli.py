"""``camo optimize``: its flags fill a run spec (:class:`optimizer.optimise.spec.RunSpec`); the work is in
:func:`optimizer.optimise.run.run`.

Every option but those of :data:`EXECUTION` sets one field of the spec (:data:`OPTION_FIELDS`; a method may take an
option for its own options instead: ``--iterations`` is GANmouflage's training iterations, see
``optimizer.optimise.spec.Method.option_names``). An option the chosen method does not read is an error (one line,
exit 2), never ignored. Options default to "absent" (None); what an absent option means is the spec's default, the
preset's or the pack's value.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

from camo_base.errors import CamoError

#: Iteration cap of a stage under --time-budget when no iteration count is given (the budget ends it first).
UNCAPPED = 100_000

#: Every ``--method`` name (optimizer.optimise.spec.METHOD_NAMES; a literal so that ``camo --help`` stays light).
METHODS = ("ours", "transparent", "mean", "random", "greedy", "diffusion2d", "ganmouflage", "ganmouflage-paper")

#: Options that say where and how a run executes, not what it is: never part of the spec.
EXECUTION = ("scene", "spec", "out", "resume", "overwrite", "quiet", "threads")

#: The run spec field each other option sets (its ``dest``, ``-`` as ``_``). ``init`` sets the pack's material,
#: ``no_planner`` and ``stage2_fixed_displacement`` set the negation of their field.
OPTION_FIELDS: dict[str, str] = {
    "method": "method", "seed": "seed", "preset": "preset",
    "resolution": "pack.render.resolution", "views": "pack.cameras.views",
    "target_vertices": "pack.object.target_vertices", "init": "pack.material",
    "spp": "spp.train", "target_spp": "spp.target",
    "iterations": "stage1.iterations", "loss": "stage1.loss", "domain": "stage1.domain",
    "silhouette_every": "stage1.silhouette_every", "warm_start": "stage1.warm_start",
    "lr_schedule": "stage1.lr_schedule", "pose_search": "stage1.pose_search",
    "average": "stage1.average", "roughness_search": "stage1.roughness_search",
    "stage2_iterations": "stage2.iterations", "stage2_backend": "stage2.backend", "stage2_strength": "stage2.strength",
    "stage2_fixed_displacement": "stage2.displacement", "sdxl_path": "stage2.sdxl_path",
    "controlnet_path": "stage2.controlnet_path",
    "lr_maps": "appearance.lr_maps", "lr_displacement": "appearance.lr_displacement",
    "grad_blur": "appearance.grad_blur",
    "map_resolution": "appearance.map_resolution", "displacement_resolution": "appearance.displacement_resolution",
    "displacement_bound": "appearance.displacement_bound",
    "stages": "stages", "ablate": "ablate", "time_budget": "time_budget", "checkpoint_every": "checkpoint_every",
    "snapshot_every": "snapshot_every", "no_planner": "planner", "shadow_gradients": "shadow_gradients",
    "holdout_views": "holdout.views", "holdout_every": "holdout.every", "holdout_spp": "holdout.spp",
    "patience": "holdout.patience",
}

#: What an absent option means, for the options whose absence is a fixed value (not the pack's or the preset's):
#: the run spec's defaults, written as the option would be. ``camo grid`` drops an option set to this value from a
#: cell's key (the same work); tests/test_optimize_cli.py checks it against the spec.
ABSENT: dict[str, Any] = {"seed": 0, "preset": "fast", "ablate": "", "init": "", "stages": "1,2",
                          "checkpoint_every": 10, "snapshot_every": 0, "method": "ours"}


#: Option values ``camo grid`` also leaves out of cell keys although they are no longer what an absent option
#: means: ``loss = "gated"`` was the default until the fast preset took the squared error (2026-11-24), and grid
#: folders made before keep their keys. Known limit: a grid naming ``loss = "gated"`` and one naming no loss get the
#: same cell keys; give such grids their own output folder (each cell's config.toml records the loss it ran).
KEY_STABLE: dict[str, Any] = {"loss": "gated"}


def register(sub) -> None:
    p = sub.add_parser("optimize", help="optimise an object's appearance to hide it in a scene")
    p.add_argument("scene", nargs="?",
                   help="built-in scene name (ENV or ENV:OBJECT) or a scene pack .toml (or give --spec instead)")
    p.add_argument("--spec", metavar="CONFIG",
                   help="run the spec a run directory recorded (its config.toml, or the directory): the same run "
                        "again, in --out; only --seed may change it (a replicate), every other spec option is refused")
    p.add_argument("--out", required=True, help="run directory (must be new or empty unless --resume/--overwrite)")
    p.add_argument("--method", help=f"method: {', '.join(METHODS)} (default ours)")
    p.add_argument("--preset", choices=("fast", "paper"),
                   help="fast (default): least-squares albedo warm start, transmittance start 0.75, squared-error loss, "
                        "proximal L1 step on the displacement, map gradients blurred by 2 texels, 60 + 4 "
                        "iterations, a 16-turn pose search first, the best iterate on 4 held-out views is the result; paper: the paper's schedule exactly (Eq. 9 loss, grey start, constant rates 1e-2 / "
                        "1e-1, 50 + 20 iterations, silhouette term on every view). Explicit flags override either")
    p.add_argument("--time-budget", type=float, metavar="SECONDS",
                   help="stop when warm start + Stage 1 + Stage 2 iterations have taken this long (Stage 1 gets 80 %%; "
                        "without --iterations / --stage2-iterations the iteration caps are lifted)")
    p.add_argument("--warm-start", choices=("on", "off"),
                   help="least-squares albedo start (fast: on unless --init sets albedo; paper: off)")
    p.add_argument("--lr-schedule", choices=("cosine", "constant"), help="learning-rate schedule (both presets: constant)")
    p.add_argument("--lr-maps", type=float, help="Adam rate of the BSDF maps (both presets: 1e-2)")
    p.add_argument("--lr-displacement", type=float, help="Adam rate of the normalised displacement (paper: 1e-1, fast: 5e-2)")
    p.add_argument("--grad-blur", type=float, metavar="TEXELS",
                   help="blur the BSDF maps' gradients by a Gaussian of this sigma before each Adam step (fast: 2; paper "
                        "and 0: off); averages the per-texel Monte Carlo noise that otherwise speckles the maps")
    p.add_argument("--average", type=float, metavar="DECAY",
                   help="the result is the moving average of the iterates with this decay (about the last "
                        "1 / (1 - DECAY) iterates; 0: the iterate itself)")
    p.add_argument("--roughness-search", metavar="R1,R2,...",
                   help="before Stage 1, warm-start each of these uniform starting roughness values and start from the "
                        "one that scores best on the held-out views (fast: 0.5,0.7; paper, 'off' and --init "
                        "roughness=X: off)")
    p.add_argument("--snapshot-every", type=int, metavar="N",
                   help="save the parameters every N iterations to snapshots/ (bench/bench_convergence.py scores them)")
    p.add_argument("--pose-search", type=int, metavar="N",
                   help="before Stage 1, try N turns of the object about the vertical axis and start from the one whose "
                        "shadow and reflections change the ground least (fast: 16; paper and 0: off)")
    p.add_argument("--holdout-views", type=int, metavar="N",
                   help="held-out jittered views (own seed stream, never the evaluation's) that pick the result among "
                        "the iterates checked every --holdout-every iterations and at each stage's end (fast: 4; paper "
                        "and 0: the last iterate is the result)")
    p.add_argument("--holdout-every", type=int, metavar="N", help="iterations between held-out checks (fast: 10)")
    p.add_argument("--holdout-spp", type=int, metavar="N", help="samples per pixel of the held-out renders (fast: 16)")
    p.add_argument("--patience", type=int, metavar="N",
                   help="stop Stage 1 after N held-out checks in a row without a better iterate (default 0: never)")
    p.add_argument("--iterations", type=int, help="Stage 1 iterations (paper: 50, fast: 60)")
    p.add_argument("--resolution", type=int, help="render width = height in pixels (default: the pack's)")
    p.add_argument("--spp", type=int, help="samples per pixel of each training render (default 4; the run spec's spp.train)")
    p.add_argument("--target-spp", type=int, help="samples per pixel of the background targets, the loss domain, the warm "
                   "start and the final render (default 64; spp.target)")
    p.add_argument("--views", type=int, help="number of orbit views (default: the pack's, 16)")
    p.add_argument("--seed", type=int, help="the run seed (default 0): every random stream derives from it "
                   "(camo_base.seeds)")
    p.add_argument("--ablate", help="comma list: pose,displacement,bsdf,transmittance,inpainting")
    p.add_argument("--init", metavar="KEY=VALUE,...",
                   help="initial material values, overriding the scene pack's [material]: albedo (grey, or R/G/B), "
                        "metallic, roughness, transmittance in [0, 1] (paper: 0.5, 0, 0, 0.5)")
    p.add_argument("--loss", choices=("gated", "mse"),
                   help="luminance-gated (Eq. 9; paper preset) or squared error (fast preset: unbiased at a few spp)")
    p.add_argument("--map-resolution", type=int, help="BSDF map resolution (paper: 800)")
    p.add_argument("--displacement-resolution", type=int, help="displacement map resolution (default 256)")
    p.add_argument("--displacement-bound", type=float, help="displacement amplitude bound, fraction of object size (default 0.02)")
    p.add_argument("--target-vertices", type=int, help="remeshing target (paper: ~30,000)")
    p.add_argument("--domain", choices=("object+shadow", "frame"), help="loss pixel domain (default object+shadow)")
    p.add_argument("--stages", help="stages to run: 1 (background matching), 2 (synthesis); default 1,2")
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
    p.add_argument("--checkpoint-every", type=int, metavar="N", help="checkpoint every N iterations (default 10)")
    p.add_argument("--no-planner", action="store_true", help="always full path tracing (max_depth 12, projective on)")
    p.add_argument("--shadow-gradients", action="store_true", help="let shadow boundaries drive the pose (~35x cost)")
    p.add_argument("--threads", type=int, help="CPU threads for the LLVM backend")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing run directory's files")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_optimize)


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


def option_field(method, dest: str) -> str:
    """The run spec field option ``dest`` sets for ``method`` (an :class:`optimizer.optimise.spec.Method`)."""
    return dict(method.option_names).get(dest) or OPTION_FIELDS[dest]


def flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def given_options(args) -> dict[str, Any]:
    """The spec options given on the command line, ``{dest: value}`` (absent: None, or False for a flag)."""
    out = {}
    for d in OPTION_FIELDS:
        v = getattr(args, d, None)
        if v is not None and v is not False:  # (not `in (None, False)`: 0 == False, and --iterations 0 is given)
            out[d] = v
    return out


def option_applies(method_name: str, dest: str) -> bool:
    """Whether ``method_name`` reads what option ``dest`` sets (execution options apply to every method)."""
    from optimizer.optimise.spec import resolve_method

    if dest not in OPTION_FIELDS:
        return True
    method, _ = resolve_method(method_name)
    return method.reads_path(option_field(method, dest))


def check_options_apply(method_name: str, dests) -> None:
    """CamoError (one line) naming the first option in ``dests`` that ``method_name`` does not read."""
    from optimizer.optimise.spec import resolve_method

    method, _ = resolve_method(method_name)
    for d in dests:
        if d not in OPTION_FIELDS:
            continue
        field = option_field(method, d)
        if not method.reads_path(field):
            takes = sorted(flag(x) for x in OPTION_FIELDS if method.reads_path(option_field(method, x)))
            raise CamoError(f"{flag(d)} does not apply to --method {method_name} (it sets {field}, which "
                            f"{method.name} does not use); {method_name} takes {', '.join(takes)}")


def field_names(method) -> dict[str, str]:
    """``{spec field: --flag}`` for messages about a spec built from flags."""
    out = {option_field(method, d): flag(d) for d in OPTION_FIELDS}
    out["planner"] = "--no-planner"
    out["stage2.displacement"] = "--stage2-fixed-displacement"
    return out


#: Options whose value is not the field's value as given (read and converted by :func:`spec_from_args` itself).
_SPECIAL = ("method", "preset", "resolution", "views", "target_vertices", "init", "ablate", "stages", "warm_start",
            "no_planner", "stage2_fixed_displacement", "roughness_search")


def parse_roughness_list(text: str) -> tuple[float, ...]:
    """``--roughness-search``: ``R1,R2,...`` (numbers in [0, 1]) or ``off`` / empty -> a tuple; CamoError otherwise."""
    if text.strip().lower() in ("", "off", "none"):
        return ()
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise CamoError(f"--roughness-search must be a comma list of numbers in [0, 1] or 'off', got {text!r}") from None
    return values


def spec_from_args(args):
    """The run spec of ``camo optimize`` arguments; CamoError (one line) for bad input or an option the method does
    not use. Applies the preset (``optimizer.optimise.schedule.PRESETS``) and the option interplay (``--init``,
    ``--ablate``, ``--time-budget``) the way ``camo optimize`` always has."""
    from camo.cli import load_scene_arg, parse_ablate
    from optimizer.optimise.run import appearance_for
    from optimizer.optimise.schedule import PRESETS
    from optimizer.optimise.holdout import HoldoutSettings
    from optimizer.optimise.spec import RunSpec, SppSettings, resolve_method
    from optimizer.optimise.stage1 import Stage1Settings
    from optimizer.optimise.stage2 import Stage2Settings
    from optimizer.rendering.appearance import AppearanceConfig

    method_name = args.method or ABSENT["method"]
    method, make_options = resolve_method(method_name)
    given = given_options(args)
    check_options_apply(method_name, given)
    # the pack's own [render] spp is not a run's: --spp is spp.train only
    pack = load_scene_arg(args.scene, argparse.Namespace(resolution=args.resolution, views=args.views))
    if args.target_vertices is not None:
        pack.object = dataclasses.replace(pack.object, target_vertices=args.target_vertices)
    ablate = parse_ablate(args.ablate or "")
    init = parse_init(args.init or "")
    for key, part in (("transmittance", "transmittance"), ("transmittance", "bsdf"), ("metallic", "bsdf"), ("roughness", "bsdf")):
        if key in init and part in ablate:
            raise CamoError(f"--init {key} conflicts with --ablate {part} (the ablation fixes it)")
    preset_name = args.preset or ABSENT["preset"]
    preset = PRESETS[preset_name]
    # the preset's starting material (every method: a baseline's loss domain and targets stay those of `ours`;
    # painted baselines set their own maps)
    start = {k: v for k, v in preset["material"].items() if k not in init}
    if init or start:
        pack.material = dataclasses.replace(pack.material, **start, **init)
    if "transmittance" in ablate or "bsdf" in ablate:
        pack.material = dataclasses.replace(pack.material, transmittance=0.0)
    # every other option sets its field as given: group them by table
    tables: dict[str, dict[str, Any]] = {"": {}, "spp": {}, "stage1": {}, "stage2": {}, "appearance": {}, "holdout": {},
                                         "options": {}}
    for d, value in given.items():
        if d not in _SPECIAL:
            head, _, rest = option_field(method, d).partition(".")
            if rest:
                tables[head][rest] = value
            else:
                tables[""][head] = value
    app = appearance_for(ablate, dataclasses.replace(AppearanceConfig(), **preset["appearance"]))
    app = dataclasses.replace(app, **tables["appearance"])
    s1 = dataclasses.replace(Stage1Settings(**preset["stage1"]), **tables["stage1"])
    holdout = dataclasses.replace(HoldoutSettings(**preset["holdout"]), **tables["holdout"])
    s2 = dataclasses.replace(Stage2Settings(**preset["stage2"]), **tables["stage2"],
                             displacement=not args.stage2_fixed_displacement)
    if args.time_budget and args.iterations is None:
        s1 = dataclasses.replace(s1, iterations=UNCAPPED)
    if args.time_budget and args.stage2_iterations is None:
        s2 = dataclasses.replace(s2, iterations=UNCAPPED)
    if args.warm_start:
        s1 = dataclasses.replace(s1, warm_start=args.warm_start == "on")
    elif "albedo" in init:  # an explicit starting albedo is kept (the warm start would replace it)
        s1 = dataclasses.replace(s1, warm_start=False)
    if args.roughness_search is not None:
        s1 = dataclasses.replace(s1, roughness_search=parse_roughness_list(args.roughness_search))
    elif "roughness" in init or "bsdf" in ablate or not holdout.views:
        # an explicit (or ablated) starting roughness is kept; without held-out views there is nothing to score on
        s1 = dataclasses.replace(s1, roughness_search=())
    stages = (1, 2)
    if args.stages is not None:
        try:
            stages = tuple(sorted({int(x) for x in args.stages.split(",") if x.strip()}))
        except ValueError:
            raise CamoError(f"--stages must be a comma list of 1 and 2, got {args.stages!r}") from None
        if not stages or set(stages) - {1, 2} or 1 not in stages:
            raise CamoError(f"--stages must include 1 and may include 2, got {args.stages!r}")
    if "inpainting" in ablate:
        stages = (1,)
    options = make_options()
    for path, value in tables["options"].items():
        options = _set_option(options, path.split("."), value)
    spec = RunSpec(scene=args.scene, pack=pack, method=method_name, preset=preset_name, stages=stages,
                   ablate=tuple(ablate), planner=not args.no_planner, rough_start=preset_name == "fast" and "roughness" not in init, spp=SppSettings(**tables["spp"]),
                   stage1=s1, stage2=s2, appearance=app, holdout=holdout, options=options, **tables[""])
    # what the method does not read goes back to its default (the preset's values for `ours` among them): the spec
    # records only what the method reads; every option given was checked above to be read
    return spec.normalised().validate(field_names(method))


def _set_option(options, path: list[str], value):
    """``options`` with the field at ``path`` (``["backend_options", "sdxl_path"]``: a key of a dict field) set."""
    if len(path) == 1:
        return dataclasses.replace(options, **{path[0]: value})
    d = dict(getattr(options, path[0]) or {})
    d[path[1]] = value
    return dataclasses.replace(options, **{path[0]: d})


def spec_from_file(path: str, seed: int | None = None):
    """The run spec recorded in ``path`` (a run directory's ``config.toml`` or the directory), with ``seed`` replaced
    when given; CamoError (one line) for a missing file, a config.toml from before run specs, or a bad spec."""
    from pathlib import Path

    from camo_base.documents import read_toml
    from optimizer.assets.rundir import read_config, spec_of_config
    from optimizer.optimise.spec import RunSpec

    p = Path(path)
    run_dir = p if p.is_dir() else p.parent
    if not p.is_dir() and not p.is_file():
        raise CamoError(f"--spec {path}: no such file or run directory")
    cfg = read_config(run_dir) if p.is_dir() else read_toml(p, "--spec")
    data = spec_of_config(cfg, run_dir)
    if seed is not None:
        data["seed"] = seed
    spec = RunSpec.from_dict(data, where=str(p))
    return spec.validate()


def spec_of(args):
    """The run spec of ``camo optimize`` arguments: from the flags, or from ``--spec`` (then only ``--seed``)."""
    if args.spec is None:
        if args.scene is None:
            raise CamoError("give a SCENE (built-in name or scene pack) or --spec CONFIG")
        return spec_from_args(args)
    if args.scene is not None:
        raise CamoError("give a SCENE or --spec CONFIG, not both (the spec names its scene)")
    other = sorted(flag(d) for d in given_options(args) if d != "seed")
    if other:
        raise CamoError(f"--spec runs the recorded spec as written; {other[0]} would change it (edit a copy of the "
                        "config.toml instead, or give the scene and flags)")
    return spec_from_file(args.spec, args.seed)


def run_optimize(args) -> int:
    from optimizer.optimise.run import run

    spec = spec_of(args)
    out = run(spec, args.out, resume=args.resume, overwrite=args.overwrite, progress=not args.quiet, threads=args.threads)
    print(f"wrote {out}")
    return 0
