"""Detail ratio: the give-away of speckle (or of a body too smooth for its background).

High-frequency luminance energy of the object's pixels in the with-object view over that of the same pixels in
the background view: 1 = the body carries the background's texture, > 1 = speckle / sparkle / salt-and-pepper
maps, < 1 = a flat, too smooth body. Measure it on converged renders (``camo evaluate --spp`` high), or Monte
Carlo noise of the object's transmissive paths counts as speckle too.
"""

from __future__ import annotations

from typing import Optional

import torch

from evaluation.metrics._common import ImageLike, Metric, metric_thread_policy, masked, prepare_pair, to_mask

#: Rec. 709 luma weights on the sRGB-encoded values (a luma, not linear luminance: the eye's contrast scale)
LUMA = (0.2126, 0.7152, 0.0722)
#: added to both energies: one 8-bit step (a flat region over a flat region is 1, never 0 / 0)
EPS = 1.0 / 255.0


#: Smallest image side (px) this module's metrics accept: the 3x3 Laplacian must fit once.
MIN_SIDE = 3


def _laplacian_energy(x: torch.Tensor) -> torch.Tensor:
    """``|Laplacian|`` of the luma of ``x`` ``(N, 3, H, W)`` -> ``(N, 1, H, W)`` (kornia's 3x3 8-neighbour kernel,
    unnormalised, reflected edges)."""
    import kornia

    w = torch.tensor(LUMA, dtype=x.dtype).view(1, 3, 1, 1)
    y = (x * w).sum(dim=1, keepdim=True)
    return kornia.filters.laplacian(y, kernel_size=3, border_type="reflect", normalized=False).abs()


def interior(mask: torch.Tensor) -> torch.Tensor:
    """Pixels of ``mask`` ``(N, 1, H, W)`` whose whole 3x3 neighbourhood is in the mask (the image border counts
    as inside): the Laplacian there sees the body only, not the silhouette's edge against the background."""
    m = mask.to(torch.float32)
    padded = torch.nn.functional.pad(1.0 - m, (1, 1, 1, 1), value=0.0)
    outside_near = torch.nn.functional.max_pool2d(padded, 3, stride=1)
    return outside_near == 0


@metric_thread_policy
def detail_ratio(x: ImageLike, y: ImageLike, mask: Optional[object] = None) -> torch.Tensor:
    r"""Mean |Laplacian| of the luma of ``x`` over that of ``y``, inside ``mask``'s interior, per image.

    .. math:: D = \frac{\epsilon + \operatorname{mean}_{p \in M^\circ} |\nabla^2 Y_x(p)|}
                       {\epsilon + \operatorname{mean}_{p \in M^\circ} |\nabla^2 Y_y(p)|}

    ``Y``: Rec. 709 luma of the sRGB values; ``\nabla^2``: the 3x3 8-neighbour Laplacian
    (``kornia.filters.laplacian``, reflected edges); ``M^\circ``: the mask eroded by one pixel (the silhouette's
    own edge is not texture); :data:`EPS` = 1/255.

    Args:
        x: the with-object view(s), sRGB ``[0, 1]`` ``(N, 3, H, W)`` or NumPy ``(H, W, 3)``.
        y: the background view(s), same shape.
        mask: the object's pixels ``(H, W)`` / ``(N, H, W)`` / ``(N, 1, H, W)``; None = the whole image.

    Returns:
        ``(N,)``: 1 = same texture energy, > 1 speckle, < 1 too smooth; NaN where the mask has no interior pixel
        (an object under 3 px across shows no texture).

    Raises:
        CamoError: images that are not sRGB in [0, 1], differ in shape, are smaller than 3x3, or a mask that
            does not fit.

    Example:
        >>> import numpy as np
        >>> bg = np.full((8, 8, 3), 0.5, np.float32)
        >>> obj = bg.copy(); obj[2:6, 2:6] = np.indices((4, 4)).sum(0)[..., None] % 2   # a checkerboard body
        >>> round(float(detail_ratio(bg, bg)), 3), round(float(detail_ratio(obj, bg)), 1)
        (1.0, 303.8)
    """
    ex, ey = detail_energies(x, y, mask)
    return (EPS + ex) / (EPS + ey)


def detail_energies(x: ImageLike, y: ImageLike, mask: Optional[object] = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The detail ratio's two sides: mean |Laplacian| of the luma of ``x`` and of ``y`` inside ``mask``'s interior.

    Same inputs and checks as :func:`detail_ratio`; returns two ``(N,)`` tensors in sRGB units (multiply by 255 for
    8-bit steps). Which side moves tells render noise from the material: a background's side that falls with more
    samples was noise; an object's side that stays is the body's own texture (``bench/detail_sides.py``).

    Example:
        >>> import numpy as np
        >>> bg = np.full((8, 8, 3), 0.5, np.float32)
        >>> obj = bg.copy(); obj[2:6, 2:6] = np.indices((4, 4)).sum(0)[..., None] % 2
        >>> ex, ey = detail_energies(obj, bg)
        >>> round(float(ex) * 255, 1), float(ey)
        (302.8, 0.0)
    """
    x, y = prepare_pair(x, y, "detail_ratio", min_size=MIN_SIDE)
    m = interior(to_mask(mask, x, "detail_ratio"))
    n = m.sum(dim=(1, 2, 3)).to(x.dtype)
    return (_laplacian_energy(x) * m).sum(dim=(1, 2, 3)) / n, (_laplacian_energy(y) * m).sum(dim=(1, 2, 3)) / n


METRICS = (Metric("detail_ratio", masked(detail_ratio), False, "ratio", "[0, inf), best 1",
                  "give-away: high-frequency luma energy (mean absolute Laplacian) inside the object's mask, with the object "
                  "over the background (1 = same texture, > 1 speckle, < 1 too smooth); measure at converged spp",
                  "Detail", decimals=2, order=200.0, table_order=200.0, masked=True, target=1.0, min_size=MIN_SIDE),)
