"""Baselines of the paper (Sec. IV-B), each chosen by ``camo optimize SCENE --method NAME --out RUN_DIR``.

============== ========================================================================
method         what it does (module)
============== ========================================================================
transparent    transmittance 1 everywhere, glass-like principled BSDF (``transparent``)
mean           Owens et al. 2014: mean of the background colours a texel projects to
               over the views that see it (``owens2014``)
random         Owens et al. 2014: one random projection order of the views; a texel
               takes the first view in that order that sees it (``owens2014``)
greedy         Owens et al. 2014: views picked greedily by how many still-unpainted
               texels they see within 70 degrees of head-on (``owens2014``)
diffusion2d    per-view inpainting with the Stage-2 backend, projected onto the
               surface view by view (``diffusion2d``)
ganmouflage    Guo et al. 2023: texture field + perceptual and adversarial losses,
               trained per scene in torch, baked to an albedo atlas (``ganmouflage``);
               ``ganmouflage-paper`` = the same with the paper's settings (8,000 its)
============== ========================================================================

Every method writes the run directory of ``ours`` through
:func:`optimizer.assets.result.write_result` (same renderer, lighting, spp, export),
with the background targets rendered as in Stage 1
(:func:`optimizer.optimise.baselines.common.render_targets`). Painted methods produce
an albedo atlas at ``--map-resolution`` with metallic 0, roughness 1 (map
value), transmittance 0, no displacement and no pose change. How background
radiance becomes albedo: :mod:`optimizer.optimise.baselines.common`.

CLI flags that apply: ``--out --seed --resolution --views --target-spp
--map-resolution --target-vertices --loss --domain --no-planner --threads
--overwrite --quiet``; ``--iterations`` (GANmouflage training iterations;
``--threads`` also sets torch's thread count there); ``--stage2-backend``,
``--sdxl-path``, ``--controlnet-path`` (the inpainter of ``diffusion2d``,
default ``patch``). ``--ablate`` and ``--resume`` are refused; ``--spp``,
``--stages``, ``--stage2-iterations`` and ``--stage2-strength`` are ignored
(``diffusion2d`` always inpaints with strength 1: the background behind the
object must not leak into the result). Importing this package imports
neither Mitsuba nor torch.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from camo_base.errors import CamoError

#: method names accepted by ``camo optimize --method`` besides ``ours``
BASELINES = ("transparent", "mean", "random", "greedy", "diffusion2d", "ganmouflage", "ganmouflage-paper")


def _compute_fn(method: str, options: Any, progress: bool):
    if method == "transparent":
        from optimizer.optimise.baselines.transparent import compute

        return compute
    if method in ("mean", "random", "greedy"):
        from optimizer.optimise.baselines.owens2014 import compute

        return lambda st: compute(st, method, options)
    if method == "diffusion2d":
        from optimizer.optimise.baselines.diffusion2d import compute

        return lambda st: compute(st, options)
    if method in ("ganmouflage", "ganmouflage-paper"):
        from optimizer.optimise.baselines.ganmouflage import compute

        return lambda st: compute(st, options, progress)
    raise CamoError(f"unknown baseline {method!r}; choose one of: {', '.join(BASELINES)}")


def run_baseline(pack, cfg, out: str | Path, overwrite: bool = False, progress: bool = True, options: Any = None) -> Path:
    """Run the baseline ``cfg.method`` for ``pack`` into the run directory ``out``.

    ``cfg`` is an :class:`optimizer.optimise.run.RunConfig`; ``options`` the method's
    options dataclass (``OwensOptions``, ``Diffusion2DOptions``,
    ``GanmouflageConfig``; ``None`` = defaults).
    """
    from optimizer.optimise.baselines.common import run_directory

    method = cfg.method
    if method == "ganmouflage-paper":
        from optimizer.optimise.baselines.ganmouflage import GanmouflageConfig

        options = options or GanmouflageConfig.paper()
        cfg = dataclasses.replace(cfg, method="ganmouflage")
    recorded = cfg.method
    return run_directory(pack, cfg, out, recorded, _compute_fn(method, options, progress), overwrite, progress)


def run_from_args(args, pack, cfg) -> Path:
    """``camo optimize --method BASELINE``: CLI flags -> options, then :func:`run_baseline`."""
    if getattr(args, "resume", False):
        raise CamoError(f"--resume: method {args.method!r} is a one-shot baseline and keeps no checkpoint; run it again")
    if getattr(args, "ablate", ""):
        raise CamoError("--ablate applies to --method ours only")
    options = None
    if args.method in ("ganmouflage", "ganmouflage-paper"):
        from optimizer.optimise.baselines.ganmouflage import GanmouflageConfig

        options = GanmouflageConfig.paper() if args.method == "ganmouflage-paper" else GanmouflageConfig()
        over = {"threads": args.threads}
        if args.iterations is not None:
            over["iterations"] = args.iterations
        options = dataclasses.replace(options, **over)
    elif args.method == "diffusion2d":
        from optimizer.optimise.baselines.diffusion2d import Diffusion2DOptions

        backend = getattr(args, "stage2_backend", None) or "patch"
        extra = {k: getattr(args, k) for k in ("sdxl_path", "controlnet_path") if getattr(args, k, None)}
        options = Diffusion2DOptions(backend=backend, backend_options=extra if backend == "diffusers" else {})
    return run_baseline(pack, cfg, args.out, overwrite=args.overwrite, progress=not args.quiet, options=options)


__all__ = ["BASELINES", "run_baseline", "run_from_args"]
