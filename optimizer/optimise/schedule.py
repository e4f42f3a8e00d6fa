"""Learning-rate schedules (choices beyond the paper; the run presets are :mod:`optimizer.optimise.presets`).

The paper trains with constant Adam rates (1e-2 for the maps, 1e-1 for the displacement) for 50 Stage 1 and
20 Stage 2 iterations. Two things make a constant rate a poor fit on a CPU budget:

* with a warm-started albedo (:mod:`optimizer.optimise.warmstart`) the loss is near its plateau after a few steps, and
  what is left is Monte Carlo noise in the gradients: a constant normalised Adam step keeps every map value
  jittering by about one learning rate per step around its optimum;
* the displacement regulariser ``L_disp = E|d|`` (Eq. 5) has a gradient of constant size ``sign(d) / N``;
  Adam normalises it to a full step, so a texel the images do not constrain oscillates around 0 with an
  amplitude of about one learning rate (0.1 of the bound at the paper's rate), and texels with noisy
  photometric gradients random-walk. This is why ``L_disp`` grows or stalls instead of settling.

Two measures: a proximal step for the L1 term (``AppearanceConfig.displacement_shrink``: after each Adam step
``d <- sign(d) max(|d| - k lr_t, 0)``), which returns noise-driven texels to 0 while a texel with a consistent
photometric gradient still moves; and a cosine decay of every rate, ``scale(p) = floor + (1 - floor) (1 + cos(pi p)) / 2`` over the run's progress
``p`` in [0, 1], removes both: large steps early, vanishing jitter at the end. Progress is the larger of the
iteration fraction and, with ``--time-budget``, the fraction of the budget spent, so a time-limited run still
ends on small steps.
"""

from __future__ import annotations

import math

SCHEDULES = ("constant", "cosine")


def lr_scale(progress: float, kind: str = "cosine", floor: float = 0.1) -> float:
    """Learning-rate multiplier at ``progress`` in [0, 1] (clamped): 1 for ``constant``; cosine decay to ``floor``."""
    if kind == "constant":
        return 1.0
    if kind != "cosine":
        raise ValueError(f"unknown learning-rate schedule {kind!r}; choose one of: {', '.join(SCHEDULES)}")
    p = min(max(float(progress), 0.0), 1.0) if math.isfinite(progress) else 1.0
    return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * p))


def soft_threshold(x, k: float):
    """The proximal operator of ``k |x|``: ``sign(x) max(|x| - k, 0)`` on a (detached) Dr.Jit array or tensor."""
    import drjit as dr

    d = dr.detach(x)
    return type(d)(dr.select(d > 0, 1.0, -1.0) * dr.maximum(dr.abs(d) - k, 0.0))


def progress(iteration: int, iterations: int, seconds: float = 0.0, budget: float | None = None) -> float:
    """Fraction of a stage done: iterations done / planned, or seconds spent / budget if that is larger."""
    p = iteration / max(iterations, 1)
    if budget:
        p = max(p, seconds / budget)
    return min(max(p, 0.0), 1.0)
