"""The ``camo`` command line: one CLI, subcommands per package.

``camo doctor | scenes list | scenes render | plan`` live here; the other
commands come from the modules in :data:`PLUGINS` (``optimize``, ``evaluate`` /
``report``, ``study ...``, ``data ...``). Every handler takes the parsed
arguments and returns an exit code; a :class:`CamoError` becomes one line on
stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import Callable, Sequence

from camo_base.errors import CamoError

#: Modules that contribute subcommands through a ``register(subparsers)`` function.
PLUGINS = ("camo.optimize_cli", "evaluation.cli", "study_site.cli", "optimizer.scenes.data", "camo.grid")


def _add_render_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--resolution", type=int, help="image width = height in pixels (default: the pack's)")
    p.add_argument("--spp", type=int, help="samples per pixel (default: the pack's)")
    p.add_argument("--views", type=int, help="number of orbit views (default: the pack's)")
    p.add_argument("--threads", type=int, help="CPU threads for the LLVM backend (default: all cores; env CAMO_THREADS)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="camo", description="3D camouflage: optimise, evaluate, study.")
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
    p.add_argument("--seed", type=int, default=0)
    _add_render_args(p)
    p.set_defaults(func=_scenes_render)

    p = sub.add_parser("plan", help="run the effect planner's pilot on a scene and print its decisions, their "
                       "measured contributions and the accuracy-vs-seconds curve")
    p.add_argument("scene", help="built-in scene name or scene pack .toml")
    p.add_argument("--purpose", choices=("optimize", "render", "evaluate"), default="optimize")
    p.add_argument("--ablate", default="", help="comma list of parameters switched off: pose,displacement,bsdf,transmittance")
    p.add_argument("--shadow-gradients", action="store_true", help="let shadow boundaries drive the pose (~35x cost)")
    p.add_argument("--spp", type=int, help="optimize: training spp (default 4); evaluate/render: the renders' spp "
                   "(default 64)")
    p.add_argument("--target-spp", type=int, default=64, help="optimize: the targets' spp (default 64)")
    p.add_argument("--resolution", type=int, help="image width = height in pixels (default: the pack's)")
    p.add_argument("--views", type=int, help="number of orbit views (default: the pack's)")
    p.add_argument("--seed", type=int, default=0, help="the run's (or evaluation's) seed: the pilot's random numbers")
    p.add_argument("--png", metavar="FILE", help="also draw the accuracy-vs-seconds curve to FILE (PNG)")
    p.add_argument("--no-pilot", action="store_true", help="print the rule-based plan only (what correctness "
                   "requires, every bounce kept)")
    p.add_argument("--threads", type=int, help="CPU threads for the LLVM backend (default: all cores)")
    p.set_defaults(func=_plan)

    for name in PLUGINS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a package installed without that part
            if exc.name != name:
                raise
            continue
        module.register(sub)
    return parser


def _doctor(args) -> int:
    from camo.doctor import run_doctor

    return run_doctor()


def _scenes_list(args) -> int:
    from optimizer.scenes import builtin_scenes

    for name, (obj, _, _, desc) in builtin_scenes.SCENES.items():
        print(f"{name}\t{obj}\t{desc}")
    return 0


def _apply_overrides(pack, args):
    import dataclasses

    if getattr(args, "resolution", None):
        if args.resolution < 8:
            raise CamoError(f"--resolution must be >= 8, got {args.resolution}")
        pack.render = dataclasses.replace(pack.render, resolution=(args.resolution, args.resolution))
    if getattr(args, "spp", None) is not None:
        if args.spp < 1:
            raise CamoError(f"--spp must be >= 1, got {args.spp}")
        pack.render = dataclasses.replace(pack.render, spp=args.spp)
    if getattr(args, "views", None) is not None:
        if args.views < 1:
            raise CamoError(f"--views must be >= 1, got {args.views}")
        if pack.cameras.mode == "list":
            raise CamoError("--views only applies to orbit cameras")
        pack.cameras = dataclasses.replace(pack.cameras, views=args.views)
    return pack


def load_scene_arg(name: str, args=None):
    """Resolve a SCENE argument (built-in name or pack file) and apply CLI overrides."""
    from optimizer.scenes.builtin_scenes import resolve_scene

    pack = resolve_scene(name)
    return _apply_overrides(pack, args) if args is not None else pack


def _scenes_render(args) -> int:
    from optimizer import backend
    from optimizer.assets.export_views import render_scene_to_dir

    pack = load_scene_arg(args.scene, args)
    backend.init(threads=args.threads)
    out = render_scene_to_dir(pack, args.out, seed=args.seed)
    print(f"wrote {out}")
    return 0


def parse_ablate(text: str) -> set[str]:
    allowed = {"pose", "displacement", "bsdf", "transmittance", "inpainting"}
    items = {t.strip() for t in text.split(",") if t.strip()}
    bad = items - allowed
    if bad:
        raise CamoError(f"unknown --ablate item(s) {', '.join(sorted(bad))}; allowed: {', '.join(sorted(allowed))}")
    return items


def _plan(args) -> int:
    import dataclasses

    from optimizer.scenes.environments import get_environment
    from optimizer.rendering.planner import curve_png, plan

    pack = load_scene_arg(args.scene, args)
    ablate = parse_ablate(args.ablate)
    params = {"albedo", "pose", "displacement", "bsdf", "transmittance"} - ablate
    if "bsdf" in ablate:
        params.discard("transmittance")
    if "transmittance" in ablate:
        pack.material = dataclasses.replace(pack.material, transmittance=0.0)
    for flag in ("spp", "target_spp"):
        v = getattr(args, flag)
        if v is not None and v < 1:
            raise CamoError(f"--{flag.replace('_', '-')} must be >= 1, got {v}")
    if args.png and not args.png.lower().endswith(".png"):
        raise CamoError(f"--png {args.png}: the file name must end in .png")
    from optimizer import backend

    backend.init(threads=args.threads)
    env = get_environment(pack.environment)
    print(f"scene: {pack.name} ({env.description})")
    print(f"purpose: {args.purpose}; optimised parameters: {', '.join(sorted(params)) if args.purpose == 'optimize' else '-'}")
    if args.no_pilot:
        pl = plan(pack, env, params, args.purpose, args.shadow_gradients)
    elif args.purpose == "optimize":
        from optimizer.optimise.planning import measure_plan
        from optimizer.optimise.run import appearance_for
        from optimizer.rendering.placement import prepare_object
        from optimizer.scenes.cameras import cameras

        spp = {"training": args.spp or 4, "targets": args.target_spp}
        pl = measure_plan(pack, env, prepare_object(pack), cameras(pack), appearance_for(ablate), args.seed, spp,
                          args.shadow_gradients)
    else:
        from evaluation.views import evaluation_cameras, evaluation_plan
        from optimizer.scenes.cameras import cameras

        cams = evaluation_cameras(pack, seed=args.seed).cams if args.purpose == "evaluate" else cameras(pack)
        pl = evaluation_plan(pack, env, cams, args.spp or 64, args.seed)
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return int(func(args) or 0)
    except CamoError as exc:
        print(f"camo: error: {exc}", file=sys.stderr)
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
