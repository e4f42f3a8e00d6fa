"""Owens et al. 2014, "Camouflaging an object from many viewpoints" (CVPR): the Mean, Random and Greedy models.

Each texel of the albedo atlas is coloured from the background renders of the
training views it is visible in (texel projection and visibility:
:mod:`optimizer.rendering.projection`; colour -> albedo:
:mod:`optimizer.optimise.baselines.common`). Where the paper leaves details open we
follow the authors' published code (``andrewowens/camo``, ``src/camo.py``):

``mean``    (``mean_project``) each texel = the mean of the colours it projects
            to over all views in which it is visible.
``random``  (``random_project``) one random *projection order* of the views
            (seeded); each texel takes its colour from the first view in that
            order that sees it. So the choice is per texel, but contiguous
            regions come from the same view (not an independent coin per texel,
            and not per face: the original's faces are the six faces of a cube,
            its texels are what is assigned). GANmouflage's ``random`` baseline
            does the same (its reference views are already shuffled).
``greedy``  (``greedy_project``) a texel is *stable* in a view if it is visible
            and its face is seen within 70 degrees of head-on
            (``|cos| >= cos 70``); texels stable in no view may use any view
            that sees them. Repeatedly pick the unused view with the most
            still-projectable texels (ties broken at random, seeded), give
            those texels its colours, and remove them; stop when nothing is
            left. The count is recomputed after every pick (a set cover), as in
            the original; GANmouflage's re-implementation instead sorts the views
            once by the number of faces within 20 degrees of head-on -- set
            ``stable_angle_deg=20, adaptive=False`` for that variant.

Texels no view sees (the underside on the ground) take the nearest seen
texel's colour (:func:`optimizer.rendering.projection.bake`); the original
leaves them black (mean) or unset.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from camo_base import seeds
from optimizer.optimise.baselines.common import BaselineOptions, Setup, observed_albedo, painted_values
from optimizer.optimise.method import Method
from optimizer.rendering.projection import Observations, bake


@dataclasses.dataclass
class OwensOptions(BaselineOptions):
    stable_angle_deg: float = 70.0  # greedy: Owens' threshold on the angle to head-on
    adaptive: bool = True  # greedy: recount projectable texels after every pick (Owens); False = one static order


def mean_colours(visible: np.ndarray, colours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-texel mean of ``colours (V, N, 3)`` over the views where ``visible (V, N)``; returns (colours, assigned)."""
    w = visible.astype(np.float64)[..., None]
    n = w.sum(0)
    out = (w * colours).sum(0) / np.maximum(n, 1.0)
    return out.astype(np.float32), n[:, 0] > 0


def fill_in_order(visible: np.ndarray, colours: np.ndarray, order) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texels take the colour of the first view in ``order`` that sees them.

    Returns ``(colours (N, 3), assigned (N,), source_view (N,) with -1 where unassigned)``.
    """
    V, N = visible.shape
    out = np.zeros((N, colours.shape[-1]), np.float32)
    src = np.full(N, -1, np.int64)
    for v in order:
        take = visible[v] & (src < 0)
        out[take] = colours[v][take]
        src[take] = v
    return out, src >= 0, src


def random_order(views: int, seed: int) -> list[int]:
    return [int(v) for v in np.random.default_rng(seed).permutation(views)]


def greedy_assignment(visible: np.ndarray, cos: np.ndarray, stable_angle_deg: float = 70.0, seed: int = 0,
                      adaptive: bool = True) -> tuple[np.ndarray, list[int]]:
    """Owens' greedy model: the source view of every texel (``-1``: never seen) and the order views were used in."""
    V, N = visible.shape
    stable = visible & (cos >= math.cos(math.radians(stable_angle_deg)))
    projectable = stable.copy()
    unstable = ~stable.any(0)
    projectable[:, unstable] = visible[:, unstable]
    rng = np.random.default_rng(seed)
    src = np.full(N, -1, np.int64)
    unused = list(range(V))
    used: list[int] = []
    static = None if adaptive else sorted(unused, key=lambda v: (-int(projectable[v].sum()), rng.random()))
    while unused and projectable.any():
        if static is not None:
            v = static[len(used)]
        else:
            counts = projectable[unused].sum(1)
            best = np.flatnonzero(counts == counts.max())
            v = unused[int(best[rng.integers(len(best))])]
        ok = projectable[v]
        src[ok] = v
        projectable[:, ok] = False
        unused.remove(v)
        used.append(v)
    return src, used


def compute(setup: Setup, method: str, opts: OwensOptions | None = None):
    """Run one Owens model; returns ``(values, history, info)`` for :func:`common.run_directory`."""
    opts = opts or OwensOptions()
    seed = seeds.seed("baseline", setup.seed)
    setup.say(f"{method}: rasterising the {setup.app.map_resolution}^2 atlas and casting visibility rays")
    surf = setup.texel_surface()
    obs: Observations = setup.observe(surf, opts.visibility_eps)
    albedo = observed_albedo(setup, obs, setup.targets.background, opts.albedo_mode)  # (V, N, 3)
    info: dict = {"albedo_mode": opts.albedo_mode, "visibility_eps": opts.visibility_eps,
                  "texels": len(surf), "texels_seen": int(obs.visible.any(0).sum())}
    if method == "mean":
        col, assigned = mean_colours(obs.visible, albedo)
    elif method == "random":
        order = random_order(len(setup.cams), seed)
        col, assigned, _ = fill_in_order(obs.visible, albedo, order)
        info["order"] = order
    elif method == "greedy":
        src, used = greedy_assignment(obs.visible, obs.cos, opts.stable_angle_deg, seed, opts.adaptive)
        assigned = src >= 0
        col = np.zeros((len(surf), 3), np.float32)
        col[assigned] = albedo[src[assigned], np.flatnonzero(assigned)]
        info.update(order=used, stable_angle_deg=opts.stable_angle_deg, adaptive=opts.adaptive)
    else:
        raise ValueError(f"unknown Owens 2014 model {method!r}")
    values = painted_values(setup, bake(surf, col, assigned))
    return values, [], info


def _model(name: str):
    def run(setup: Setup, opts: OwensOptions | None, progress: bool):
        return compute(setup, name, opts)

    return run


#: The methods of this module (collected by :mod:`optimizer.optimise.methods`).
METHODS = (
    Method("mean", "Owens et al. 2014: mean background colour over the views (baselines.owens2014)",
           options=OwensOptions, compute=_model("mean")),
    Method("random", "Owens et al. 2014: one random projection order (baselines.owens2014)",
           options=OwensOptions, compute=_model("random")),
    Method("greedy", "Owens et al. 2014: greedy view choice (baselines.owens2014)",
           options=OwensOptions, compute=_model("greedy")),
)
