"""Peak signal-to-noise ratio."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from evaluation.metrics._common import (ImageLike, Metric, check_data_range, metric_thread_policy, plain,
                                        prepare_pair)

#: Elements per block of the fast path: a float32 block of x and of y (2 x 256 kB) stay in a 1 MB L2 cache between
#: the fused sum of squares and the range check (bench/bench_metrics.py: 65536 beat 32768 and 98304).
FAST_CHUNK = 65536


def _flat_images(a: ImageLike) -> tuple[np.ndarray, tuple[int, ...], str] | None:
    """``(flat, shape, order)``: an ``(N, D)`` NumPy view of a float image batch in memory order, its logical
    ``(N, 3, H, W)`` shape and its memory order (``"nchw"`` or ``"nhwc"``); None when the fast path does not apply
    (integers, autograd, other devices, layouts that need a copy). Two images take the fast path together only
    when both shape and order agree: the sum of squares runs over memory, so a pair in different layouts (a NumPy
    HWC image and a torch CHW one, NCHW and channels-last) would otherwise compare unrelated values."""
    if isinstance(a, torch.Tensor):
        if a.requires_grad or a.device.type != "cpu" or a.dtype not in (torch.float32, torch.float64):
            return None
        t = a[None] if a.ndim == 3 else a
        if t.ndim != 4 or t.shape[1] != 3:
            return None
        shape = tuple(int(v) for v in t.shape)
        if t.is_contiguous():
            return t.numpy().reshape(t.shape[0], -1), shape, "nchw"
        if t.is_contiguous(memory_format=torch.channels_last):
            return t.permute(0, 2, 3, 1).numpy().reshape(t.shape[0], -1), shape, "nhwc"
        return None
    if isinstance(a, np.ndarray) and a.dtype in (np.float32, np.float64) and a.ndim in (3, 4) and a.shape[-1] == 3 \
            and a.flags.c_contiguous:
        b = a[None] if a.ndim == 3 else a
        return b.reshape(b.shape[0], -1), (b.shape[0], 3, b.shape[1], b.shape[2]), "nhwc"
    return None


def _fast_mse(x: ImageLike, y: ImageLike, data_range: float) -> np.ndarray | None:
    """MSE per image in one cache-blocked sweep, or None when the generic path must decide (other inputs, or any
    value outside ``[+0, data_range]``: clamping, NaN and the error messages are the generic path's).

    Per block of ``FAST_CHUNK`` elements: OpenCV's ``cv2.norm(a, b, NORM_L2SQR)`` reads both blocks once from
    memory and sums the squared differences with float64 accumulation (one fused, vectorised pass, one thread:
    ``cv::norm`` does not use OpenCV's thread pool); the range check then reads the same blocks from the L2 cache.
    Measured relative error of the MSE against a float64 reference: ~2e-14 (float32 or float64 input).

    Range check without a float compare: a float's bits read as an unsigned integer are ordered like the floats
    for +0 .. +inf and NaN lies above +inf; every negative value (also -0) has the top bit set, i.e. lies above
    too. So ``max(bits) <= bits(data_range)`` holds exactly when every value is in ``[+0, data_range]``."""
    fx, fy = _flat_images(x), _flat_images(y)
    if fx is None or fy is None or fx[1:] != fy[1:]:
        return None  # different shapes or memory layouts: the generic path compares (or refuses) them
    a, b = fx[0], fy[0]
    if a.dtype != b.dtype or a.size == 0:
        return None
    import cv2  # lazy: the rest of the metrics do not need OpenCV

    utype = np.uint32 if a.dtype == np.float32 else np.uint64
    limit = int(np.asarray(data_range, dtype=a.dtype).view(utype))
    au, bu = a.view(utype), b.view(utype)
    n, d = a.shape
    spans = [(i, min(d, i + FAST_CHUNK)) for i in range(0, d, FAST_CHUNK)]
    top, l2sqr = np.maximum.reduce, cv2.NORM_L2SQR
    out = np.empty(n, np.float64)
    for k in range(n):
        ak, bk, auk, buk = a[k], b[k], au[k], bu[k]
        s = 0.0
        for i, j in spans:
            s += cv2.norm(ak[i:j], bk[i:j], l2sqr)
            if top(auk[i:j]) > limit or top(buk[i:j]) > limit:
                return None
        out[k] = s / d
    return out


@metric_thread_policy
def psnr(x: ImageLike, y: ImageLike, data_range: float = 1.0) -> torch.Tensor:
    r"""Peak signal-to-noise ratio of each image pair, in decibels (higher is better).

    .. math:: \text{PSNR} = 10 \log_{10} \frac{L^2}{\text{MSE}}, \qquad
        \text{MSE} = \frac{1}{3HW} \sum_{c,i,j} (x_{cij} - y_{cij})^2

    The MSE is taken over all three channels and every pixel of one image (scikit-image's
    ``peak_signal_noise_ratio`` on an ``(H, W, 3)`` image gives the same number). Float inputs already in
    ``[0, L]`` take a single cache-blocked sweep (per 65536-element block a fused sum of squared differences
    with float64 accumulation, then the range check from the cache; ``_fast_mse``): about 2e-14 relative.
    Anything else (uint8, autograd, values to clamp or reject) goes through the generic torch path (cascaded
    float32 sums, about 1e-7 relative). The logarithm is taken in float64. Runs with
    :func:`~evaluation.metrics._common.metric_threads` torch threads (1 unless ``CAMO_METRIC_THREADS`` says
    otherwise); the fast path is single-threaded.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, data_range]`` (or a NumPy ``(H, W, 3)``), any size >= 1x1.
        y: images of the same shape.
        data_range: :math:`L`, the span of the pixel values (1.0 for sRGB in ``[0, 1]``).

    Returns:
        ``(N,)`` float64 tensor in dB, range ``(-inf, +inf]``; for images in ``[0, L]`` it is >= 0.
        **Identical images give** ``+inf`` (MSE = 0), never NaN; constant or black images are no special case.
    """
    check_data_range(data_range, "psnr")
    mse_fast = _fast_mse(x, y, data_range)
    if mse_fast is not None:
        return 10.0 * torch.log10(data_range**2 / torch.from_numpy(mse_fast))
    x, y = prepare_pair(x, y, "psnr", data_range)
    mse = F.mse_loss(x, y, reduction="none").mean(dim=(1, 2, 3)).double()
    return 10.0 * torch.log10(data_range**2 / mse)


#: The metric of this module (collected by :mod:`evaluation.metrics.registry`).
METRICS = (Metric("psnr", plain(psnr), True, "dB", "[0, inf], inf if identical", "peak signal-to-noise ratio, data range 1",
                  "PSNR", decimals=2, order=0, table_order=4),)
