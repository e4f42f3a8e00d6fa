"""The asset: write any method's result (maps, displacement, pose) into a run directory.

Every method (ours, ablations, baselines) ends here, so evaluation and the
study treat them the same way: the result is re-rendered with the same
physically based renderer and lighting, exported as ``result.glb`` /
``result.obj`` / ``scene.xml``, with maps, pose, previews and the renders.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from camo_base import atomic, imaging, seeds
from optimizer.scenes.bsdf_maps import MAPS
from optimizer.assets import export, scene_xml
from optimizer.rendering import scene as scn
from optimizer.rendering.appearance import AppearanceConfig, Geometry, object_bsdf, object_mesh, pose_record, rendered_maps, world_positions
from optimizer.scenes.cameras import Camera
from optimizer.scenes.environments import Environment
from optimizer.rendering.render import render_shaded
from optimizer.scenes.scenepack import ScenePack


@dataclasses.dataclass
class Result:
    pack: ScenePack
    env: Environment
    cams: list[Camera]
    geometry: Geometry
    values: dict[str, np.ndarray]  # appearance parameters (see optimizer.rendering.appearance)
    app: AppearanceConfig
    integrator: dict[str, Any]  # path tracer for the final renders
    spp: int
    targets: Any  # stage1.Targets: background, coverage, domain, depth


def preview_strip(bg: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """sRGB strip: background | object | 4x amplified absolute difference."""
    a, b = imaging.linear_to_srgb(bg), imaging.linear_to_srgb(obj)
    return np.concatenate([a, b, np.clip(4.0 * np.abs(a - b), 0.0, 1.0)], axis=1)


def plot_loss(path: Path, history: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    for stage in sorted({h["stage"] for h in history}):
        hs = [h for h in history if h["stage"] == stage]
        ax.plot([h["iteration"] for h in hs], [h["loss"] for h in hs], label=f"stage {stage} total")
        if "loss_photo" in hs[0]:
            ax.plot([h["iteration"] for h in hs], [h["loss_photo"] for h in hs], "--", label=f"stage {stage} photometric")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def render_result(res: Result, seed: int = 12345) -> np.ndarray:
    """Path-traced renders ``(V, H, W, 3)`` of the result in its scene."""
    g = res.geometry
    mesh = object_mesh(g, res.values, res.app)
    return render_shaded(res.env.build(), mesh, res.cams, res.integrator, res.spp, seed)


def final_render_seed(seed: int) -> int:
    """Sampler seed of the final render for run seed ``seed`` (stream ``final_render`` of :mod:`camo_base.seeds`)."""
    return seeds.seed("final_render", seed)


def write_result(out: Path, res: Result, history: list[dict[str, Any]] | None = None, seed: int = 0) -> np.ndarray:
    """Write previews, maps, glb/obj/ply, scene.xml, pose.json and renders.npz; return the final renders."""
    out = Path(out)
    final = render_result(res, seed=final_render_seed(seed))
    bg = res.targets.background
    for v in range(len(final)):
        imaging.save_png(out / "previews" / f"view_{v:02d}.png", preview_strip(bg[v], final[v]))
    step = max(1, len(final) // 4)
    imaging.save_png(out / "previews" / "overview.png",
                     np.concatenate([preview_strip(bg[v], final[v]) for v in range(0, len(final), step)], axis=0))
    if history:
        plot_loss(out / "loss.png", history)

    g, v = res.geometry, res.values
    maps = rendered_maps(v)
    maps["displacement"] = v["displacement"][..., 0] * g.bound
    export.save_maps(out / "maps", maps, displacement_bound=g.bound)
    verts = world_positions(g, v, res.app)
    bsdf = {k: maps[k] if m.colour else maps[k][..., 0] for k, m in MAPS.items()}
    for writer, name in ((export.write_glb, "result.glb"), (export.write_obj, "result.obj")):
        writer(out / name, verts, g.faces, g.uvs, bsdf, res.app.eta)
    export.write_ply(out / "result.ply", verts, g.faces, g.uvs)
    scene_xml.write_scene_xml(out / "scene.xml", res.env.build(), out / "result.ply", object_bsdf(v, res.app),
                              [scn.perspective(c, res.spp) for c in res.cams], res.integrator)
    atomic.write_json(out / "pose.json", pose_record(res.pack.object, v))
    with atomic.atomic_path(out / "renders.npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, final=final, background=bg, domain=res.targets.domain.astype(np.uint8),
                                coverage=res.targets.coverage, depth=res.targets.depth)
    return final
