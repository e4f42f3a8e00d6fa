"""The "2D Diffusion" baseline (paper Sec. IV-B (iv)): per-view image inpainting projected onto the surface.

For every training view ``i`` (independently, as in the paper: "generate the
target camouflage textures purely in image space across the training views"):

1. the object's visible pixels in view ``i`` (coverage > 0, so anti-aliased
   silhouette pixels are re-synthesised too) form the hole ``M_i``;
2. the Stage-2 inpainting backend (:func:`optimizer.optimise.inpaint.get_inpainter`,
   default ``"patch"``, offline; ``"diffusers"`` = SDXL inpainting + depth
   ControlNet from local weights, the paper's model) fills ``M_i`` in the
   sRGB-encoded background render, conditioned on the background depth,
   ``strength = 1`` (synthesised from scratch; the pixels behind the object are
   never read), seed: stream ``diffusion2d`` of :mod:`camo_base.seeds` (``seed + i``);
3. "projected iteratively onto the 3D model": views are taken in their orbit
   order 0, 1, ..., V-1; each view colours the texels visible in it (same
   projection and visibility test as the Owens baselines) that no earlier view
   has coloured (first come, no blending -- each texel shows exactly one
   inpainting, so the per-view inconsistency the paper reports stays visible
   as seams between the regions of different views).

The inpainted sRGB image is decoded to linear and turned into albedo like the
other painting baselines (:mod:`optimizer.optimise.baselines.common`, default: global
white level). Unseen and off-chart texels: :func:`projection.bake`.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from camo_base import imaging, seeds
from optimizer.optimise.baselines.common import BaselineOptions, Setup, observed_albedo, painted_values
from optimizer.optimise.baselines.owens2014 import fill_in_order
from optimizer.optimise.method import Method
from optimizer.rendering.projection import bake


@dataclasses.dataclass
class Diffusion2DOptions(BaselineOptions):
    backend: str = "patch"  # optimizer.optimise.inpaint backend name
    backend_options: dict = dataclasses.field(default_factory=dict)  # e.g. sdxl_path=..., controlnet_path=...
    strength: float = 1.0
    mask_threshold: float = 0.0  # a pixel is in the hole when the object's coverage exceeds this


def inpaint_views(setup: Setup, opts: Diffusion2DOptions) -> tuple[np.ndarray, list[float]]:
    """Per-view inpainted images, linear ``(V, H, W, 3)``, and the seconds each took."""
    from optimizer.optimise.inpaint import get_inpainter

    inp = get_inpainter(opts.backend, **opts.backend_options)
    t = setup.targets
    out, secs = [], []
    for v in range(len(setup.cams)):
        t0 = time.perf_counter()
        bg = imaging.linear_to_srgb(t.background[v])
        mask = t.coverage[v] > opts.mask_threshold
        res = inp.inpaint(bg, mask, bg, t.depth[v], strength=opts.strength, seed=seeds.seed("diffusion2d", setup.seed, view=v))
        out.append(imaging.srgb_to_linear(res))
        secs.append(time.perf_counter() - t0)
        setup.say(f"diffusion2d: inpainted view {v + 1}/{len(setup.cams)} ({secs[-1]:.1f} s)")
    return np.stack(out), secs


def compute(setup: Setup, opts: Diffusion2DOptions | None = None):
    opts = opts or Diffusion2DOptions()
    images, secs = inpaint_views(setup, opts)
    surf = setup.texel_surface()
    obs = setup.observe(surf, opts.visibility_eps)
    albedo = observed_albedo(setup, obs, images, opts.albedo_mode)
    order = list(range(len(setup.cams)))
    col, assigned, src = fill_in_order(obs.visible, albedo, order)
    values = painted_values(setup, bake(surf, col, assigned))
    info = {"backend": opts.backend, "strength": opts.strength, "albedo_mode": opts.albedo_mode,
            "visibility_eps": opts.visibility_eps, "order": order, "texels": len(surf),
            "texels_seen": int(assigned.sum()), "seconds_inpaint": float(sum(secs))}
    setup.inpainted = images  # for inspection by callers/tests
    return values, [], info


#: The method of this module (collected by :mod:`optimizer.optimise.methods`): ``--stage2-backend``,
#: ``--sdxl-path`` and ``--controlnet-path`` set its inpainter.
METHODS = (Method("diffusion2d", "per-view inpainting projected onto the surface (baselines.diffusion2d)",
                  options=Diffusion2DOptions, compute=lambda setup, options, progress: compute(setup, options),
                  option_names=(("stage2_backend", "options.backend"),
                                ("sdxl_path", "options.backend_options.sdxl_path"),
                                ("controlnet_path", "options.backend_options.controlnet_path"))),)
