"""Structural similarity (Wang et al. 2004), matching scikit-image's Gaussian mode."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from evaluation.metrics._common import ImageLike, Metric, chunks, metric_thread_policy, plain, prepare_pair

#: Window of Wang et al.: Gaussian, sigma 1.5, truncated at 3.5 sigma -> 11 taps (scikit-image's choice).
SSIM_SIGMA = 1.5
SSIM_WIN = 2 * int(3.5 * SSIM_SIGMA + 0.5) + 1
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def gaussian_window_1d(win_size: int = SSIM_WIN, sigma: float = SSIM_SIGMA, dtype=torch.float32) -> torch.Tensor:
    """Normalised sampled Gaussian ``(win_size,)``, centred, summing to 1 (as ``scipy.ndimage.gaussian_filter``)."""
    r = win_size // 2
    t = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    return (g / g.sum()).to(dtype)


def _valid_blur(maps: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of every channel of ``maps`` ``(N, C, H, W)``, 'valid' part only.

    Channels-last layout: oneDNN then runs the depthwise convolutions in place instead of re-blocking NCHW.
    """
    c = maps.shape[1]
    k = g.numel()
    if maps.device.type == "cpu" and maps.dtype == torch.float32:
        maps = maps.contiguous(memory_format=torch.channels_last)
    out = F.conv2d(maps, g.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c)
    return F.conv2d(out, g.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c)


def _ssim_map(x: torch.Tensor, y: torch.Tensor, data_range: float, k1: float, k2: float) -> torch.Tensor:
    c = x.shape[1]
    g = gaussian_window_1d(SSIM_WIN, SSIM_SIGMA, x.dtype).to(x.device)
    ox = x.mean(dim=(2, 3), keepdim=True)
    oy = y.mean(dim=(2, 3), keepdim=True)
    xs, ys = x - ox, y - oy
    moments = _valid_blur(torch.cat([xs, ys, xs * xs, ys * ys, xs * ys], dim=1), g)
    mx, my, mxx, myy, mxy = moments.split(c, dim=1)
    vx = mxx - mx * mx
    vy = myy - my * my
    vxy = mxy - mx * my
    ux, uy = mx + ox, my + oy
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    num = (2.0 * ux * uy + c1) * (2.0 * vxy + c2)
    den = (ux * ux + uy * uy + c1) * (vx + vy + c2)
    return num / den


@metric_thread_policy
def ssim_map(
    x: ImageLike,
    y: ImageLike,
    data_range: float = 1.0,
    k1: float = SSIM_K1,
    k2: float = SSIM_K2,
) -> torch.Tensor:
    r"""Local SSIM of every channel, ``(N, 3, H - 10, W - 10)``, values in ``[-1, 1]``.

    Border handling is scikit-image's: it filters with reflect padding and then crops :math:`(w-1)/2 = 5` px from
    every side of the map before averaging; the cropped map depends only on interior pixels, so it equals the
    'valid' part of the filtered moments computed here (no padding at all). Population (biased) variances,
    i.e. ``use_sample_covariance=False``; :math:`C_1 = (K_1 L)^2`, :math:`C_2 = (K_2 L)^2`.

    The moments are computed from images shifted by their per-channel mean (SSIM's variances and covariance are
    shift invariant) so that float32 keeps about 1e-6 of accuracy on near-flat images.
    """
    x, y = prepare_pair(x, y, "ssim", data_range)
    return torch.cat([_ssim_map(x[s], y[s], data_range, k1, k2) for s in chunks(x)], dim=0)


@metric_thread_policy
def ssim(x: ImageLike, y: ImageLike, data_range: float = 1.0) -> torch.Tensor:
    r"""Mean structural similarity of each image pair (higher is better, 1 for identical images).

    Wang et al. (2004) Gaussian mode: 11x11 window, :math:`\sigma = 1.5`, :math:`K_1 = 0.01`, :math:`K_2 = 0.03`,
    explicit data range, mean over the cropped SSIM map of each channel, then the mean of the three channels.
    Equals ``skimage.metrics.structural_similarity(x, y, channel_axis=-1, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=data_range)`` to about 1e-6 in float32.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, data_range]`` (or NumPy ``(H, W, 3)``); H, W >= 11.
        y: images of the same shape.
        data_range: :math:`L`, the span of the pixel values.

    Returns:
        ``(N,)`` tensor (dtype of the input: float32, or float64 for float64 input), dimensionless, in ``[-1, 1]``.
        Constant and black images are well defined (1 when equal, no NaN: both denominators are >= C1 C2 > 0).
    """
    x, y = prepare_pair(x, y, "ssim", data_range)
    return torch.cat([_ssim_map(x[s], y[s], data_range, SSIM_K1, SSIM_K2).mean(dim=(1, 2, 3)) for s in chunks(x)])


#: The metric of this module (collected by :mod:`evaluation.metrics.registry`).
METRICS = (Metric("ssim", plain(ssim), True, "1", "[-1, 1]",
                  "SSIM, Gaussian 11x11 sigma 1.5, = scikit-image gaussian_weights=True", "SSIM", order=1,
                  table_order=3),)
