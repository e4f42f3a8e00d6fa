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
:func:`optimizer.optimise.finish.finish` (same renderer, lighting, spp, export,
``summary.json``), with the background targets rendered by Stage 1's own
:func:`optimizer.optimise.stage1.render_targets`. Painted methods produce
an albedo atlas at ``--map-resolution`` with metallic 0, roughness 1 (map
value), transmittance 0, no displacement and no pose change. How background
radiance becomes albedo: :mod:`optimizer.optimise.baselines.common`.

Each module declares its methods in a ``METHODS`` tuple of
:class:`optimizer.optimise.method.Method` records (name, summary, options
dataclass, ``compute``); :mod:`optimizer.optimise.methods` collects them, so a
new baseline is one new module here (CONTRIBUTING.md, "Adding a baseline").
What a baseline reads of its run spec is declared there: the common part (scene and pack,
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
neither Mitsuba nor torch; :func:`optimizer.optimise.run.run_baseline` runs one.
"""
