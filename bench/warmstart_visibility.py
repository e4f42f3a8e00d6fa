"""How many texels the warm start solves in a run's own set-up, and how that depends on the projection's visibility
tolerance (issue 29, docs/results/giveaways.md, "A grain layer projected from the ground").

Sets a run up as ``camo optimize SCENE --views 4 --resolution 64 --map-resolution 128 --target-vertices 3000
--displacement-resolution 64`` does (the glint-safe start, the measured plan and its environment, the turn search),
renders the targets, runs the warm start and prints what it solved, then counts the texels
:func:`optimizer.rendering.projection.observe` finds visible (and facing) in some training view at the warm start's
tolerance (0.01 x the object's size) and at larger ones.

    python bench/warmstart_visibility.py meadow
"""

from __future__ import annotations

import argparse


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    a = ap.parse_args(argv)

    from optimizer import backend
    from optimizer.optimise import run as R
    from optimizer.optimise.spec import RunSpec
    from optimizer.optimise.stage1 import Stage1
    from optimizer.rendering import projection
    from optimizer.rendering.appearance import world_positions
    from optimizer.scenes.environments import get_environment

    spec = RunSpec.from_options({"scene": a.scene, "views": 4, "resolution": 64, "map_resolution": 128,
                                 "target_vertices": 3000, "displacement_resolution": 64, "iterations": 24}).validate()
    backend.init()
    env = get_environment(spec.pack.environment)
    pack, note = R.glint_safe_start(spec.pack, env, spec)
    setup = R._setup(spec, pack, env, note, lambda s: None)
    s1 = Stage1(setup.pack, setup.env, setup.prepared, setup.cams, setup.plan, spec.stage1_config(time_budget=None),
                setup.app)
    s1.search_pose()
    s1.render_targets()
    s1.warm_start()
    info = s1.warm_start_info
    print(f"{a.scene}: warm start solved {info.texels_seen} of {info.texels} on-chart texels")
    g = s1.geometry
    pos = world_positions(g, s1.values, s1.app)
    surface = projection.rasterise_texels(pos, g.faces, g.uvs, s1.values["albedo"].shape[0], g.normal)
    sc, shape = projection.object_scene(s1.env, pos, g.faces, g.uvs)
    for k in (0.01, 0.03, 0.1):
        obs = projection.observe(sc, shape, s1.cams, surface, k * float(g.size))
        print(f"  tolerance {k:g} x size: {int((obs.visible & (obs.cos > 0)).any(0).sum())} texels visible and facing "
              "in some view")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
