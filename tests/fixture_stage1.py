"""A tiny real Stage 1 on gravel for tests of Stage 1 loss terms (the detail term, the perceptual term).

2 views of 24 px, 32-texel maps, 800 vertices, 2 spp (targets 4), seed 0, squared error on the frame, the silhouette
term every step; ``batched`` selects the one-launch path (pose and displacement frozen) over the per-view one.
Needs the Mitsuba backend (the ``mi_backend`` fixture). Imported by tests/test_detail_term.py and tests/test_perceptual.py.
"""

from __future__ import annotations

import dataclasses


def tiny_gravel_stage1(batched: bool, views: int = 2, **config):
    """A prepared ``Stage1`` on gravel at test size; ``views`` training views (2 unless a test needs texels seen
    twice); ``config`` adds ``Stage1Config`` fields (e.g. ``detail_match``)."""
    from optimizer.optimise.stage1 import Stage1, Stage1Config
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.rendering.placement import prepare_object
    from optimizer.rendering.planner import plan
    from optimizer.scenes import builtin_scenes
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment

    pack = builtin_scenes.get("gravel")
    pack.cameras = dataclasses.replace(pack.cameras, views=views)
    pack.render = dataclasses.replace(pack.render, resolution=(24, 24))
    app = dataclasses.replace(AppearanceConfig(), map_resolution=32, displacement_resolution=16)
    if batched:
        app = dataclasses.replace(app, pose=False, freeze_displacement=True)
    env = get_environment(pack.environment)
    cfg = Stage1Config(spp=2, target_spp=4, seed=0, loss="mse", domain="frame", silhouette_every=1, **config)
    return Stage1(pack, env, prepare_object(pack, target_vertices=800), cameras(pack),
                  plan(pack, env, app.planner_params()), cfg, app).prepare()
