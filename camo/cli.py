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
from camo_base.ranges import Range

def _add_render_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--resolution", type=Range(int, 8, 8192).arg_type(),
                   help="image width = height in pixels (default: the pack's)")
    p.add_argument("--spp", type=Range(int, 1, 1 << 16).arg_type(),
                   help="samples per pixel of this render (default: the pack's [render] spp; `camo optimize --spp` is "
                        "a run's training spp)")
    p.add_argument("--views", type=Range(int, 1, 1024).arg_type(), help="number of orbit views (default: the pack's)")
    p.add_argument("--threads", type=Range(int, 1, 4096).arg_type(),
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
    p.add_argument("--seed", type=Range(int, 0, 2**63 - 1).arg_type(), default=0)
    _add_render_args(p)
    p.set_defaults(func=_scenes_render)

    p = sub.add_parser("plan", help="print the effect planner's integrator decision and why")
    p.add_argument("scene", help="built-in scene name or scene pack .toml")
    p.add_argument("--purpose", choices=("optimize", "render", "evaluate"), default="optimize")
    p.add_argument("--ablate", default="", help="comma list of parts switched off (the ablations of camo optimize)")
    p.add_argument("--shadow-gradients", action="store_true", help="let shadow boundaries drive the pose (~35x cost)")
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
    ``--out``): the flag whose argparse ``dest`` it is; a name no flag carries stays as it is."""
    for action in parser._actions:  # argparse keeps its sub-parsers only here
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):  # aliases share a parser
                _name_settings_by_flags(child)
    if parser.get_default("func") is None or parser.get_default("setting_names") is not None:
        return
    flags = {a.dest: max(a.option_strings, key=len) for a in parser._actions
             if a.option_strings and a.dest not in (argparse.SUPPRESS, "help")}
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
    from optimizer.scenes.environments import get_environment
    from optimizer.rendering.planner import plan

    import dataclasses

    from optimizer.assets.conditions import ABLATIONS, ablated_switches, parse_ablations
    from optimizer.rendering.appearance import AppearanceConfig

    pack = load_scene_arg(args.scene)
    ablate = parse_ablations(args.ablate)
    params = AppearanceConfig(**ablated_switches(ablate)).planner_params()
    pins = {k: v for a in ablate for k, v in ABLATIONS[a].pins}  # (as camo optimize pins them)
    if pins:
        pack.material = dataclasses.replace(pack.material, **pins)
    from optimizer import backend

    backend.init()
    env = get_environment(pack.environment)
    pl = plan(pack, env, params, args.purpose, args.shadow_gradients)
    print(f"scene: {pack.name} ({env.description})")
    print(f"purpose: {args.purpose}; optimised parameters: {', '.join(sorted(params)) if args.purpose == 'optimize' else '-'}")
    print(pl.describe())
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
