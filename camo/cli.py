"""The ``camo`` command line: one CLI, subcommands per package.

``camo doctor | scenes list | scenes render | plan`` live here; the other
commands come from each package's ``register(subparsers)`` (``optimize``:
:mod:`camo.optimize_cli`, ``evaluate`` / ``report``: :mod:`evaluation.cli`, ``video`` / ``view``: :mod:`camo.video_cli`,
``study ...``: :mod:`study_site.cli`, ``data ...``: :mod:`optimizer.scenes.data`,
``grid ...``: :mod:`camo.grid`), imported here by name like any other module.
Helpers those modules share live in the leaf module :mod:`camo.cli_common`
(nothing imports this module back). Every handler takes the parsed arguments
and returns an exit code; a :class:`CamoError` becomes one line on stderr and
exit code 2.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Callable, Sequence

from camo.cli_common import load_scene_arg
from camo_base.errors import CamoError, SettingError
from optimizer.optimise.options import RANGES

#: The ranges of ``camo scenes render`` and ``camo plan``: the run options' (one place a limit is written).
RENDER_RANGES = {"resolution": RANGES["pack.render.resolution"], "views": RANGES["pack.cameras.views"],
                 "spp": RANGES["spp.train"], "target_spp": RANGES["spp.target"], "seed": RANGES["seed"],
                 "threads": RANGES["threads"]}


def _add_render_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--resolution", type=RENDER_RANGES["resolution"].arg_type(),
                   help="image width = height in pixels (default: the pack's)")
    p.add_argument("--spp", type=RENDER_RANGES["spp"].arg_type(),
                   help="samples per pixel of this render (default: the pack's [render] spp; `camo optimize --spp` is "
                        "a run's training spp)")
    p.add_argument("--views", type=RENDER_RANGES["views"].arg_type(), help="number of orbit views (default: the pack's)")
    p.add_argument("--threads", type=RENDER_RANGES["threads"].arg_type(),
                   help="CPU threads for the LLVM backend (default: all cores; env CAMO_THREADS)")


def build_parser() -> argparse.ArgumentParser:
    parser = CamoArgumentParser(prog="camo", description="3D camouflage: optimise, evaluate, study.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser("doctor", help="check the backend, libraries and optional local weights")
    p.set_defaults(func=_doctor)

    scenes = sub.add_parser("scenes", help="built-in scenes: list, render")
    ssub = scenes.add_subparsers(dest="scenes_command", metavar="SUBCOMMAND")
    ssub.required = True
    p = ssub.add_parser("list", help="print one built-in scene per line, name first")
    p.set_defaults(func=_scenes_list)
    p = ssub.add_parser("render", help="render a scene's views (background, object, mask, depth) to a folder")
    p.add_argument("scene", help="built-in scene name (ENV or ENV:OBJECT) or a scene pack .toml")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=RENDER_RANGES["seed"].arg_type(), default=0)
    _add_render_args(p)
    p.set_defaults(func=_scenes_render)

    p = sub.add_parser("plan", help="run the effect planner's pilot on a scene and print its decisions, their "
                       "measured contributions and the accuracy-vs-seconds curve")
    p.add_argument("scene", help="built-in scene name or scene pack .toml")
    p.add_argument("--purpose", choices=("optimize", "render", "evaluate"), default="optimize")
    p.add_argument("--ablate", default="", help="comma list of parts switched off (the ablations of camo optimize)")
    p.add_argument("--shadow-gradients", action="store_true", help="let shadow boundaries drive the pose (~35x cost)")
    p.add_argument("--timed", action="store_true", help="optimize: price a training depth cut in seconds timed on "
                   "this machine (a run's plan is untimed, priced in path vertices, so that it is reproducible)")
    p.add_argument("--spp", type=RENDER_RANGES["spp"].arg_type(),
                   help="optimize: training spp (default 4); evaluate/render: the renders' spp (default 64)")
    p.add_argument("--target-spp", type=RENDER_RANGES["target_spp"].arg_type(), default=64,
                   help="optimize: the targets' spp (default 64)")
    p.add_argument("--resolution", type=RENDER_RANGES["resolution"].arg_type(),
                   help="image width = height in pixels (default: the pack's)")
    p.add_argument("--views", type=RENDER_RANGES["views"].arg_type(), help="number of orbit views (default: the pack's)")
    p.add_argument("--seed", type=RENDER_RANGES["seed"].arg_type(), default=0,
                   help="the run's (or evaluation's) seed: the pilot's random numbers")
    p.add_argument("--png", metavar="FILE", help="also draw the accuracy-vs-seconds curve to FILE (PNG)")
    p.add_argument("--no-pilot", action="store_true", help="print the rule-based plan only (what correctness "
                   "requires, every bounce kept)")
    p.add_argument("--threads", type=RENDER_RANGES["threads"].arg_type(),
                   help="CPU threads for the LLVM backend (default: all cores)")
    from optimizer.rendering.planner import DENOISER, DENOISERS

    p.add_argument("--denoise", nargs="?", const=DENOISER, default="", choices=DENOISERS, metavar="VARIANT",
                   help="--purpose evaluate: the plan with this denoiser (as camo evaluate --denoise; the flag alone: "
                   f"{DENOISER}), and the object's spp factor its pilot measures (the object no noisier than its "
                   "denoised surroundings)")
    p.add_argument("--setting", choices=("auto",), default="", help="--purpose evaluate: also the setting of the "
                   "render with the object a pilot chooses (as camo evaluate --setting auto): its spp level, the "
                   "object's samples, the features' spp, with every candidate's measured seconds, error and noise "
                   "ratio")
    p.set_defaults(func=_plan, setting_names=lambda name, args: f"--{name}")

    from camo import grid, optimize_cli, video_cli
    from evaluation import cli as evaluation_cli
    from optimizer.scenes import data
    from study_site import cli as study_cli

    for module in (optimize_cli, evaluation_cli, video_cli, study_cli, data, grid):
        module.register(sub)
    _name_settings_by_flags(parser)
    return parser


def _name_settings_by_flags(parser: argparse.ArgumentParser) -> None:
    """Give every command without its own ``setting_names`` one that shows a library's setting name (a
    :class:`SettingError` names ``time_budget``, ``out``, ...) as that command's flag (``--time-budget``,
    ``--out``): the flag whose argparse ``dest`` it is; a positional argument's as its metavar (``run_dirs``:
    ``RUN_DIR``); a key of the command's ``setting_keys`` default (``{library name: dest}``, e.g. a config key a
    flag sets) as the name and its flag (``MIN_AGE (--min-age)``); a name nothing carries stays as it is."""
    for action in parser._actions:  # argparse keeps its sub-parsers only here
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):  # aliases share a parser
                _name_settings_by_flags(child)
    if parser.get_default("func") is None or parser.get_default("setting_names") is not None:
        return
    flags = {a.dest: max(a.option_strings, key=len) if a.option_strings else (a.metavar or a.dest.upper())
             for a in parser._actions
             if a.dest not in (argparse.SUPPRESS, "help") and not isinstance(a, argparse._SubParsersAction)}
    flags.update({key: f"{key} ({flags[dest]})" for key, dest in (parser.get_default("setting_keys") or {}).items()})
    parser.set_defaults(setting_names=lambda name, args, flags=flags: flags.get(name, name))


def _doctor(args) -> int:
    from camo.doctor import run_doctor

    return run_doctor()


def _scenes_list(args) -> int:
    from optimizer.scenes import builtin_scenes

    for name, (obj, _, _, desc) in builtin_scenes.SCENES.items():
        print(f"{name}\t{obj}\t{desc}")
    return 0


def _scenes_render(args) -> int:
    from optimizer import backend
    from optimizer.assets.export_views import render_scene_to_dir

    pack = load_scene_arg(args.scene, args)
    backend.init(threads=args.threads)
    out = render_scene_to_dir(pack, args.out, seed=args.seed)
    print(f"wrote {out}")
    return 0


def _plan(args) -> int:
    import dataclasses

    from optimizer.assets.conditions import ABLATIONS, ablated_switches, parse_ablations
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.rendering.planner import curve_png, plan
    from optimizer.scenes.environments import get_environment

    pack = load_scene_arg(args.scene, args)
    ablate = parse_ablations(args.ablate)
    app = AppearanceConfig(**ablated_switches(ablate))
    params = app.planner_params()
    pins = {k: v for a in ablate for k, v in ABLATIONS[a].pins}  # (as camo optimize pins them)
    if pins:
        pack.material = dataclasses.replace(pack.material, **pins)
    if args.png and not args.png.lower().endswith(".png"):
        raise CamoError(f"--png {args.png}: the file name must end in .png")
    from optimizer import backend

    backend.init(threads=args.threads)
    env = get_environment(pack.environment)
    print(f"scene: {pack.name} ({env.description})")
    print(f"purpose: {args.purpose}; optimised parameters: {', '.join(sorted(params)) if args.purpose == 'optimize' else '-'}")
    if args.denoise and args.purpose != "evaluate":
        raise CamoError(f"--denoise {args.denoise}: only with --purpose evaluate (the evaluation's denoiser)")
    if args.setting and (args.purpose != "evaluate" or args.no_pilot):
        raise CamoError(f"--setting {args.setting}: only with --purpose evaluate and its pilot (drop --no-pilot)")
    if args.timed and (args.purpose != "optimize" or args.no_pilot):
        raise CamoError("--timed: only with --purpose optimize and its pilot (drop --no-pilot)")
    if args.no_pilot:
        pl = plan(pack, env, params, args.purpose, args.shadow_gradients)
    elif args.purpose == "optimize":
        from optimizer.optimise.planning import measure_plan
        from optimizer.rendering.placement import prepare_object
        from optimizer.scenes.cameras import cameras

        spp = {"training": args.spp or 4, "targets": args.target_spp}
        pl = measure_plan(pack, env, prepare_object(pack), cameras(pack), app, args.seed, spp, args.shadow_gradients,
                          timed=args.timed)
    else:
        from evaluation.views import evaluation_cameras, evaluation_plan
        from optimizer.scenes.cameras import cameras

        cams = evaluation_cameras(pack, seed=args.seed).cams if args.purpose == "evaluate" else cameras(pack)
        pl = evaluation_plan(pack, env, cams, args.spp or 64, args.seed,
                             denoise=args.denoise if args.purpose == "evaluate" else "", setting=args.setting)
    if pl.pilot:
        p = pl.pilot
        print(f"pilot: {p['views']} views at {p['width']}x{p['height']}, {p['spp']} spp, full depth {p['max_depth']}, "
              f"{p['seconds']:.1f} s; the object changes {p['region_share']:.0%} of its frames")
    print(pl.describe())
    if args.png:
        if not pl.curve:
            raise CamoError("--png needs the pilot (drop --no-pilot)")
        curve_png(pl.curve, args.png, f"{pack.name}: {args.purpose}, max_depth {pl.max_depth}")
        print(f"wrote {args.png}")
    return 0


class CamoArgumentParser(argparse.ArgumentParser):
    """argparse's parser with camo's error convention: one line ``camo: error: COMMAND: ...``, exit code 2 (argparse
    prints the usage above its error; ``--help`` shows it)."""

    def error(self, message: str):  # type: ignore[override]
        command = self.prog.removeprefix("camo").strip()
        where = f"{command}: " if command else ""
        self.exit(2, f"camo: error: {where}{' '.join(message.split())} (see: {self.prog} --help)\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad command line (2, one line printed)
        return int(exc.code or 0) if isinstance(exc.code, int) else 2
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return int(func(args) or 0)
    except CamoError as exc:
        rename = getattr(args, "setting_names", None)
        message = exc.renamed(lambda n: rename(n, args)) if rename is not None and isinstance(exc, SettingError) \
            else str(exc)
        print(f"camo: error: {message}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("camo: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `camo grid status DIR | head`: the reader left; not an error of ours
        # Python flushes stdout again at exit; point it at devnull so that flush cannot fail too.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
