"""A grain layer on the albedo, projected from the ground behind (``--grain G``, issue 29): the body gets the ground's
own pixel-scale texture instead of the smooth multi-view mean.

Why. The least-squares warm start (:mod:`optimizer.optimise.warmstart`) gives a texel the weighted mean, over the
training views that see it, of the albedo that would match each view's background. One texel is seen over different
ground pixels in different views, so the mean of V unrelated patches of grass or gravel keeps about 1 / sqrt(V) of
their amplitude, and Stage 1's squared error keeps it there: its multi-view optimum is that mean. Today's body ends
with a detail ratio of 0.57-0.74 on the grainy built-in scenes (docs/results/giveaways.md). Neither the map resolution
(at 128 texels and 64 px a texel is under a pixel) nor a term on the texture's energy (the detail term: blotches of
3-4 px, not the ground's grain) fixed it. This layer puts the ground's own texture on the body: the paper's projection
idea (Sec. III: the inpainted or projected background is what the texture should show), per texel from one view.

The layer. For each texel the warm start's observations are solved twice: over every view that sees it (the mean,
what the warm start keeps) and over its *best* view alone (the largest weight: the most head-on, fully covered view,
where the texel is least blurred over pixels). The residual::

    grain = clip(a_best, 0, 1) - clip(a_mean, 0, 1)

is the texture of that view's background that the mean averaged away, in albedo units (the material's own slope
``L1 - L0`` divides it out, so it holds for a transmissive, glossy start). Its low frequencies are small (the mean and
the best view agree on the ground's colour); what is left is grain. Stage 1 renders the albedo as::

    albedo_rendered = clip(albedo_fine + G grain (+ U c, the coarse level), low, 1)

with ``grain`` fixed (not a parameter: the squared error would scale it down to about 1 / V, the multi-view optimum
that makes the body smooth) and ``G`` the option's gain. The fine map and the coarse level are optimised under it;
the result the stage hands on is folded (:func:`fold`), so Stage 2, the saved maps and the exported asset carry the
grain and nothing downstream knows the layer existed. Texels no training view sees fully get no grain (0), as do
off-chart texels.

What it costs by construction: in a texel's best view the grain is that view's ground (free), in the others it is
unrelated texture of the same statistics, which adds its energy to their squared error. Measured in
docs/results/giveaways.md ("A grain layer projected from the ground"). Cost per step: one add of an ``R x R x 3``
constant; before Stage 1, one more least-squares solve per texel on the warm start's two renders (no render):
:func:`optimizer.optimise.warmstart.grain_residual`.
"""

from __future__ import annotations

import numpy as np


def best_view_weights(weight: np.ndarray) -> np.ndarray:
    """``weight (V, N)`` with only each texel's largest weight kept (its best view; the others 0).

    >>> best_view_weights(np.array([[0.2, 0.0], [0.9, 0.0], [0.5, 0.0]])).tolist()
    [[0.0, 0.0], [0.9, 0.0], [0.0, 0.0]]
    """
    w = np.asarray(weight, np.float64)
    w = np.where(np.isfinite(w), np.maximum(w, 0.0), 0.0)
    if w.size == 0:
        return w
    best = np.argmax(w, axis=0)
    out = np.zeros_like(w)
    cols = np.arange(w.shape[1])
    out[best, cols] = w[best, cols]
    return out


#: the unsharp mask's Gaussian (pixels) of ``--grain-sharpen``
SHARPEN_SIGMA = 0.7


def sharpen(images: np.ndarray, amount: float, sigma: float = SHARPEN_SIGMA) -> np.ndarray:
    """Unsharp mask ``B + amount (B - G_sigma B)`` of ``images (V, H, W, 3)`` (linear radiance; per view and channel,
    scipy's Gaussian, reflected edges), float32, not clipped (the least-squares solve clips the albedo).

    >>> x = np.zeros((1, 5, 5, 3)); x[0, 2, 2] = 1.0
    >>> float(sharpen(x, 0.0)[0, 2, 2, 0]), bool(sharpen(x, 2.0)[0, 2, 2, 0] > 1.5), bool(sharpen(x, 2.0)[0, 2, 1, 0] < 0)
    (1.0, True, True)
    """
    from scipy.ndimage import gaussian_filter

    b = np.asarray(images, np.float64)
    if amount == 0:
        return b.astype(np.float32)
    blur = np.stack([gaussian_filter(v, (sigma, sigma, 0), mode="reflect") for v in b])
    return (b + amount * (b - blur)).astype(np.float32)


def grain_map(surface, grain: np.ndarray, assigned: np.ndarray) -> np.ndarray:
    """An ``(R, R, 3)`` float32 map of per-texel ``grain (N, 3)`` on ``surface``
    (:class:`optimizer.rendering.projection.TexelSurface`) where ``assigned``; 0 elsewhere (unseen and off-chart
    texels)."""
    R = surface.resolution
    out = np.zeros((R * R, 3), np.float32)
    a = np.asarray(assigned, bool)
    out[np.asarray(surface.index)[a]] = np.asarray(grain, np.float32)[a]
    return out.reshape(R, R, 3)


def fold(values: dict[str, np.ndarray], grain: np.ndarray, gain: float, low: float) -> dict[str, np.ndarray]:
    """The albedo as rendered without a coarse level: ``clip(albedo + gain grain, low, 1)`` (a new dict; the other
    values as they are).

    >>> fold({"albedo": np.full((1, 1, 3), 0.5, np.float32)}, np.array([[[0.2, -0.6, 0.7]]]), 1.0, 0.01)["albedo"]
    array([[[0.7 , 0.01, 1.  ]]], dtype=float32)
    """
    out = dict(values)
    out["albedo"] = np.clip(np.asarray(values["albedo"], np.float64) + gain * np.asarray(grain, np.float64),
                            low, 1.0).astype(np.float32)
    return out
