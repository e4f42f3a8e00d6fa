"""Noise matching: the render with the object no noisier around the object than the background render.

A transmissive or glossy object under a compact light brings paths of high variance (light through it onto the
ground, the sun seen through it or mirrored in it): at the same spp its pixels and their surroundings are noisier
than the same pixels of the background render, and at 64 spp a participant can find it by its fireflies (measured
on the demo's result on meadow: RMS noise on the object 4.3/255 against 2.7/255 in the background, and 5 pixels in
1000 off by more than 20/255 against none). A uniform spp cannot fix that (both noises fall alike), so the noise is
matched per pixel:

1. the with-object render at ``spp`` (the pixels the object can change) keeps each pixel's per-sample variance
   (:func:`optimizer.rendering.render.render_moments`), as does the background render;
2. both variances, in sRGB (the encoding's slope at each pixel's value), are box-filtered over ``window`` pixels
   (a variance from one pixel's samples is itself too noisy, fireflies most of all);
3. a pixel whose with-object variance exceeds the background's by a factor ``r > 1.1`` gets ``k - 1`` times ``spp``
   further samples (new ones: samples ``spp`` to ``k spp - 1``), ``k`` the power of two at or above ``r / 1.1``, at
   most ``max_factor``: its mean over ``k spp`` samples has (within 10 %) the background's noise.

The estimate stays unbiased (more samples of the same estimator), the first ``spp`` samples of every pixel are the
background's (common random numbers are kept where the object does not matter: there ``k = 1``). What remains
above the background's noise (pixels that hit ``max_factor``) is reported.
"""

from __future__ import annotations

import dataclasses

import numpy as np

MAX_FACTOR = 8
WINDOW = 5
#: A variance ratio up to this is left alone (its estimate from one render is not finer than that).
TOLERANCE = 1.1


@dataclasses.dataclass
class NoiseMatch:
    factor: np.ndarray  # (V, H, W) int: total spp / base spp per pixel (1 outside the region)
    ratio: np.ndarray  # (V, H, W) float: with-object / background per-sample variance (filtered), before matching
    extra_samples: float  # extra samples as a share of one full-frame render at the base spp
    seconds: float

    def to_dict(self) -> dict:
        sel = self.factor > 1
        return {"extra_samples_share": round(float(self.extra_samples), 4),
                "pixels_with_more_samples": round(float(sel.mean()), 4),
                "max_factor_hit": round(float((self.factor >= MAX_FACTOR).mean()), 5),
                "variance_ratio_p95": round(float(np.percentile(self.ratio, 95)), 3) if self.ratio.size else 0.0,
                "seconds": round(self.seconds, 3)}


def srgb_variance(image: np.ndarray, lum2: np.ndarray) -> np.ndarray:
    """Per-sample variance of a pixel's sRGB value (first order: the encoding's slope at its luminance) from the mean
    image ``(..., 3)`` and the mean squared luminance ``(...)``."""
    from optimizer.rendering.pilot import srgb_slope
    from optimizer.rendering.tracer import LUMA

    y = np.asarray(image, np.float64) @ np.asarray(LUMA)
    return srgb_slope(np.clip(y, 0, None)) ** 2 * np.maximum(np.asarray(lum2, np.float64) - y * y, 0.0)


def factors(obj_var: np.ndarray, bg_var: np.ndarray, region: np.ndarray, window: int = WINDOW,
            max_factor: int = MAX_FACTOR) -> tuple[np.ndarray, np.ndarray]:
    """``(factor, ratio)`` per pixel ``(V, H, W)`` (see the module doc)."""
    from scipy.ndimage import uniform_filter

    o = np.stack([uniform_filter(v, window) for v in obj_var])
    b = np.stack([uniform_filter(v, window) for v in bg_var])
    ratio = np.where(region, o / np.maximum(b, 1e-12), 1.0)
    ratio = np.where(region & (b <= 1e-12) & (o <= 1e-12), 1.0, ratio)
    k = np.ones(ratio.shape, np.int64)
    for f in (2, 4, 8, 16, 32):
        if f > max_factor:
            break
        k = np.where(ratio > TOLERANCE * (f // 2), f, k)
    return np.where(region, k, 1), ratio


def match(render_more, image: np.ndarray, lum2: np.ndarray, bg_image: np.ndarray, bg_lum2: np.ndarray,
          region: np.ndarray, spp: int, window: int = WINDOW, max_factor: int = MAX_FACTOR
          ) -> tuple[np.ndarray, NoiseMatch]:
    """The with-object ``image`` with its noise matched to the background's (module doc). ``render_more(masks, spp,
    first_sample)`` renders further samples of the pixels in ``masks`` (``(V, H, W, 3)`` means of those samples);
    ``lum2`` / ``bg_lum2``: mean squared luminance per sample of the two renders at ``spp``."""
    import time

    t0 = time.perf_counter()
    k, ratio = factors(srgb_variance(image, lum2), srgb_variance(bg_image, bg_lum2), region, window, max_factor)
    out = np.array(image, np.float32, copy=True)
    extra = 0
    for f in sorted(set(np.unique(k).tolist()) - {1}):
        sel = k == f
        more = render_more(sel, (f - 1) * spp, spp)
        out[sel] = (image[sel] + (f - 1) * more[sel]) / f
        extra += int(sel.sum()) * (f - 1)
    return out, NoiseMatch(k, ratio[region] if region.any() else np.zeros(0), extra / max(k.size, 1),
                           time.perf_counter() - t0)


def noise_rms(a1: np.ndarray, a2: np.ndarray, pixels: np.ndarray) -> float:
    """RMS noise (8-bit sRGB units) of a render from two independent copies of it: ``|a1 - a2| / sqrt 2``, as the
    saved PNGs hold them, over ``pixels``."""
    from camo_base.imaging import linear_to_srgb

    e = lambda x: np.round(np.clip(linear_to_srgb(np.clip(x, 0, None)), 0, 1) * 255)  # noqa: E731
    d = (e(a1) - e(a2))[pixels] / np.sqrt(2.0)
    return float(np.sqrt(np.mean(d ** 2))) if d.size else 0.0
