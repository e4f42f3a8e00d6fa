"""Which texels the warm start solves in a run's own set-up, and which condition drops the others (issue 29,
docs/results/giveaways.md, "Why the warm start solved a tenth of meadow's texels").

Sets a run up as ``camo optimize SCENE --views 4 --resolution 64 --map-resolution 128 --target-vertices 3000
--displacement-resolution 64`` does (the glint-safe start, the measured plan and its environment, the turn search),
renders the targets and runs the warm start, then counts the on-chart texels that pass each of its conditions in
some training view, in turn: facing the camera (the face normal, oriented by the vertex normals, towards it), the
first hit of the camera ray within the tolerance (0.01 x the object's size) and the pixel fully covered by the object
(the solve's weight > 0). The counts are made twice: with the faces oriented by the vertex normals of the turned
object (:func:`optimizer.rendering.appearance.world_normals`, what the warm start uses) and by the unturned ones
(``Geometry.normal``, what it used before the fix: right only for turns under 90 degrees), and at larger
tolerances.

    python bench/warmstart_visibility.py meadow gravel
    python bench/warmstart_visibility.py packs/real/*.toml              # the real cross's diagonal (giveaways.md)
    python bench/warmstart_visibility.py --size real_cross --turn-only packs/real/cross/sky-*.toml

``--size real_cross``: the set-up of ``grids/real_cross.toml``'s ``[optimize]`` table (8 views at 96 px, 256-texel maps,
10,000 vertices, 32-spp targets) instead of giveaways.md's; ``--turn-only``: the turn search alone (which runs turn
past 90 degrees, i.e. were hit by the bug before the fix), one row per scene.
"""

from __future__ import annotations

import argparse
import math


#: run set-ups: giveaways.md's (bench/bench_giveaways.py's SIZE) and grids/real_cross.toml's [optimize] table
SIZES = {"giveaways": {"views": 4, "resolution": 64, "map_resolution": 128, "target_vertices": 3000,
                       "displacement_resolution": 64},
         "real_cross": {"views": 8, "resolution": 96, "map_resolution": 256, "target_vertices": 10000,
                        "displacement_resolution": 128, "spp": 4, "target_spp": 32}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--size", choices=tuple(SIZES), default="giveaways")
    ap.add_argument("--turn-only", action="store_true")
    a = ap.parse_args(argv)

    import numpy as np

    from optimizer import backend
    from optimizer.optimise import run as R
    from optimizer.optimise.spec import RunSpec
    from optimizer.optimise.stage1 import Stage1
    from optimizer.rendering import projection
    from optimizer.rendering.appearance import world_normals, world_positions
    from optimizer.scenes.environments import get_environment

    backend.init()
    if a.turn_only:
        print("| scene | turn (deg) | past 90 degrees |")
        print("|---|---|---|")
    else:
        print("| scene | turn (deg) | faces oriented by | on-chart texels | facing a camera | first hit | fully covered "
              "(solved) | first hit at tolerance 0.03 / 0.1 x size |")
        print("|---|---|---|---|---|---|---|---|")
    for scene in a.scenes:
        spec = RunSpec.from_options({"scene": scene, **SIZES[a.size], "iterations": 24}).validate()
        env = get_environment(spec.pack.environment)
        pack, note = R.glint_safe_start(spec.pack, env, spec)
        setup = R._setup(spec, pack, env, note, lambda s: None)
        s1 = Stage1(setup.pack, setup.env, setup.prepared, setup.cams, setup.plan,
                    spec.stage1_config(time_budget=None), setup.app)
        s1.search_pose()
        if a.turn_only:
            turn = (math.degrees(float(s1.values["rotation"][0])) + 180.0) % 360.0 - 180.0
            print(f"| {scene} | {turn:.0f} | {'yes' if abs(turn) > 90 else 'no'} |", flush=True)
            continue
        s1.render_targets()
        s1.warm_start()
        info = s1.warm_start_info
        g = s1.geometry
        pos = world_positions(g, s1.values, s1.app)
        sc, shape = projection.object_scene(s1.env, pos, g.faces, g.uvs)
        turn = math.degrees(float(s1.values["rotation"][0]))
        cov = s1.targets.coverage
        for label, normals in (("the turned object (the fix)", world_normals(g, s1.values)),
                               ("the unturned object (before)", g.normal)):
            surface = projection.rasterise_texels(pos, g.faces, g.uvs, s1.values["albedo"].shape[0], normals)
            n = len(surface)
            facing = np.zeros(n, bool)
            for cam in s1.cams:
                to_cam = np.asarray(cam.origin, np.float64) - surface.points
                x, y, z = projection.project(surface.points, cam)
                facing |= projection.in_frame(x, y, z, cam) & (np.einsum("ij,ij->i", surface.normals, to_cam) > 0)
            hit = {}
            for k in (0.01, 0.03, 0.1):
                obs = projection.observe(sc, shape, s1.cams, surface, k * float(g.size))
                hit[k] = obs
            obs = hit[0.01]
            full = np.stack([projection.sample_bilinear(cov[v][..., None], obs.x[v], obs.y[v])[:, 0]
                             for v in range(len(s1.cams))]) >= 0.999
            solved = (obs.visible & full & (obs.cos > 0)).any(0)
            print(f"| {scene} | {turn:.0f} | {label} | {n} | {int(facing.sum())} | {int(obs.visible.any(0).sum())} | "
                  f"{int(solved.sum())} | {int(hit[0.03].visible.any(0).sum())} / {int(hit[0.1].visible.any(0).sum())} |")
        print(f"<!-- {scene}: the warm start itself solved {info.texels_seen} of {info.texels} -->")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
