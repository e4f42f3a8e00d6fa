"""HaarPSI (Reisenhofer et al. 2018) and the weight-free ``lpips_proxy`` built on it."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from camo_base.errors import CamoError

from evaluation.metrics._common import ImageLike, Metric, chunks, metric_thread_policy, plain, prepare_pair

#: Constants of the paper, fitted on natural images in the 0..255 scale.
HAARPSI_C = 30.0
HAARPSI_ALPHA = 4.2
HAARPSI_SCALES = 3

#: RGB -> YIQ matrices, rows Y, I, Q. "matlab": exactly the authors' MATLAB/Python code (rgcda/haarpsi), the
#: default; "piq": the 4-digit NTSC coefficients piq uses. Only because of them, piq's HaarPSI differs from the
#: authors': measured (``bench/bench_metrics.py``, 128x128 photo crops) up to 2e-4 for noise and blur, up to 1.8e-3
#: for +-20 % per-channel colour scaling and 3.1e-3 for +-50 %; issue #18 measured up to 5e-3 on colour edits.
#: So differences of a few 1e-3 between the two on colour changes are expected, not a bug.
YIQ_MATRICES = {
    "matlab": ((0.299, 0.587, 0.114), (0.596, -0.274, -0.322), (0.211, -0.523, 0.312)),
    "piq": ((0.299, 0.587, 0.114), (0.5959, -0.2746, -0.3213), (0.2115, -0.5227, 0.3112)),
}


def _box(t: torch.Tensor, k: int, dim: int) -> torch.Tensor:
    """Sums of ``k`` (a power of 2) consecutive entries along ``dim`` by recursive doubling; length - (k - 1)."""
    step = 1
    while step < k:
        t = _box_step(t, step, dim)
        step *= 2
    return t


def _haar_magnitudes(lum: torch.Tensor) -> list[torch.Tensor]:
    """``|conv2(lum, f, 'same')|`` (MATLAB alignment) of the reference's 3 scales x 2 orientations, as box sums.

    ``lum`` is ``(B, h, w)``. The filter of scale ``s`` is ``2**-s`` on a ``k = 2**s`` square, negated in its top
    half (orientation 0) or, transposed, in its left half (orientation 1); MATLAB's 'same' window for output ``o``
    spans ``[o - (k/2 - 1), o + k/2]``. With zero padding (3 before, 4 after) the response is a box sum of
    ``k`` along one axis, then (bottom half - top half) of box sums of ``k/2`` along the other: a few slice-adds
    instead of an 8x8 convolution. Order: scales 1..3 of orientation 0, then of orientation 1 (as the reference).
    """
    h, w = lum.shape[-2:]
    p = F.pad(lum, (3, 4, 3, 4))
    out = []
    for box_dim, sign_dim in ((-1, -2), (-2, -1)):
        length = {-1: w, -2: h}
        boxed = p  # box sums of 1
        for s in range(1, HAARPSI_SCALES + 1):
            k = 2**s
            boxed = _box_step(boxed, k // 2, box_dim)  # box sums of k from those of k / 2
            off = 4 - k // 2
            a = boxed.narrow(box_dim, off, length[box_dim])
            half = _box(a, k // 2, sign_dim)
            lo = half.narrow(sign_dim, off, length[sign_dim])
            hi = half.narrow(sign_dim, off + k // 2, length[sign_dim])
            out.append((hi - lo).abs() * 2.0**-s)
    return out


def _box_step(t: torch.Tensor, step: int, dim: int) -> torch.Tensor:
    """Box sums of ``2 * step`` from box sums of ``step`` along ``dim``."""
    n = t.shape[dim] - step
    return t.narrow(dim, 0, n) + t.narrow(dim, step, n)


def _similarity(a: torch.Tensor, b: torch.Tensor, c: float) -> torch.Tensor:
    return (2.0 * a * b + c) / (a * a + b * b + c)


@metric_thread_policy
def haarpsi(x: ImageLike, y: ImageLike, data_range: float = 1.0, yiq: str = "matlab") -> torch.Tensor:
    r"""Haar wavelet-based perceptual similarity index, colour version (higher is better).

    A port of the authors' reference code (``haarPsi.py`` / ``HaarPSI.m``, rgcda/haarpsi) to batched torch, equal
    to it to float64 round-off (the Haar filters are evaluated as box sums, see ``_haar_magnitudes``): images are rescaled to 0..255, converted to YIQ, subsampled by a 2x2 mean (with the reference's
    MATLAB ``'same'`` alignment and zero borders), decomposed with 3 scales x 2 orientations of Haar filters;
    local similarities of the two finest scales and of the 2x2-mean I and Q channels are weighted by the
    coarsest-scale magnitudes, passed through a logistic with :math:`\alpha = 4.2`, :math:`C = 30`:

    .. math:: \text{HaarPSI} = \left(\text{logit}_\alpha \frac{\sum_{k,p} \sigma_\alpha(S_k(p))\, W_k(p)}
              {\sum_{k,p} W_k(p)}\right)^2

    No learned weights. Differentiable (autograd) in ``x`` and ``y``. On TID2013 ``I01.BMP`` vs ``i01_01_5.bmp``
    (piq's fixture) it gives the MATLAB value 0.71706527.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, data_range]`` (or NumPy ``(H, W, 3)``); H, W >= 16.
        y: images of the same shape.
        data_range: span of the pixel values; images are rescaled to 0..255 internally.
        yiq: ``"matlab"`` (the authors' colour matrix, default) or ``"piq"`` (piq's rounded one, to reproduce piq:
            equal to it to float32 round-off; the two matrices differ by up to ~5e-3 on colour edits, see
            :data:`YIQ_MATRICES`).

    Returns:
        ``(N,)`` tensor, dimensionless, in ``[0, 1]``; exactly 1 for identical images. Two all-black images (every
        Haar weight zero, where the reference divides 0 by 0) give 1: the unweighted mean is used when all weights
        vanish.
    """
    if yiq not in YIQ_MATRICES:
        raise CamoError(f"haarpsi: yiq must be one of {sorted(YIQ_MATRICES)}, got {yiq!r}")
    x, y = prepare_pair(x, y, "haarpsi", data_range)
    m = torch.tensor(YIQ_MATRICES[yiq], dtype=x.dtype, device=x.device) * (255.0 / data_range)
    return torch.cat([_haarpsi(x[s], y[s], m) for s in chunks(x)])


def _haarpsi(x: torch.Tensor, y: torch.Tensor, yiq: torch.Tensor) -> torch.Tensor:
    n = x.shape[0]
    both = torch.einsum("kc,nchw->nkhw", yiq, torch.cat([x, y], dim=0))
    # Subsample: MATLAB conv2(., ones(2)/4, 'same') then [::2, ::2] == mean of each 2x2 block, zero beyond the edge.
    hh, ww = (both.shape[-2] + 1) // 2, (both.shape[-1] + 1) // 2
    bp = F.pad(both, (0, 1, 0, 1))
    both = 0.25 * (bp[..., 0 : 2 * hh : 2, 0 : 2 * ww : 2] + bp[..., 1 : 2 * hh : 2, 0 : 2 * ww : 2]
                   + bp[..., 0 : 2 * hh : 2, 1 : 2 * ww : 2] + bp[..., 1 : 2 * hh : 2, 1 : 2 * ww : 2])
    coeff = _haar_magnitudes(both[:, 0])  # 6 x (2N, h, w)
    iq = (0.25 * _box(_box(F.pad(both[:, 1:], (0, 1, 0, 1)), 2, -1), 2, -2)).abs()  # |conv2(., ones(2)/4, 'same')|
    c = HAARPSI_C
    sims, weights = [], []
    for o in range(2):
        c1, c2, c3 = coeff[3 * o : 3 * o + 3]
        weights.append(torch.maximum(c3[:n], c3[n:]))
        sims.append(0.5 * (_similarity(c1[:n], c1[n:], c) + _similarity(c2[:n], c2[n:], c)))
    sims.append(0.5 * _similarity(iq[:n], iq[n:], c).sum(dim=1))
    weights.append(0.5 * (weights[0] + weights[1]))
    s = torch.stack(sims, dim=1)
    w = torch.stack(weights, dim=1)
    sig = torch.sigmoid(HAARPSI_ALPHA * s)
    wsum = w.sum(dim=(1, 2, 3))
    weighted = (sig * w).sum(dim=(1, 2, 3)) / torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    v = torch.where(wsum > 0, weighted, sig.mean(dim=(1, 2, 3)))
    score = (torch.log(v / (1.0 - v)) / HAARPSI_ALPHA) ** 2
    # All local similarities exactly 1 (e.g. identical images) means HaarPSI = 1 exactly; return that rather than
    # 1 - 4e-15 of logit round-off.
    exact = (s == 1.0).flatten(1).all(dim=1)
    return torch.where(exact, torch.ones_like(score), score.clamp(0.0, 1.0))


@metric_thread_policy
def lpips_proxy(x: ImageLike, y: ImageLike, data_range: float = 1.0) -> torch.Tensor:
    r"""Weight-free perceptual distance ``1 - HaarPSI(x, y)`` (lower is better).

    **This is not LPIPS.** It needs no network weights, so it always runs, and it is a documented perceptual
    full-reference index validated against human quality judgements (Reisenhofer et al. 2018: LIVE, TID2008,
    TID2013, CSIQ). Its scale differs from LPIPS: do not compare its numbers with published LPIPS values
    (the paper's Table II); compare methods with each other on the same proxy only.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, data_range]``; H, W >= 16.
        y: images of the same shape.
        data_range: span of the pixel values.

    Returns:
        ``(N,)`` tensor, dimensionless, in ``[0, 1]``; 0 for identical images. Differentiable.
    """
    return (1.0 - haarpsi(x, y, data_range)).clamp_min(0.0)


#: The metric of this module (collected by :mod:`evaluation.metrics.registry`).
METRICS = (Metric("lpips_proxy", plain(lpips_proxy, "1-haarpsi"), False, "1", "[0, 1]",
                  "1 - HaarPSI; weight-free cross-check, NOT LPIPS, different scale", "LPIPS-proxy", order=3,
                  table_order=5, variant=True, cross_check=True),)
