"""Noise matching: the render with the object no noisier around the object than the background render.

A transmissive or glossy object under a compact light brings paths of high variance (light through it onto the
ground, the sun seen through it or mirrored in it): at the same spp its pixels and their surroundings are noisier
than the same pixels of the background render, and at 64 spp a participant can find it by its fireflies (measured
on the demo's result on meadow: RMS noise on the object 4.2/255 against 2.7/255 in the background, and 4 pixels in
1000 off by more than 20/255 against none). A uniform spp cannot fix that (both noises fall alike), so the noise is
matched per pixel:

1. each render (with the object: its region; the background: every pixel) keeps the means of ``G`` equal groups of
   its samples (:func:`groups_for`: 4 at multiples of 4 spp, one sample each at 5-7 spp;
   :func:`optimizer.rendering.tracer.render_pixels`, no extra cost): the variance of their 8-bit sRGB values over the
   groups, divided by ``G``, estimates the noise the saved image shows -- in the encoding that
   is seen, clipping included (a per-sample variance in linear units misjudges fireflies both ways: it misses the
   rare ones and overrates the clipped ones);
2. both are pooled over the ``window x window`` pixels around each pixel, **leaving the pixel itself out**: a pixel's
   extra samples are decided by its neighbours' samples, never its own (a pixel given more samples because its own
   samples came out bright would be diluted exactly there: biased low). The neighbours' streams are independent of
   its own, so the estimate stays unbiased;
3. a pixel whose noise variance exceeds the background's by ``r > 1.1`` gets ``k - 1`` times ``spp`` further samples
   (samples ``spp`` to ``k spp - 1`` of its stream), ``k`` the power of two at or above ``r / 1.1``, at most
   ``max_factor``: its mean over ``k spp`` samples has (within 10 %) the background's noise.

The first ``spp`` samples of every pixel are the background's (common random numbers are kept where the object does
not matter: there ``k = 1``). What remains above the background's noise (pixels that hit ``max_factor``) is
reported. What it cannot do: light through a near-specular surface (roughness below ~0.1) straight from the sun is
rarer than one in a few thousand samples and far brighter than the rest; 8x the samples do not tame it. Noise
matching is for the rough transmission and gloss the optimiser produces (the built-in scenes start at roughness 0.5
under compact lights, ``optimizer.rendering.planner.GLINT_ROUGHNESS``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

MAX_FACTOR = 8
WINDOW = 5
GROUPS = 4


def groups_for(spp: int) -> int:
    """How many groups of its samples a render at ``spp`` keeps for noise matching: the fewest equal groups, at least
    :data:`GROUPS` (so the variance over them has at least 3 degrees of freedom), that divide ``spp`` -- 4 at any
    multiple of 4, ``spp`` itself at 5, 6, 7 (groups of one sample), 5 at 10 -- or 0 below :data:`GROUPS` spp (no
    matching). The groups must be equal: :func:`display_variance` divides their variance by their count, which
    estimates the noise of their mean only when every group has the same number of samples. A background and a
    render with the object at the same spp get the same count, so their noise estimates (of 8-bit sRGB group means,
    clipping included) are alike and their ratio is what matching compares."""
    spp = int(spp)
    if spp < GROUPS:
        return 0
    return next(g for g in range(GROUPS, spp + 1) if spp % g == 0)
#: How :func:`match` makes a pixel's total factor from noise matching's and a boost's (the object's spp factor).
COMBINE = ("product", "max")
#: A noise-variance ratio up to this is left alone (its estimate is not finer than that).
TOLERANCE = 1.1


@dataclasses.dataclass
class NoiseMatch:
    factor: np.ndarray  # (V, H, W) int: total spp / base spp per pixel (1 outside the region)
    ratio: np.ndarray  # (N,) float: with-object / background noise variance (pooled) in the region, before matching
    extra_samples: float  # extra samples as a share of one full-frame render at the base spp
    seconds: float

    def to_dict(self) -> dict:
        sel = self.factor > 1
        return {"extra_samples_share": round(float(self.extra_samples), 4),
                "pixels_with_more_samples": round(float(sel.mean()), 4),
                "max_factor_hit": round(float((self.factor >= MAX_FACTOR).mean()), 5),
                "variance_ratio_p95": round(float(np.percentile(self.ratio, 95)), 3) if self.ratio.size else 0.0,
                "seconds": round(self.seconds, 3)}


def display_variance(groups: np.ndarray) -> np.ndarray:
    """``(V, H, W)``: the noise variance of the saved 8-bit sRGB image (units of 1/255, mean over channels)
    estimated from the means of ``G`` groups of its samples ``(G, V, H, W, 3)``: their variance over the groups
    (``ddof = 1``) divided by ``G``."""
    from camo_base.imaging import linear_to_srgb

    e = np.round(np.clip(linear_to_srgb(np.clip(groups, 0, None)), 0, 1) * 255.0)
    g = e.shape[0]
    return (e.var(0, ddof=1) / g).mean(-1)


def pooled(values: np.ndarray, window: int) -> np.ndarray:
    """The mean of ``values (V, H, W)`` over each pixel's ``window x window`` neighbourhood without the pixel itself
    (at the frame's edge, over the neighbours that exist)."""
    from scipy.ndimage import uniform_filter

    n = float(window * window)
    ones = np.ones(values.shape[1:])
    out = []
    for v in values:
        s = uniform_filter(v.astype(np.float64), window, mode="constant") * n - v
        c = uniform_filter(ones, window, mode="constant") * n - 1.0
        out.append(s / np.maximum(c, 1.0))
    return np.stack(out)


def factors(obj_var: np.ndarray, bg_var: np.ndarray, region: np.ndarray, window: int = WINDOW,
            max_factor: int = MAX_FACTOR) -> tuple[np.ndarray, np.ndarray]:
    """``(factor, ratio)`` per pixel ``(V, H, W)`` from the noise variances with and without the object (module
    doc; the region's pixels only, 1 elsewhere)."""
    o, b = pooled(obj_var, window), pooled(bg_var, window)
    ratio = np.where(region, o / np.maximum(b, 1e-6), 1.0)
    ratio = np.where(region & (b <= 1e-6) & (o <= 1e-6), 1.0, ratio)
    k = np.ones(ratio.shape, np.int64)
    for f in (2, 4, 8, 16, 32):
        if f > max_factor:
            break
        k = np.where(ratio > TOLERANCE * (f // 2), f, k)
    return np.where(region, k, 1), ratio


def match(render_more, image: np.ndarray, groups: np.ndarray, bg_groups: np.ndarray, region: np.ndarray, spp: int,
          window: int = WINDOW, max_factor: int = MAX_FACTOR,
          boost: np.ndarray | None = None, combine: str = "product") -> tuple[np.ndarray, NoiseMatch]:
    """The with-object ``image`` (``spp`` samples) with its noise matched to the background's (module doc).
    ``groups`` / ``bg_groups``: ``(G, V, H, W, 3)`` group means of the two renders (the with-object one over
    ``region``); ``render_more(counts, spp, first_sample)`` renders ``counts (V, H, W)`` x ``spp`` further samples
    per pixel (their means; :func:`more_samples`). ``boost (V, H, W)`` int: a further factor on the matched one
    (the object's spp factor before a denoiser, :func:`evaluation.views.object_spp_pilot`); it must not depend on
    the render's samples. ``combine``: how a pixel's matched factor and its boost make its total (:data:`COMBINE`:
    ``product`` multiplies them; ``max`` takes the larger: the boost already gives the object's pixels the samples
    matching would, so they are not multiplied on top)."""
    import time

    if combine not in COMBINE:
        raise ValueError(f"combine must be one of {', '.join(COMBINE)}, got {combine!r}")
    t0 = time.perf_counter()
    k, ratio = factors(display_variance(groups), display_variance(bg_groups), region, window, max_factor)
    if boost is not None:  # a factor decided from geometry, not from any pixel's samples: stays unbiased
        b = np.asarray(boost, np.int64)
        k = np.where(region, k * b if combine == "product" else np.maximum(k, b), k)
    out, extra = more_samples(render_more, image, k, spp)
    return out, NoiseMatch(k, ratio[region] if region.any() else np.zeros(0), extra,
                           time.perf_counter() - t0)


def more_samples(render_more, image: np.ndarray, factor: np.ndarray, spp: int) -> tuple[np.ndarray, float]:
    """``image`` (``spp`` samples per pixel) with ``factor (V, H, W)`` times the samples per pixel: samples ``spp``
    to ``factor * spp - 1`` of each pixel's stream (``render_more(counts, spp, first_sample)``: per pixel the mean
    of ``counts * spp`` samples from ``first_sample`` on, :class:`optimizer.rendering.render.PathRenderer` with
    ``counts``), merged as the mean of all ``factor * spp`` samples -- the same estimator as one render at that spp
    (``tests/test_noise.py``). One launch for every factor (was one per distinct factor: each launch's fixed cost,
    ~25 ms at 96 px, is most of the matching's at low spp). Returns the image and the extra samples as a share of
    one full-frame render at ``spp``."""
    factor = np.asarray(factor, np.int64)
    if factor.shape != image.shape[:3]:
        raise ValueError(f"factor has shape {factor.shape}, the image {image.shape[:3]}")
    if (factor < 1).any():
        raise ValueError("every factor must be >= 1")
    out = np.array(image, np.float32, copy=True)
    sel = factor > 1
    if not sel.any():
        return out, 0.0
    more = render_more(factor - 1, spp, spp)
    f = factor[sel][:, None].astype(np.float32)
    out[sel] = (image[sel] + (f - 1) * more[sel]) / f
    return out, float((factor - 1).sum()) / max(factor.size, 1)


def noise_rms(a1: np.ndarray, a2: np.ndarray, pixels: np.ndarray) -> float:
    """RMS noise (8-bit sRGB units) of a render from two independent copies of it: ``|a1 - a2| / sqrt 2``, as the
    saved PNGs hold them, over ``pixels``."""
    from camo_base.imaging import linear_to_srgb

    e = lambda x: np.round(np.clip(linear_to_srgb(np.clip(x, 0, None)), 0, 1) * 255)  # noqa: E731
    d = (e(a1) - e(a2))[pixels] / np.sqrt(2.0)
    return float(np.sqrt(np.mean(d ** 2))) if d.size else 0.0


def fireflies(a1: np.ndarray, a2: np.ndarray, pixels: np.ndarray, level: float = 20.0) -> float:
    """Per 1000 pixels of ``pixels``: those whose two 8-bit sRGB renders differ by more than ``level`` (any
    channel)."""
    from camo_base.imaging import linear_to_srgb

    e = lambda x: np.round(np.clip(linear_to_srgb(np.clip(x, 0, None)), 0, 1) * 255)  # noqa: E731
    d = np.abs(e(a1) - e(a2)).max(-1)[pixels]
    return float((d > level).mean() * 1000) if d.size else 0.0
