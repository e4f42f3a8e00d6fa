"""A global search of the object's turn about the vertical axis before Stage 1 (beyond the paper; the ``fast`` preset).

The paper optimises the pose (Eq. 3: ``theta_z`` and a ground offset) by gradient descent with the other parameters.
Two things keep that from finding the orientation that hides best:

* **the shadow is what gives the object away** once its body matches the background (meadow: 78 % of the
  evaluation crop's squared error lies outside the object's pixels, gravel 66 %; docs/results/convergence.md), and
  how much ground the shadow darkens depends on how the object is turned to the sun -- but a shadow's edge is a
  visibility discontinuity of *shadow rays*, whose gradient the training integrator does not sample (``sppi = 0``;
  ``--shadow-gradients`` does, at ~35x the cost), so no gradient turns the object to cast a smaller shadow;
* Adam moves ``theta`` by about its rate, 1e-2 rad, per step: 60 steps reach ~34 degrees at most.

So before Stage 1 (and before the targets' loss domain and the warm start, which then follow the chosen pose) the
object is rendered at ``angles`` turns ``theta_k = 2 pi k / angles`` from a few training views at a low spp, each
with the background render of the same seed (common random numbers: paths that miss the object and its shadow
give identical radiance), and each turn is scored by the sRGB squared difference over the pixels the object does
not cover -- its shadow, and its reflections and refractions onto the ground -- summed over the views. The turn
with the lowest score becomes the initial ``theta``; the gradient steps refine it as before.

Measured at demo sizes (8 views, 96 px, 8 spp; the shadow-only score): gravel's box at theta 0 scores 1.69e-4,
turned by 135 degrees 1.12e-4 (-34 %); meadow's backpack 1.13e-4 at 0 and 1.06e-4 at 22.5 degrees (-6 %).

Choices: the object's own pixels are left out (its body is matched afterwards by the warm start and Stage 1; the
covered area changed by < 2 % over the turns on those scenes); ``views`` evenly spaced training views (4) at
``spp`` (8); scores in sRGB like the evaluation; ties keep the smaller turn (theta 0 first: an object whose turn
does not matter keeps its pose).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable, Sequence

import numpy as np

from camo_base import imaging


#: Training views the search renders (evenly spaced over the rig) and their spp.
VIEWS = 4
SPP = 8


@dataclasses.dataclass
class PoseSearchInfo:
    """What the search did (``summary.json``'s ``pose_search``)."""

    angles_deg: list[float]  # the turns tried, degrees
    scores: list[float]  # their scores (sRGB squared difference outside the object, summed over views, per pixel)
    chosen_deg: float  # the best turn, degrees
    rotation: float  # the initial theta it set, radians in [-pi, pi] (the turn added to the pose it started from)
    views: int
    spp: int
    seconds: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def outside_score(img: np.ndarray, bg: np.ndarray, coverage: np.ndarray) -> float:
    """Mean over the pixels of every view of the sRGB squared difference (channels averaged) where the object covers
    nothing (``coverage`` <= 1e-3); ``img``, ``bg`` ``(V, H, W, 3)`` linear, ``coverage`` ``(V, H, W)`` in [0, 1].
    Covered pixels count 0, so the mean is over the whole frame (turns stay comparable when the silhouette's area
    changes)."""
    d = imaging.linear_to_srgb(img).astype(np.float64) - imaging.linear_to_srgb(bg).astype(np.float64)
    out = (np.asarray(coverage) <= 1e-3)[..., None]
    return float((d * d * out).mean())


def search_turn(angles: int, render: Callable[[float], tuple[np.ndarray, np.ndarray]], background: np.ndarray,
                ) -> tuple[float, list[float], list[float]]:
    """``(best theta, thetas, scores)``: ``render(theta)`` gives ``(image, coverage)`` of the object turned by
    ``theta`` (radians); ``background`` the scene without it, same views, spp and seed. Ties keep the first turn."""
    thetas = [2.0 * math.pi * k / angles for k in range(angles)]
    scores = []
    for th in thetas:
        img, cov = render(th)
        s = outside_score(img, background, cov)
        scores.append(s if math.isfinite(s) else math.inf)
    best = int(np.argmin(scores))  # first of equal minima
    return thetas[best], thetas, scores


def pose_search(values: dict[str, np.ndarray], geometry, app, env, cams: Sequence, integrator: dict, angles: int,
                views: int, spp: int, seed: int, log: Callable[[str], None] = lambda s: None
                ) -> tuple[dict[str, np.ndarray], PoseSearchInfo]:
    """Return ``values`` with ``rotation`` set to the best of ``angles`` turns (module doc) and what was done."""
    from optimizer.rendering import scene as scn
    from optimizer.rendering.appearance import object_mesh
    from optimizer.rendering.render import coverage_and_depth_views, render_shaded
    from optimizer.scenes.cameras import evenly_spaced

    t0 = time.perf_counter()
    sub = [cams[i] for i in evenly_spaced(len(cams), max(1, min(views, len(cams))))]
    bg = render_shaded(env.build(), None, sub, integrator, spp, seed)
    base = float(values["rotation"][0])
    trial = {key: v for key, v in values.items()}

    def render(theta: float):
        trial["rotation"] = np.array([base + theta], np.float32)
        mesh = object_mesh(geometry, trial, app)
        img = render_shaded(env.build(), mesh, sub, integrator, spp, seed)
        sc = scn.build_scene(env.build(), mesh)
        cov = coverage_and_depth_views(sc, sub, mesh, ss=2)[0]
        return img, cov

    best, thetas, scores = search_turn(angles, render, bg)
    out = dict(values)
    out["rotation"] = np.array([math.remainder(base + best, 2.0 * math.pi)], np.float32)
    info = PoseSearchInfo([math.degrees(t) for t in thetas], scores, math.degrees(best), float(out["rotation"][0]),
                          len(sub), spp, time.perf_counter() - t0)
    log(f"pose search: {angles} turns, best {info.chosen_deg:.0f} deg (score {min(scores):.3g}, at 0 deg "
        f"{scores[0]:.3g}), {info.seconds:.1f} s")
    return out, info
