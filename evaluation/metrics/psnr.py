"""Peak signal-to-noise ratio."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ._common import ImageLike, prepare_pair


def psnr(x: ImageLike, y: ImageLike, data_range: float = 1.0) -> torch.Tensor:
    r"""Peak signal-to-noise ratio of each image pair, in decibels (higher is better).

    .. math:: \text{PSNR} = 10 \log_{10} \frac{L^2}{\text{MSE}}, \qquad
        \text{MSE} = \frac{1}{3HW} \sum_{c,i,j} (x_{cij} - y_{cij})^2

    The MSE is taken over all three channels and every pixel of one image (scikit-image's
    ``peak_signal_noise_ratio`` on an ``(H, W, 3)`` image gives the same number). It is computed in the input's
    dtype (torch's cascaded sums: about 1e-7 relative in float32, i.e. < 1e-6 dB) and the logarithm in float64;
    float64 input is exact to round-off.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, data_range]`` (or a NumPy ``(H, W, 3)``), any size >= 1x1.
        y: images of the same shape.
        data_range: :math:`L`, the span of the pixel values (1.0 for sRGB in ``[0, 1]``).

    Returns:
        ``(N,)`` float64 tensor in dB, range ``(-inf, +inf]``; for images in ``[0, L]`` it is >= 0.
        **Identical images give** ``+inf`` (MSE = 0), never NaN; constant or black images are no special case.
    """
    x, y = prepare_pair(x, y, "psnr", data_range)
    mse = F.mse_loss(x, y, reduction="none").mean(dim=(1, 2, 3)).double()
    return 10.0 * torch.log10(data_range**2 / mse)
