"""A search of the starting roughness on held-out views before Stage 1 (beyond the paper; the ``fast`` preset).

The paper starts from roughness 0 and lets Stage 1 move the roughness map by Adam steps. Two measurements say the
starting roughness decides the result while the steps do not find it (demo sizes, 60 + 4 iterations,
docs/results/convergence.md):

* **the map hardly moves**: from starts of 0.2, 0.35, 0.5 and 0.7 the final median roughness on meadow was 0.23,
  0.37, 0.51 and 0.65 (each within ~0.1 of its start), whatever is better for the novel views. Its gradient is
  dominated by Monte Carlo noise at 4 spp, and what a rougher surface buys in *other* views (a view-independent
  appearance: blurred refractions, no highlights that move with the viewpoint) is not in the training views' loss;
* **which start is best depends on the scene**: meadow ends at 31.99 dB crop PSNR from 0.7 against a mean of 31.53
  from 0.5 (and 31.68 from 0.85, 31.28 from 1.0); gravel +0.51 dB and occluded +0.61 from 0.7; but split -0.74 and
  room -0.63.

And one measurement makes a search cheap: **the score of a start after the warm start predicts the score of the
run's result.** Over seven starts on meadow and 0.5 against 0.7 on five other scenes, the order of the novel-view
crop PSNR right after the warm start (iteration 0) was the order of the results, in every case but one near-tie
(panorama: 0.5 ahead at iteration 0, 0.7 ahead by 0.2 dB PSNR at the end and behind by 0.005 LPIPS-proxy).

So each candidate roughness (``Stage1Settings.roughness_search``; fast: 0.5 and 0.7) is set as a uniform map, the
albedo is warm-started for it (:mod:`optimizer.optimise.warmstart`: the least-squares albedo depends on the other
maps), and the start is scored on the run's held-out views (:class:`optimizer.optimise.holdout.Holdout`, its own
seed stream, never the evaluation's; the score counts the noise a 64-spp evaluation would see). Stage 1 starts from
the best; ties keep the earlier candidate. Cost: one warm start and one held-out score per candidate
beyond the first (whose warm start Stage 1 needs anyway), counted in Stage 1's seconds (``seconds_start_search``):
1.4-2.4 s at demo sizes, ~11 s at the paper's (16 views at 128 px, 64 spp, 800 px maps: the warm start's two
renders dominate; its geometry-only work is shared by the candidates). A third candidate, 0.9, never won on the seven scenes measured and cost another warm start:
at the paper's sizes it put Stage 1's first step at 41 s instead of 28.

The chosen start's score is Stage 1's first held-out check (:meth:`Holdout.score` remembers what it scored, so
that check renders nothing). The held-out views' object+shadow domain is fixed by the first candidate scored (as it is by Stage 1's first check
without the search), so every candidate is scored on the same pixels.

Choices: the candidates stay at or above the planner's glint-safe roughness (``planner.GLINT_ROUGHNESS`` = 0.5):
below it a sun-lit facet mirrors the sun as a glint no step removes; transmittance and metallic keep their starts
(one parameter; per candidate the warm start's two renders and the held-out score's two pairs).

The init search (:func:`init_search`, issue 32).
``camo optimize --init`` sets starting maps, and a start the optimiser cannot leave costs the whole run: from a mirror
(``--init albedo=1,metallic=1,roughness=0,transmittance=0``) on meadow, Stage 1 moves each map value by about one
learning rate (0.01) per step, roughness below ~0.032 has no gradient at all, and 20 + 2 iterations ended at 21 dB on
the held-out views where the default start ends at 24.7. With ``stage1.init_search`` (fast: on) Stage 1 also prepares
the start the run would take without ``init`` (the scene pack's and the preset's material for the maps ``init`` set,
at each ``--roughness-search`` value of the preset, warm-started) and starts from whichever scores best on the
held-out views; the ``init`` start wins ties and is what a run with ``--init`` and the search off keeps. It applies
whenever ``init`` set anything, also a single map. Cost: one warm start and one held-out score per alternative.

The clear-glass candidate (:func:`clear_search`, issue 29; ``stage1.clear_candidate``, off by default).
With a shared index of refraction near 1 and a smooth start (``CLEAR_ROUGHNESS``) the ground behind shows through
the body sharp and barely displaced, texture and colour that are the ground's own: measured on split (4 views at
64 px, 24 + 4 iterations, evaluation at 2048 spp) +2.9 dB crop PSNR and the tint halved, on meadow +0.5 dB, but on
gravel -2.7 dB (docs/results/giveaways.md). So it is a start to choose per scene, not a default: after the other
searches the chosen start (``"start"``, the run's IOR) and the clear-glass start (the IOR ``clear_candidate``, every
map but roughness the chosen start's, warm-started at that IOR) are scored on the held-out views, and the run keeps
the better one with its IOR (Stage 2, the final renders and the exported asset's ``eta``); the start wins ties. The
held-out score counts the noise a ``holdout.noise_spp`` evaluation would see, so sunlight focused by the smooth body
(caustics, which a path tracer reaches only by chance: bright single-pixel fireflies at a few hundred spp) counts
against the candidate as the evaluation would see it. Cost: one warm start and one held-out score.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import numpy as np


@dataclasses.dataclass
class StartSearchInfo:
    """What the search did (``summary.json``'s ``start_search``)."""

    roughness: list[float]  # the candidate starts, in the order tried
    scores: list[float]  # their held-out scores (sRGB squared error, bias^2 + noise at the evaluation's spp)
    chosen: float  # the starting roughness of Stage 1
    seconds: float  # the search's seconds; Stage1.search_start leaves out the chosen start's warm start (its own record)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def start_search(candidates: Sequence[float], values: dict[str, np.ndarray],
                 prepare: Callable[[dict[str, np.ndarray]], tuple[dict[str, np.ndarray], object]],
                 score: Callable[[dict[str, np.ndarray]], float], say=lambda s: None
                 ) -> tuple[dict[str, np.ndarray], object, StartSearchInfo]:
    """Try each roughness in ``candidates`` as a uniform map on ``values`` (the start before the warm start),
    ``prepare`` it (the warm start: ``values -> (values, info)``) and ``score`` it (lower is better); returns the
    best prepared values, its ``prepare`` info and the search's record. Non-finite scores lose; ties keep the
    earlier candidate."""
    if not candidates:
        raise ValueError("the start search needs at least one candidate roughness")
    t0 = time.perf_counter()
    tried = []  # (score, roughness, prepared values, prepare info)
    for r in candidates:
        start = dict(values)
        start["roughness"] = np.full_like(values["roughness"], float(r))
        prepared, info = prepare(start)
        s = float(score(prepared))
        say(f"start search: roughness {r:g} scores {s:.4g}")
        tried.append((s, float(r), prepared, info))
    finite = [t for t in tried if np.isfinite(t[0])]
    best = min(finite, key=lambda t: t[0]) if finite else tried[0]  # min keeps the first of equals
    record = StartSearchInfo([t[1] for t in tried], [t[0] for t in tried], best[1], time.perf_counter() - t0)
    return best[2], best[3], record


# ----------------------------------------------------------------------------------------------------------------
# The init search (issue 32): an ``--init`` start against the start the run takes without it



@dataclasses.dataclass
class InitSearchInfo:
    """What the init search did (``summary.json``'s ``init_search``)."""

    candidates: list[str]  # "init" (the start --init set), then the alternatives' labels
    scores: list[float]  # their held-out scores (lower is better)
    chosen: str
    seconds: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def init_search(labels: Sequence[str], candidates: dict, prepare: Callable[[str, object], tuple[dict, object]],
                score: Callable[[dict[str, np.ndarray]], float], say=lambda s: None
                ) -> tuple[dict[str, np.ndarray], object, InitSearchInfo]:
    """Prepare (``prepare(label, candidate) -> (values, info)``) and score each candidate in ``labels`` order;
    returns the best prepared values, its ``prepare`` info and the record. Non-finite scores lose; ties keep the
    earlier candidate (the first is the ``init`` start)."""
    if not labels:
        raise ValueError("the init search needs at least one candidate")
    t0 = time.perf_counter()
    tried = []
    for label in labels:
        values, info = prepare(label, candidates[label])
        sc = float(score(values))
        say(f"init search: {label} scores {sc:.4g}")
        tried.append((sc, label, values, info))
    finite = [t for t in tried if np.isfinite(t[0])]
    best = min(finite, key=lambda t: t[0]) if finite else tried[0]
    return best[2], best[3], InitSearchInfo([t[1] for t in tried], [t[0] for t in tried], best[1],
                                            time.perf_counter() - t0)


# ----------------------------------------------------------------------------------------------------------------
# The clear-glass candidate (issue 29)

#: The clear-glass candidate's uniform starting roughness (map value). 0.2: the smooth start of the measured clear
#: arm (docs/results/giveaways.md); the roughness map stays within ~0.1 of its start, so this is also about where it
#: ends: smooth enough that the ground is seen through sharp, above the ~0.032 below which roughness has no gradient.
CLEAR_ROUGHNESS = 0.2


@dataclasses.dataclass
class ClearSearchInfo:
    """What the clear-glass search did (``summary.json``'s ``clear_search``)."""

    candidates: list[str]  # "start" (the start the other searches chose, the run's IOR), "clear glass"
    eta: list[float]  # each candidate's shared index of refraction
    scores: list[float]  # their held-out scores (lower is better; sRGB squared error, bias^2 + noise)
    bias2: list[float]  # the scores' noise-free squared bias ...
    variance: list[float]  # ... and the noise variance at the held-out spp (holdout.split_error)
    chosen: str
    chosen_eta: float  # the IOR the run keeps (Stage 2, final renders, the exported asset)
    seconds: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def clear_search(start_eta: float, clear_eta: float, prepare: Callable[[str, float], tuple[dict, object]],
                 score: Callable[[dict[str, np.ndarray]], tuple[float, float, float]], say=lambda s: None
                 ) -> tuple[dict[str, np.ndarray], object, ClearSearchInfo]:
    """Prepare (``prepare(label, eta) -> (values, info)``, which also sets the IOR the next ``score`` renders with)
    and score (``score(values) -> (score, bias2, variance)``, lower is better) the start at ``start_eta`` and the
    clear-glass start at ``clear_eta``; returns the better prepared values, its ``prepare`` info and the record.
    A non-finite score loses; a tie keeps the start."""
    t0 = time.perf_counter()
    tried = []
    for label, eta in (("start", float(start_eta)), ("clear glass", float(clear_eta))):
        values, info = prepare(label, eta)
        sc, b2, var = (float(x) for x in score(values))
        say(f"clear search: {label} (IOR {eta:g}) scores {sc:.4g} (bias^2 {b2:.4g}, variance {var:.4g})")
        tried.append((sc, label, eta, b2, var, values, info))
    start, clear = tried
    best = clear if np.isfinite(clear[0]) and (not np.isfinite(start[0]) or clear[0] < start[0]) else start
    record = ClearSearchInfo([t[1] for t in tried], [t[2] for t in tried], [t[0] for t in tried],
                             [t[3] for t in tried], [t[4] for t in tried], best[1], best[2],
                             time.perf_counter() - t0)
    return best[5], best[6], record
