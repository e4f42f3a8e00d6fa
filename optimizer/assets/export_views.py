"""``camo scenes render``: write a scene's per-view renders to a folder.

Per view ``XX``: ``view_XX_bg.png`` / ``view_XX_obj.png`` (sRGB previews),
``view_XX_mask.png`` (0/255 visible-object mask), ``view_XX_bg.exr`` /
``view_XX_obj.exr`` (linear radiance), ``view_XX_depth.exr`` (background depth,
scene units, 0 = miss); plus ``overview.png`` (rows: background, object, mask)
and ``scene.json`` (resolved pack, plan, cameras).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from camo_base import atomic, imaging
from optimizer.scenes.cameras import cameras
from optimizer.scenes.environments import get_environment
from optimizer.rendering.placement import prepare_object, static_object_fn
from optimizer.rendering.planner import plan
from optimizer.rendering.render import ViewRenders, render_views
from optimizer.scenes.scenepack import ScenePack


def overview(vr: ViewRenders, max_views: int = 8) -> np.ndarray:
    """A contact sheet (sRGB): background / with object / mask rows, up to ``max_views`` columns."""
    idx = np.linspace(0, len(vr.background) - 1, min(max_views, len(vr.background))).round().astype(int)
    rows = [
        np.concatenate([imaging.linear_to_srgb(vr.background[i]) for i in idx], axis=1),
        np.concatenate([imaging.linear_to_srgb(vr.with_object[i]) for i in idx], axis=1),
        np.concatenate([np.repeat(vr.coverage[i][..., None], 3, -1) for i in idx], axis=1),
    ]
    return np.concatenate(rows, axis=0)


def write_view_renders(out: Path, vr: ViewRenders) -> None:
    for i in range(len(vr.background)):
        imaging.save_png(out / f"view_{i:02d}_bg.png", imaging.linear_to_srgb(vr.background[i]))
        imaging.save_png(out / f"view_{i:02d}_obj.png", imaging.linear_to_srgb(vr.with_object[i]))
        imaging.save_png(out / f"view_{i:02d}_mask.png", vr.mask[i])
        imaging.save_exr(out / f"view_{i:02d}_bg.exr", vr.background[i])
        imaging.save_exr(out / f"view_{i:02d}_obj.exr", vr.with_object[i])
        imaging.save_exr(out / f"view_{i:02d}_depth.exr", vr.depth[i])
    imaging.save_png(out / "overview.png", overview(vr))


def render_scene_to_dir(pack: ScenePack, out: str | Path, seed: int = 0) -> Path:
    out = Path(out)
    env = get_environment(pack.environment)
    pl = plan(pack, env, purpose="render")
    cams = cameras(pack)
    prepared = prepare_object(pack)
    vr = render_views(env.build, static_object_fn(pack, prepared), cams, pl.integrator, pack.render.spp, seed)
    out.mkdir(parents=True, exist_ok=True)
    write_view_renders(out, vr)
    atomic.write_json(out / "scene.json", {
        "pack": pack.to_dict(),
        "plan": {"integrator": pl.integrator, "reasons": pl.reasons},
        "cameras": [dataclasses.asdict(c) for c in cams],
        "seed": seed,
        "units": {"radiance": "linear", "png": "sRGB", "depth": "scene units along the ray, 0 = miss"},
    })
    return out
