"""SIFID (Shaham et al. 2019, SinGAN): Frechet distance of the per-position Inception features of two images.

The Inception v3 stem is defined here (no torchvision) and filled from a local state dict. Accepted key layout:
torchvision's ``Inception3`` names, ``Conv2d_1a_3x3.conv.weight`` and ``Conv2d_1a_3x3.bn.{weight, bias,
running_mean, running_var}`` for ``1a``, ``2a``, ``2b`` (other keys are ignored; a ``module.`` prefix or a
``{"state_dict": ...}`` wrapping is accepted). Both files that carry such keys work:

* torchvision's ImageNet weights ``inception_v3_google-*.pth`` -- what SinGAN's ``SIFID/inception.py`` loads
  (``models.inception_v3(pretrained=True)``), so the one that reproduces published SIFID numbers;
* pytorch-fid's FID port ``pt_inception-2015-12-05-*.pth`` (same stem keys, different values).

The SHA-256 of the file is recorded with every score (``model.weights_sha256``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import torch
import torch.nn as nn

from camo_base.errors import CamoError

from evaluation.metrics._common import ImageLike, Metric, prepare_pair
from evaluation.metrics.frechet import frechet_of_feature_maps
from evaluation.metrics.weights import (cached_model, file_key, find_trunk_weights, load_state_dict, take,
                                        weights_sha256)

PathLike = Union[str, os.PathLike]

#: Feature variants. "singan" is the default and what SinGAN's ``sifid_score.py`` computes with ``dims=64``
#: (``InceptionV3([0])``): its ``SIFID/inception.py`` builds block 0 from Conv2d_1a, 2a, 2b only, *without*
#: the max-pool. "pytorch-fid" is pytorch-fid's block 0 (``BLOCK_INDEX_BY_DIM[64]``), which ends with
#: ``MaxPool2d(3, stride=2)``.
SIFID_VARIANTS = {
    "singan": "SinGAN SIFID dims=64: InceptionV3 Conv2d_1a_3x3, Conv2d_2a_3x3, Conv2d_2b_3x3 (64 ch, before "
    "max-pool 1), input 2x-1, no resize, mean + unbiased covariance over all H*W positions",
    "pytorch-fid": "pytorch-fid block 0 (dims=64): as 'singan' followed by MaxPool2d(3, stride=2)",
}
#: The variant recorded with every SIFID score unless another is asked for.
SIFID_VARIANT = "singan"

_STEM = (  # name, in, out, stride, padding
    ("Conv2d_1a_3x3", 3, 32, 2, 0),
    ("Conv2d_2a_3x3", 32, 32, 1, 0),
    ("Conv2d_2b_3x3", 32, 64, 1, 1),
)


class BasicConv2d(nn.Module):
    """torchvision's Inception ``BasicConv2d``: 3x3 conv without bias, BatchNorm (eps 0.001), ReLU."""

    def __init__(self, cin: int, cout: int, stride: int, padding: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel_size=3, stride=stride, padding=padding, bias=False)
        self.bn = nn.BatchNorm2d(cout, eps=0.001)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.bn(self.conv(x)))


class InceptionStem(nn.Module):
    """Inception v3 block 0 -> ``(N, 64, h, w)`` features of sRGB ``[0, 1]`` input (mapped to ``2x - 1``)."""

    def __init__(self, variant: str = SIFID_VARIANT) -> None:
        super().__init__()
        if variant not in SIFID_VARIANTS:
            raise CamoError(f"unknown SIFID variant {variant!r}; expected one of {sorted(SIFID_VARIANTS)}")
        self.variant = variant
        for name, cin, cout, stride, pad in _STEM:
            self.add_module(name, BasicConv2d(cin, cout, stride, pad))
        self.pool = nn.MaxPool2d(kernel_size=3, stride=2) if variant == "pytorch-fid" else nn.Identity()
        self.weights_sha256 = ""
        self.weight_path = ""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = 2.0 * x.to(self.Conv2d_1a_3x3.conv.weight.dtype) - 1.0
        z = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(z)))
        return self.pool(z)


def load_sifid_inception(weights: Optional[PathLike] = None, variant: str = SIFID_VARIANT) -> InceptionStem:
    """Build the SIFID feature extractor from a local Inception v3 state dict (cached per file and variant).

    Args:
        weights: path of ``inception_v3_google-*.pth`` or ``pt_inception-2015-12-05-*.pth`` (torchvision key
            layout); ``None`` searches ``$TORCH_HOME/hub/checkpoints`` (google file first).
        variant: a key of :data:`SIFID_VARIANTS`.

    Raises:
        CamoError: no file, unreadable, or keys/shapes that are not torchvision's Inception v3 stem.
    """
    if variant not in SIFID_VARIANTS:
        raise CamoError(f"unknown SIFID variant {variant!r}; expected one of {sorted(SIFID_VARIANTS)}")
    path = find_trunk_weights("inception", weights)
    return cached_model(("sifid", variant, file_key(path)), lambda: _build_inception(path, variant))


def _build_inception(path: Path, variant: str) -> InceptionStem:
    sd = load_state_dict(path, "Inception v3")
    model = InceptionStem(variant)
    for name, cin, cout, _, _ in _STEM:
        block = getattr(model, name)
        block.conv.weight.data.copy_(take(sd, f"{name}.conv.weight", (cout, cin, 3, 3), "Inception v3", path))
        for part in ("weight", "bias", "running_mean", "running_var"):
            getattr(block.bn, part).data.copy_(take(sd, f"{name}.bn.{part}", (cout,), "Inception v3", path))
    model.weights_sha256 = weights_sha256(path)
    model.weight_path = str(path)
    return model


def sifid(
    x: ImageLike,
    y: ImageLike,
    model: Optional[InceptionStem] = None,
    weights: Optional[PathLike] = None,
    variant: str = SIFID_VARIANT,
    input_scale: float = 1.0,
) -> torch.Tensor:
    r"""Single-image FID of each pair (lower is better): SinGAN's SIFID with 64-dim block-0 features.

    Each image goes through the Inception stem at its own size (no resize); every spatial position of the
    ``(64, h, w)`` map is one sample; the two images' Gaussians (mean, unbiased covariance) are compared with
    :func:`~evaluation.metrics.frechet.frechet_distance`.

    Note on published numbers: SinGAN's script reads images with ``matplotlib.pyplot.imread``, which returns PNG
    files already in ``[0, 1]`` and JPEGs in ``0..255``, and then divides by 255 in both cases. Scores computed
    from PNGs with that script therefore saw images in ``[0, 1/255]``; pass ``input_scale=1/255`` to reproduce
    them. The default (1.0) is the intended ``[0, 1]`` input.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, 1]``; H, W >= 32. ``x`` and ``y`` may differ in size.
        y: images ``(N, 3, H', W')``.
        model: from :func:`load_sifid_inception`; if ``None`` it is loaded from ``weights`` and ``variant``.
        input_scale: factor applied to the ``[0, 1]`` images before the network (see the note).

    Returns:
        ``(N,)`` float64, squared feature units, >= 0; 0 for identical images.
    """
    x, y = prepare_pair(x, y, "sifid", same_size=False)
    if model is None:
        model = load_sifid_inception(weights, variant)
    with torch.no_grad():
        fx = model(x * input_scale)
        fy = model(y * input_scale)
    return frechet_of_feature_maps(fx, fy)


def _compute(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
    variant = weights.get("sifid_variant", SIFID_VARIANT)
    model = load_sifid_inception(weights.get("sifid"), variant)
    return sifid(x, y, model), {"variant": variant, "weights_sha256": model.weights_sha256}


def _from_path(path: str) -> dict[str, str]:
    p = Path(path).expanduser()
    if not p.is_file():
        raise CamoError(f"sifid weights (Inception v3 state dict): file not found: {p}")
    return {"sifid": str(p)}


def _unavailable(weights: Mapping[str, Any]) -> Optional[str]:
    find_trunk_weights("inception", weights.get("sifid"))
    return None


#: The metric of this module (collected by :mod:`evaluation.metrics.registry`).
METRICS = (Metric("sifid", _compute, False, "feature units^2", "[0, inf)",
                  "SinGAN SIFID, 64-dim Inception block-0 features, local weights", "SIFID", needs_weights=True,
                  order=4, table_order=1, variant=True, weights_key="sifid", unavailable=_unavailable, from_path=_from_path,
                  needs="a local Inception v3 state dict (--weights sifid=FILE, or torchvision's "
                        "inception_v3_google-*.pth in $TORCH_HOME/hub/checkpoints); no registry package ships it"),)
