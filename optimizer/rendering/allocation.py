"""Samples where they buy the most error per second: per-pixel spp for a render with the object.

A uniform ``spp`` spends as many samples on a pixel that converges fast as on one that does not, and as many on a
pixel whose samples are cheap (a path that meets the ground twice) as on one whose samples are dear (a path through
a transmissive principled BSDF: measured ~10x the seconds per sample on the built-in scenes). For a fixed error the
cheapest allocation (Neyman's, weighted by cost) gives pixel ``i`` with per-sample variance ``v_i`` and cost per
sample ``c_i``

    n_i = lambda * sqrt(v_i / c_i),   lambda chosen so that   sum_i v_i / n_i = sum_i v_i / spp,

the summed variance (the frame's mean squared error) that a uniform ``spp`` would have: the same error, and never
more seconds (Cauchy-Schwarz). :func:`render_allocated` does it in three steps:

1. a **base pass**: every pixel rendered (the region the object can change, :mod:`optimizer.rendering.region`,
   searched at this pass's spp) with ``spp / BASE_SHARE`` samples, kept as ``OBJECT_GROUPS`` group means;
2. **per-pixel variances** of the with-object render and of the background (its groups of the same size: the
   background is rendered with ``background_groups(spp)`` groups), in sRGB clipped to [0, 1] (the encoding the
   error and the eye see), pooled over each pixel's ``window x window`` neighbours **leaving the pixel itself out**
   (:func:`optimizer.rendering.noise.pooled`): a pixel's count never depends on its own samples, so its mean stays
   unbiased (the global scale ``lambda`` depends on every pixel: an O(1/N) coupling). The cost per sample of the
   object's pixels and of the others is timed once per scene (:func:`measure_costs`);
3. **extra passes**: samples ``n`` onward of the pixels whose count is above ``n``, for ``n`` on the ladder
   ``base * FACTORS`` (a pixel's count is rounded up to it; at most ``len(FACTORS) - 1`` launches, each pixel's
   random stream continued, so the first ``spp`` samples of a pixel are the background's where it gets ``spp``).

**Noise never gives the object away** (issue 28, item 4): with ``noise_floor`` a pixel also gets at least
``spp * v_i / (TOLERANCE * vb_i)`` samples (``vb_i`` the background's pooled variance in the same pixel, rendered
at ``spp``): its noise variance is at most ``TOLERANCE`` times the background's there. A pixel whose render is
noisier than the background's gets more samples (as :mod:`optimizer.rendering.noise` does); a pixel where the
object is less noisy than the background (often: a body that hides a bright, noisy background) may get fewer.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: The base pass takes ``spp / BASE_SHARE`` samples per pixel.
BASE_SHARE = 4
#: A pixel's count is rounded up to ``base * f`` for ``f`` in this ladder (``FACTORS[-1] / BASE_SHARE`` x ``spp`` at
#: most); each step is one launch of the pixels above it.
FACTORS = (1, 2, 3, 4, 6, 8, 12, 16)
#: Group means kept by the base pass (their spread gives the per-pixel variance).
OBJECT_GROUPS = 4
#: Neighbourhood (pixels) over which the variances are pooled, the pixel itself left out.
WINDOW = 5
#: A pixel's noise variance may exceed the background's by this factor (the estimate is not finer than that).
TOLERANCE = 1.1


def check_spp(spp: int) -> None:
    """Refuse an ``spp`` the allocation cannot split into its base pass and groups (one line)."""
    q = BASE_SHARE * OBJECT_GROUPS
    if int(spp) != spp or spp < q or spp % q:
        raise ValueError(f"per-pixel sample allocation needs spp a multiple of {q} (base pass spp/{BASE_SHARE} "
                         f"in {OBJECT_GROUPS} groups), got {spp}")


def background_groups(spp: int) -> int:
    """How many group means the background at ``spp`` keeps so that its groups hold as many samples as the base
    pass's (the sRGB variance of a group mean depends on its size: both must be alike to be compared)."""
    check_spp(spp)
    return BASE_SHARE * OBJECT_GROUPS


@dataclasses.dataclass
class Allocation:
    samples: np.ndarray  # (V, H, W) int: samples of the with-object render per pixel (0: the background's pixel)
    spp: int  # the uniform spp the error is matched to
    base: int  # samples of the base pass
    floor_share: float  # share of the rendered pixels whose count the noise floor set (above Neyman's)
    costs: tuple[float, float]  # CPU seconds per sample: object's pixels, the others
    seconds: float  # allocation and extra passes

    @property
    def extra_samples(self) -> float:
        """Samples beyond a uniform ``spp`` over the rendered pixels, as a share of one full frame at ``spp``
        (negative: fewer)."""
        rendered = self.samples > 0
        return float((self.samples[rendered] - self.spp).sum() / (self.samples.size * self.spp))

    def to_dict(self) -> dict:
        s = self.samples[self.samples > 0]
        return {"method": "allocation", "spp": self.spp, "base": self.base,
                "samples_share": round(float(s.sum() / (self.samples.size * self.spp)), 4) if s.size else 0.0,
                "extra_samples_share": round(self.extra_samples, 4),
                "samples_p5_p50_p95": [int(x) for x in np.percentile(s, [5, 50, 95])] if s.size else [],
                "floor_share": round(self.floor_share, 4),
                "cost_per_sample_object_other": [float(f"{c:.3g}") for c in self.costs],
                "seconds": round(self.seconds, 3)}


def per_sample_variance(groups: np.ndarray, samples_per_group: int) -> np.ndarray:
    """``(V, H, W)``: the per-sample variance of a pixel's sRGB value (clipped to [0, 1], mean over channels) from
    the means of ``G`` groups of ``samples_per_group`` samples each, ``groups (G, V, H, W, 3)`` linear: the
    variance over the groups (``ddof = 1``) times the group size."""
    from camo_base.imaging import linear_to_srgb

    g = np.asarray(groups)
    if g.ndim != 5 or g.shape[0] < 2:
        raise ValueError(f"groups must be (G >= 2, V, H, W, 3), got {g.shape}")
    e = np.clip(linear_to_srgb(np.clip(g, 0, None)), 0, 1).astype(np.float64)
    return e.var(0, ddof=1).mean(-1) * float(samples_per_group)


def ladder(base: int) -> np.ndarray:
    return np.array([base * f for f in FACTORS], np.int64)


def neyman(var: np.ndarray, cost: np.ndarray, target: float, floor: np.ndarray, levels: np.ndarray,
           iterations: int = 60) -> np.ndarray:
    """Samples per pixel (1-D arrays of the rendered pixels): ``n_i = lambda sqrt(var_i / cost_i)`` at least
    ``floor_i``, rounded up to the ladder ``levels`` (ascending sample counts), with the least ``lambda`` for which
    ``sum var / n <= target`` (bisection in log lambda; when even the ladder's top cannot reach ``target``, the top
    everywhere). A pixel of zero variance gets its floor.

    >>> import numpy as np
    >>> neyman(np.array([4.0, 1.0]), np.ones(2), 5.0 / 8, np.zeros(2), np.array([1, 2, 4, 8, 16])).tolist()
    [4, 2]
    """
    var = np.asarray(var, np.float64)
    cost = np.asarray(cost, np.float64)
    if var.shape != cost.shape or var.shape != np.shape(floor):
        raise ValueError(f"var, cost and floor must have one shape, got {var.shape}, {cost.shape}, {np.shape(floor)}")
    if np.any(cost <= 0) or not np.all(np.isfinite(cost)):
        raise ValueError("cost per sample must be positive and finite")
    if target <= 0:
        raise ValueError(f"target summed variance must be positive, got {target}")
    levels = np.asarray(levels, np.int64)
    floor = np.clip(np.asarray(floor, np.float64), levels[0], levels[-1])
    shape = np.sqrt(np.maximum(var, 0.0) / cost)

    def counts(lam: float) -> np.ndarray:
        n = np.maximum(lam * shape, floor)
        return levels[np.minimum(np.searchsorted(levels, n - 1e-9, "left"), len(levels) - 1)]

    def summed(n: np.ndarray) -> float:
        return float(np.sum(var / n))

    if summed(counts(0.0)) <= target or not np.any(shape > 0):
        return counts(0.0)
    if summed(counts(1e300)) > target:  # the ladder's top cannot reach the target: the top everywhere
        return counts(1e300)
    lo, hi = -60.0, 60.0  # log lambda
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if summed(counts(float(np.exp(mid)))) <= target:
            hi = mid
        else:
            lo = mid
    return counts(float(np.exp(hi)))


def allocate(obj_var: np.ndarray, bg_var: np.ndarray, cost: np.ndarray, rendered: np.ndarray, spp: int,
             noise_floor: bool = True, window: int = WINDOW) -> tuple[np.ndarray, float]:
    """``(samples (V, H, W) int, floor_share)``: the per-pixel counts of the module doc for the pixels
    ``rendered (V, H, W)`` (0 elsewhere). ``obj_var`` / ``bg_var``: per-sample variances ``(V, H, W)`` of the
    with-object render (valid on ``rendered``) and of the background; ``cost``: seconds per sample ``(V, H, W)``."""
    from optimizer.rendering.noise import pooled

    check_spp(spp)
    rendered = np.asarray(rendered, bool)
    vo = pooled(np.where(rendered, obj_var, 0.0), window)
    # the pooling leaves the pixel out and averages its neighbours; outside ``rendered`` the with-object variance
    # is unknown: the neighbours' mean over the rendered ones only
    w = pooled(rendered.astype(np.float64), window)
    vo = np.where(w > 0, vo / np.maximum(w, 1e-12), pooled(obj_var, window))
    vb = pooled(bg_var, window)
    base = spp // BASE_SHARE
    levels = ladder(base)
    sel = rendered
    v, c = vo[sel], np.asarray(cost, np.float64)[sel]
    if noise_floor:
        floor = np.where(vb[sel] > 1e-12, spp * v / (TOLERANCE * np.maximum(vb[sel], 1e-12)),
                         np.where(v > 1e-12, levels[-1], base))
    else:
        floor = np.zeros(v.shape)
    target = max(float(v.sum()) / spp, 1e-12)
    n = neyman(v, c, target, floor, levels)
    free = neyman(v, c, target, np.zeros(v.shape), levels) if noise_floor else n
    out = np.zeros(rendered.shape, np.int64)
    out[sel] = n
    return out, float(np.mean(n > free)) if n.size else 0.0


def measure_costs(renderer, coverage: np.ndarray, rendered: np.ndarray, spp: int) -> tuple[float, float]:
    """CPU seconds per sample ``(object's pixels, the others)`` of ``renderer`` (a
    :class:`optimizer.rendering.render.PathRenderer` with the object), timed on ``spp`` samples of the object's
    pixels (``coverage > 0``) within ``rendered`` and of as many other rendered pixels (the least of two launches
    each, after one that compiles). Once per scene: the ratio is what the allocation uses."""
    import time

    obj = (np.asarray(coverage) > 0) & rendered
    rest = rendered & ~obj
    idx = np.flatnonzero(rest)
    if obj.sum() and idx.size > obj.sum():  # as many other pixels as object pixels, spread over the region
        keep = idx[np.linspace(0, idx.size - 1, int(obj.sum())).astype(np.int64)]
        rest = np.zeros(rendered.size, bool)
        rest[keep] = True
        rest = rest.reshape(rendered.shape)
    out = []
    for m in (obj, rest):
        if not m.any():
            out.append(float("nan"))
            continue
        best = float("inf")
        for k in range(3):
            t = time.process_time()
            renderer(m, None, spp=spp, first_sample=10_000 + k * spp)
            if k:
                best = min(best, time.process_time() - t)
        out.append(max(best, 1e-9) / (float(m.sum()) * spp))
    c_obj, c_rest = out
    if not np.isfinite(c_obj):
        c_obj = c_rest
    if not np.isfinite(c_rest):
        c_rest = c_obj
    return (float(c_obj), float(c_rest)) if np.isfinite(c_obj) else (1.0, 1.0)


def extra_passes(renderer, image: np.ndarray, samples: np.ndarray, base: int) -> np.ndarray:
    """``image (V, H, W, 3)`` (the base pass's means, ``base`` samples per pixel) with every pixel's count raised to
    ``samples (V, H, W)``: one launch per ladder step, samples ``n`` to ``n'`` of the pixels whose count is at least
    ``n'``; each pixel's mean over all its samples."""
    levels = ladder(base)
    total = np.array(image, np.float64, copy=True) * base
    for lo, hi in zip(levels[:-1], levels[1:]):
        sel = samples >= hi
        if not sel.any():
            break
        more = renderer(sel, None, spp=int(hi - lo), first_sample=int(lo))
        total[sel] += np.asarray(more, np.float64)[sel] * float(hi - lo)
    out = total / np.maximum(samples, 1)[..., None]
    return np.where((samples > 0)[..., None], out, image).astype(np.float32)
