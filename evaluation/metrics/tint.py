"""Tint: the give-away of a colour cast (the glassy green or blue body).

CIELAB colour difference between the mean colour of the object's pixels in the with-object view and the mean
colour of the same pixels in the background view. The difference of the *means* is the cast alone: texture
mismatch and speckle cancel in the means (they are what PSNR and :mod:`.detail_ratio` measure).
"""

from __future__ import annotations

from typing import Optional

import torch

from evaluation.metrics._common import ImageLike, Metric, metric_thread_policy, masked, prepare_pair, to_mask


@metric_thread_policy
def tint(x: ImageLike, y: ImageLike, mask: Optional[object] = None) -> torch.Tensor:
    r"""CIE 1976 :math:`\Delta E^*_{ab}` between the mean CIELAB colours of ``x`` and ``y`` inside ``mask``.

    .. math:: T = \lVert \operatorname{mean}_{p \in M} \mathrm{Lab}(x_p) - \operatorname{mean}_{p \in M}
              \mathrm{Lab}(y_p) \rVert_2

    Lab from sRGB with ``kornia.color.rgb_to_lab`` (D65; it linearises the sRGB values first). About 2.3 is a
    just-noticeable difference; a pure hue shift counts as much as a lightness shift of the same size.

    Args:
        x: the with-object view(s), sRGB ``[0, 1]`` ``(N, 3, H, W)`` or NumPy ``(H, W, 3)``.
        y: the background view(s), same shape.
        mask: the object's pixels ``(H, W)`` / ``(N, H, W)`` / ``(N, 1, H, W)``; None = the whole image.

    Returns:
        ``(N,)`` in Lab units (0 = no cast); NaN where the mask is empty.

    Raises:
        CamoError: images that are not sRGB in [0, 1] or differ in shape, or a mask that does not fit.

    Example:
        >>> import numpy as np
        >>> grey = np.full((4, 4, 3), 0.5, np.float32)
        >>> green = grey.copy(); green[..., 1] = 0.6
        >>> round(float(tint(grey, grey)), 3), round(float(tint(green, grey)), 1)
        (0.0, 19.0)
    """
    import kornia

    x, y = prepare_pair(x, y, "tint")
    m = to_mask(mask, x, "tint").to(x.dtype)
    n = m.sum(dim=(1, 2, 3))
    lx = (kornia.color.rgb_to_lab(x) * m).sum(dim=(2, 3)) / n[:, None]
    ly = (kornia.color.rgb_to_lab(y) * m).sum(dim=(2, 3)) / n[:, None]
    return (lx - ly).norm(dim=1)


METRICS = (Metric("tint", masked(tint), False, "ΔE*ab", "[0, ~100]",
                  "give-away: CIELAB ΔE*ab between the mean colours inside the object's mask, with the object and "
                  "without (the colour cast; texture and speckle cancel in the means)", "Tint", decimals=2,
                  order=201.0, table_order=201.0, masked=True),)
