"""Where the object gives itself away: a view's error split into the object, its cast shadow and the rest.

A camouflaged object is found where the image with it differs from the image without it. That difference has
three places, and this module separates them for one region (the full frame or the object crop) of one view:

* **object**: the visible-object mask and its 1-px ring (pixels the object covers partly, below the mask's 0.5
  coverage, are coloured by the object's silhouette; counting them here keeps edge pixels out of the shadow);
* **shadow**: pixels outside that which the object makes *darker*: its cast shadow and its contact / ambient
  occlusion (:func:`shadow_mask`);
* **rest**: everything else (reflections and light the object throws on its surroundings, render noise).

For each part the module reports its pixel count, its part of the region's mean squared error and its part of
the region's LPIPS (:func:`split_region`). The squared error is the per-pixel mean over the three sRGB channels
(what PSNR averages): the three ``sqerr_*`` are sums over the part's pixels divided by the region's pixel count,
so they add up to the region's MSE.

LPIPS is not a sum over pixels: each of its features sees a neighbourhood (AlexNet's relu5 is 16x coarser than
the image), so its spatial map (:func:`evaluation.metrics.lpips_map`) spreads the object's and the shadow's
difference over the pixels around them, and the map's share of "rest" pixels says more about the receptive field
than about the rest of the image. The LPIPS parts are therefore the **Shapley values** of the three parts: with
``v(S) = LPIPS(image that has the parts in S from the with-object render and the others from the background,
background)``, ``lpips_<part>`` is the part's marginal contribution ``v(S + part) - v(S)`` averaged over the
orders in which the parts can be added (8 composites, one LPIPS batch). They add up exactly to ``v(all) =`` the
region's LPIPS (``v(none) = 0``), and for a metric that is a sum over pixels (the squared error) the Shapley
values are exactly the per-part sums above: the two splits mean the same thing.

**Shadow threshold (noise-aware).** Images are compared as the metrics see them: 8-bit sRGB. With ``L`` the Rec.
709 luma of the sRGB values (in [0, 1]) and ``D = box3(L_without - L_with)`` the darkening averaged over 3x3
pixels, a pixel outside the object is shadow when ``D > tau`` with

    tau = max(SHADOW_SIGMAS * sigma, SHADOW_MIN_STEP),   sigma = 1.4826 * median(|D|) over the outside pixels with D < 0

and the pixel itself darker (``L_without - L_with > 0``: the 3x3 average alone would widen the shadow by a pixel).

``sigma`` is a robust standard deviation of ``D`` itself, so it measures the render noise as it survives the 3x3
average, including any correlation between the two renders. It is taken from the pixels the object makes
*brighter*: render noise is symmetric and a shadow only darkens, so the shadow does not inflate it, and pixels
rendered identically in both images (camo renders both with the same sampler seed: far from the object the noise
cancels exactly) do not deflate it; light the object throws on its surroundings brightens too and only makes the
threshold more conservative. ``SHADOW_SIGMAS = 3`` lets through ~0.1 % of pure-noise pixels (one-sided Gaussian);
``SHADOW_MIN_STEP = 2/255`` is the smallest darkening counted at all: one 8-bit step of both images' rounding, plus
one. The threshold is estimated on the full frame and used for both regions. Soft, wide shadows (an object in a
diffusely lit room) reach the floor only in patches: their mask is ragged at its edge.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from camo_base.tables import read_parquet
from evaluation.evaldir import SPLIT_COLUMNS, SPLIT_PARTS as PARTS

#: Noise multiples of the darkening a shadow pixel must exceed (see the module docstring).
SHADOW_SIGMAS = 3.0
#: Smallest darkening (sRGB luma, [0, 1]) counted as shadow: two 8-bit steps.
SHADOW_MIN_STEP = 2.0 / 255.0
#: MAD -> standard deviation of a Gaussian.
MAD_TO_SIGMA = 1.4826
#: Fewest brightened pixels the noise estimate uses (below it: the 2/255 floor).
MIN_NOISE_SAMPLES = 30
_LUMA = np.array([0.2126, 0.7152, 0.0722])


def _unit(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img)
    return a.astype(np.float64) / 255.0 if a.dtype == np.uint8 else a.astype(np.float64)


def _box3(a: np.ndarray) -> np.ndarray:
    """3x3 mean with edge replication."""
    p = np.pad(a, 1, mode="edge")
    h, w = a.shape
    return sum(p[i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0


def object_region(mask: np.ndarray) -> np.ndarray:
    """The mask and its 1-px ring (8-neighbourhood dilation), ``(H, W)`` bool."""
    m = np.asarray(mask, dtype=bool)
    p = np.pad(m, 1)
    h, w = m.shape
    out = np.zeros_like(m)
    for i in range(3):
        for j in range(3):
            out |= p[i:i + h, j:j + w]
    return out


def shadow_mask(obj_srgb: np.ndarray, bg_srgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """The object's cast shadow: pixels outside :func:`object_region` darker in the with-object image by more than
    the noise-aware threshold of the module docstring.

    Args:
        obj_srgb: the view with the object, ``(H, W, 3)`` sRGB, ``uint8`` or float in [0, 1].
        bg_srgb: the same view without it.
        mask: ``(H, W)`` bool, the visible object.

    Returns:
        ``(shadow, tau)``: ``(H, W)`` bool and the threshold used (sRGB luma units, [0, 1]).
    """
    lo, lb = _unit(obj_srgb) @ _LUMA, _unit(bg_srgb) @ _LUMA
    raw = lb - lo
    dark = _box3(raw)
    outside = ~object_region(mask)
    tau = noise_threshold(dark[outside])
    return (dark > tau) & (raw > 0) & outside, tau


def noise_threshold(dark: np.ndarray) -> float:
    """``max(3 sigma, 2/255)`` for the darkening values ``dark`` (3x3-averaged, outside the object): ``sigma`` is
    ``1.4826 * median(|D|)`` over the *brightened* pixels (``D < 0``), whose values render noise alone makes --
    noise is symmetric, a shadow only darkens -- so neither the shadow nor the exact zeros of pixels rendered
    identically in both images (same sampler seed, far from the object) bias it; light the object throws on its
    surroundings also brightens, which only raises the threshold. With fewer than
    :data:`MIN_NOISE_SAMPLES` brightened pixels (a noise-free pair), the floor applies."""
    neg = dark[dark < 0]
    sigma = MAD_TO_SIGMA * float(np.median(-neg)) if neg.size >= MIN_NOISE_SAMPLES else 0.0
    return max(SHADOW_SIGMAS * sigma, SHADOW_MIN_STEP)


def _shapley(values: dict[frozenset, float], players: tuple[str, ...]) -> dict[str, float]:
    """Shapley values of ``players`` for the set function ``values`` (every subset given)."""
    n = len(players)
    out = {}
    for p in players:
        others = [q for q in players if q != p]
        phi = 0.0
        for k in range(n):
            for subset in itertools.combinations(others, k):
                s_ = frozenset(subset)
                weight = math.factorial(k) * math.factorial(n - k - 1) / math.factorial(n)
                phi += weight * (values[s_ | {p}] - values[s_])
        out[p] = phi
    return out


def split_region(obj_srgb: np.ndarray, bg_srgb: np.ndarray, mask: np.ndarray, shadow: np.ndarray,
                 lpips_fn: Callable[[np.ndarray, np.ndarray], Sequence[float]] | None = None) -> dict[str, float]:
    """Pixels, squared error and LPIPS of one region split into object / shadow / rest (module docstring).

    Args:
        obj_srgb, bg_srgb: the region's images ``(h, w, 3)`` sRGB (``uint8`` or [0, 1] float).
        mask: the region's object mask ``(h, w)``; ``shadow``: its shadow mask (:func:`shadow_mask`, cropped).
        lpips_fn: ``lpips_fn(images, backgrounds) -> values`` for batches ``(B, h, w, 3)`` (the LPIPS metric);
            None: no LPIPS split (NaN).

    Returns:
        ``pixels_<part>`` (counts), ``sqerr_<part>`` (adding up to the region's MSE, sRGB [0, 1] units) and
        ``lpips_<part>`` (Shapley values, adding up to the region's LPIPS; NaN without ``lpips_fn``).
    """
    obj = object_region(mask)
    shadow = np.asarray(shadow, dtype=bool) & ~obj
    parts = {"object": obj, "shadow": shadow, "rest": ~(obj | shadow)}
    n = obj.size
    a, b = np.asarray(obj_srgb), np.asarray(bg_srgb)
    se = ((_unit(a) - _unit(b)) ** 2).mean(axis=-1)
    out: dict[str, float] = {}
    for p, m in parts.items():
        out[f"pixels_{p}"] = int(m.sum())
        out[f"sqerr_{p}"] = float(se[m].sum() / n)
    if lpips_fn is None:
        out.update({f"lpips_{p}": math.nan for p in PARTS})
        return out
    subsets = [frozenset(c) for k in range(1, len(PARTS) + 1) for c in itertools.combinations(PARTS, k)]
    composites = []
    for s_ in subsets:
        take = np.zeros(obj.shape, dtype=bool)
        for p in s_:
            take |= parts[p]
        composites.append(np.where(take[..., None], a, b))
    vals = [float(v) for v in lpips_fn(np.stack(composites), np.stack([b] * len(composites)))]
    values = {frozenset(): 0.0, **dict(zip(subsets, vals))}
    out.update({f"lpips_{p}": v for p, v in _shapley(values, PARTS).items()})
    return out


def shares(row: Mapping[str, Any], what: str) -> dict[str, float]:
    """``{part: fraction}`` of ``what`` (``"sqerr"`` or ``"lpips"``) in a row or aggregated table row; NaN when
    the total is 0 or unknown."""
    vals = [float(row.get(f"{what}_{p}", math.nan)) for p in PARTS]
    total = sum(vals)
    if not math.isfinite(total) or total <= 0:
        return {p: math.nan for p in PARTS}
    return {p: v / total for p, v in zip(PARTS, vals)}


def empty_split() -> dict[str, float]:
    """The split columns of a row without scores (the object not visible): NaN."""
    return {c: math.nan for c in SPLIT_COLUMNS}


def split_eval_dir(eval_dir, lpips_fn: Callable[[np.ndarray, np.ndarray], Sequence[float]] | None = None):
    """The split columns of an existing evaluation, recomputed from its saved 8-bit renders (``renders.json``) and
    its regions (``metrics.parquet``): a DataFrame keyed by ``run``, ``view``, ``region`` with
    :data:`~evaluation.evaldir.SPLIT_COLUMNS`. For evaluations written before the columns existed (or before a
    change of this module); ``lpips_fn`` as in :func:`split_region`."""
    from pathlib import Path

    import pandas as pd

    from camo_base.imaging import load_png
    from evaluation.evaldir import renders_json

    eval_dir = Path(eval_dir)
    rows = read_parquet(eval_dir / "metrics.parquet")
    files = {(str(e["run"]), int(e["view"])): e for e in renders_json(eval_dir)}

    def png(rel: str) -> np.ndarray:  # 8-bit values, as the metrics saw them
        a = np.round(load_png(eval_dir / rel) * 255.0).astype(np.uint8)
        return a if a.ndim == 3 else np.repeat(a[..., None], 3, axis=-1)

    out = []
    cache: dict[tuple[str, int], tuple] = {}
    for r in rows.to_dict("records"):
        key = (str(r["run"]), int(r["view"]))
        if key not in files or int(r["region_height"]) == 0:
            out.append({"run": key[0], "view": key[1], "region": r["region"], **empty_split()})
            continue
        if key not in cache:
            e = files[key]
            obj, bg = png(e["image"]), png(e["background"])
            mask = png(e["mask"])[..., 0] >= 128
            cache = {key: (obj, bg, mask, *shadow_mask(obj, bg, mask))}
        obj, bg, mask, shadow, tau = cache[key]
        y0, x0, h, w = (int(r[c]) for c in ("region_y0", "region_x0", "region_height", "region_width"))
        sl = (slice(y0, y0 + h), slice(x0, x0 + w))
        split = split_region(obj[sl], bg[sl], mask[sl], shadow[sl], lpips_fn)
        out.append({"run": key[0], "view": key[1], "region": r["region"], "shadow_threshold": tau, **split})
    return pd.DataFrame(out)
