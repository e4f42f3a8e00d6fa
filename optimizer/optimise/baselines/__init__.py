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
:func:`optimizer.optimise.run.finish` (same renderer, lighting, spp, export,
``summary.json``), with the background targets rendered by Stage 1's own
:func:`optimizer.optimise.stage1.render_targets`. Painted methods produce
an albedo atlas at ``--map-resolution`` with metallic 0, roughness 1 (map
value), transmittance 0, no displacement and no pose change. How background
radiance becomes albedo: :mod:`optimizer.optimise.baselines.common`.

What a baseline reads of its run spec is declared in the registry
(:data:`optimizer.optimise.spec.METHODS`): the common part (scene and pack,
seed, target spp, the loss and its domain, map resolution, planner) and its
own ``[options]`` (``OwensOptions``, ``Diffusion2DOptions``,
``GanmouflageConfig``). ``camo optimize`` flags that set anything else
(``--spp``, ``--stages``, ``--stage2-iterations``, ``--ablate``, ...) are
errors for a baseline; ``--iterations`` sets GANmouflage's training
iterations; ``--stage2-backend``, ``--sdxl-path``, ``--controlnet-path`` set
the inpainter of ``diffusion2d`` (default ``patch``; it always inpaints with
strength 1: the background behind the object must not leak into the
result); ``--threads`` also sets torch's thread count for GANmouflage.
``--resume`` is refused (no checkpoint). Importing this package imports
neither Mitsuba nor torch.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from camo_base.errors import CamoError


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
    if method == "ganmouflage":
        from optimizer.optimise.baselines.ganmouflage import compute

        return lambda st: compute(st, options, progress)
    raise CamoError(f"unknown baseline {method!r} (the methods are optimizer.optimise.spec.METHODS)")


def run_baseline(spec, out: str | Path, overwrite: bool = False, progress: bool = True,
                 threads: int | None = None) -> Path:
    """Run the baseline of ``spec`` (an :class:`optimizer.optimise.spec.RunSpec`; its ``options`` are the method's)
    into the run directory ``out``. ``threads``: the LLVM backend's (and GANmouflage's torch) thread count."""
    from optimizer.optimise.baselines.common import run_directory

    if spec.method == "ours":
        raise ValueError("run_baseline runs baselines; method ours runs through optimizer.optimise.run.run")
    options = spec.options
    if options is not None and threads is not None and hasattr(options, "threads"):
        options = dataclasses.replace(options, threads=threads)
    return run_directory(spec, out, _compute_fn(spec.method, options, progress), overwrite, progress, threads)


__all__ = ["run_baseline"]
