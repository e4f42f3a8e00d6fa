"""Weight-free SIFID proxy: the SIFID statistics over a hand-made per-pixel texture + colour feature.

Feature of every pixel (15 dims, all from the sRGB-encoded image, reflect padding at the borders):

* **12 oriented texture energies** on luma ``Y = 0.299 R + 0.587 G + 0.114 B``: for Gaussian scales
  ``sigma`` in ``(1, 2, 4)`` px and orientations ``theta`` in ``(0, 45, 90, 135)`` degrees,
  ``sqrt(L_theta^2 + L_theta_theta^2)`` where ``L_theta = sigma * d/dtheta (G_sigma * Y)`` (odd, edge-like) and
  ``L_theta_theta = sigma^2 * d^2/dtheta^2 (G_sigma * Y)`` (even, bar-like) are scale-normalised steered
  derivative-of-Gaussian responses -- a quadrature-like local energy, the classic texture front end.
* **3 local colour means**: Gaussian (``sigma`` = 2 px) means of the opponent channels
  ``(R + G + B) / sqrt(3)``, ``(R - G) / sqrt(2)``, ``(R + G - 2B) / sqrt(6)``.

Unlike Inception's block-0 features (which the paper found "largely oblivious to stark colour differences"),
the colour means make a global colour shift count. Numbers are **not** comparable with SIFID.
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

from evaluation.metrics._common import ImageLike, Metric, chunks, metric_thread_policy, plain, prepare_pair
from evaluation.metrics.frechet import frechet_of_feature_maps

SIFID_PROXY_SCALES = (1.0, 2.0, 4.0)
SIFID_PROXY_ORIENTATIONS_DEG = (0.0, 45.0, 90.0, 135.0)
SIFID_PROXY_COLOUR_SIGMA = 2.0
SIFID_PROXY_DIMS = len(SIFID_PROXY_SCALES) * len(SIFID_PROXY_ORIENTATIONS_DEG) + 3
SIFID_PROXY_VARIANT = "dog-energy-3x4+opponent-means-3 (15 dims)"

_LUMA = (0.299, 0.587, 0.114)
_OPPONENT = (
    (1 / math.sqrt(3), 1 / math.sqrt(3), 1 / math.sqrt(3)),
    (1 / math.sqrt(2), -1 / math.sqrt(2), 0.0),
    (1 / math.sqrt(6), 1 / math.sqrt(6), -2 / math.sqrt(6)),
)


def gaussian_derivative_kernels(sigma: float, dtype=torch.float32) -> torch.Tensor:
    """Sampled 1-D Gaussian and its first two derivatives, ``(3, 2r + 1)`` with ``r = ceil(4 sigma)``.

    Row 0 sums to 1; row 1 is odd (sums to 0); row 2 is made zero-sum so that flat images give exactly 0.
    """
    r = int(math.ceil(4.0 * sigma))
    t = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    g = g / g.sum()
    g1 = -t / sigma**2 * g
    g2 = (t * t / sigma**4 - 1.0 / sigma**2) * g
    g2 = g2 - g * g2.sum()
    return torch.stack([g, g1, g2]).to(dtype)


_PAD = int(math.ceil(4.0 * max(SIFID_PROXY_SCALES + (SIFID_PROXY_COLOUR_SIGMA,))))  # 16 px


@functools.lru_cache(maxsize=8)
def _scale_bank(i: int, dtype: torch.dtype, device: torch.device):
    """Filters of scale ``i`` (plus the colour means when the colour sigma equals this scale's sigma).

    Returns ``(radius, h_index, h_kernels, v_index, v_kernels, steer, colour)``: the horizontal depthwise pass
    takes channels ``h_index`` of (Y, O1, O2, O3) with ``h_kernels``; the vertical pass takes channels ``v_index``
    of its output with ``v_kernels`` giving (Lx, Ly, Lxx, Lyy, Lxy [, 3 colour means]), scale-normalised;
    ``steer`` maps those to the 4 first- and 4 second-derivative orientations [+ the colour means].
    """
    sigma = SIFID_PROXY_SCALES[i]
    g, g1, g2 = gaussian_derivative_kernels(sigma, torch.float64)
    colour = sigma == SIFID_PROXY_COLOUR_SIGMA
    h_index, h_k = [0, 0, 0], [g, g1, g2]  # Y g, Y g', Y g''
    v_index = [1, 0, 2, 0, 1]
    v_k = [sigma * g, sigma * g1, sigma**2 * g, sigma**2 * g2, sigma**2 * g1]
    if colour:
        h_index += [1, 2, 3]
        h_k += [g, g, g]
        v_index += [3, 4, 5]
        v_k += [g, g, g]
    n_o = len(SIFID_PROXY_ORIENTATIONS_DEG)
    steer = torch.zeros(len(v_k), 2 * n_o + (3 if colour else 0), dtype=torch.float64)
    for j, deg in enumerate(SIFID_PROXY_ORIENTATIONS_DEG):
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        steer[0, j], steer[1, j] = c, s
        steer[2, n_o + j], steer[3, n_o + j], steer[4, n_o + j] = c * c, s * s, 2.0 * c * s
    if colour:
        steer[5:, 2 * n_o :] = torch.eye(3, dtype=torch.float64)

    def prep(ks: list, shape: tuple) -> torch.Tensor:
        return torch.stack(ks).to(dtype=dtype, device=device).view(len(ks), *shape)

    taps = g.numel()
    return (taps // 2, torch.tensor(h_index, device=device), prep(h_k, (1, 1, taps)),
            torch.tensor(v_index, device=device), prep(v_k, (1, taps, 1)), steer.to(dtype=dtype, device=device),
            colour)


def _features(x: torch.Tensor) -> torch.Tensor:
    dtype, dev = x.dtype, x.device
    n, _, h, w = x.shape
    mix = torch.tensor((_LUMA,) + _OPPONENT, dtype=dtype, device=dev)  # (4, 3): Y, then the opponent channels
    z = F.pad(torch.einsum("kc,nchw->nkhw", mix, x), (_PAD,) * 4, mode="reflect")
    if dev.type == "cpu" and dtype == torch.float32:
        z = z.contiguous(memory_format=torch.channels_last)
    n_o = len(SIFID_PROXY_ORIENTATIONS_DEG)
    out = torch.empty(n, h, w, SIFID_PROXY_DIMS, dtype=dtype, device=dev)  # pixels x features, channels last
    for i in range(len(SIFID_PROXY_SCALES)):
        r, h_idx, h_k, v_idx, v_k, steer, colour = _scale_bank(i, dtype, dev)
        zi = z[:, :, _PAD - r : _PAD + h + r, _PAD - r : _PAD + w + r]  # reflect padding of radius r
        hz = F.conv2d(zi.index_select(1, h_idx), h_k, groups=h_k.shape[0])  # (n, k, h + 2r, w)
        vz = F.conv2d(hz.index_select(1, v_idx), v_k, groups=v_k.shape[0])  # (n, k', h, w)
        a = vz.permute(0, 2, 3, 1) @ steer  # steering is linear: one small matmul over the pixels
        out[..., i * n_o : (i + 1) * n_o] = torch.sqrt(a[..., :n_o] ** 2 + a[..., n_o : 2 * n_o] ** 2)
        if colour:
            out[..., -3:] = a[..., 2 * n_o :]
    return out.permute(0, 3, 1, 2)


def proxy_features(x: torch.Tensor) -> torch.Tensor:
    """Per-pixel proxy features ``(N, 15, H, W)`` of sRGB images ``(N, 3, H, W)`` (see the module docstring)."""
    return torch.cat([_features(x[s]) for s in chunks(x)], dim=0)


@metric_thread_policy
def sifid_proxy(x: ImageLike, y: ImageLike) -> torch.Tensor:
    r"""Weight-free SIFID-like distance of each pair (lower is better).

    The SIFID recipe (every pixel one sample, mean + unbiased covariance per image, Frechet distance between the
    two Gaussians) over the 15-dim hand-made feature of this module instead of Inception block-0 features.
    Not comparable with SIFID values; it ranks texture and colour mismatch, and needs no weights.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, 1]`` (or NumPy ``(H, W, 3)``); H, W >= 32. Sizes of ``x`` and
            ``y`` may differ.
        y: images ``(N, 3, H', W')``.

    Returns:
        ``(N,)`` float64, squared feature units (sRGB units squared), >= 0; 0 for identical images; flat images
        are fine (zero texture covariance).
    """
    x, y = prepare_pair(x, y, "sifid_proxy", same_size=False)
    with torch.no_grad():
        return frechet_of_feature_maps(proxy_features(x), proxy_features(y))


#: The metric of this module (collected by :mod:`evaluation.metrics.registry`).
METRICS = (Metric("sifid_proxy", plain(sifid_proxy, SIFID_PROXY_VARIANT), False, "feature units^2", "[0, inf)",
                  "SIFID statistics over weight-free DoG texture energy + opponent colour; cross-check, NOT SIFID",
                  "SIFID-proxy", order=5, table_order=6, variant=True,
                  cross_check=True),)
