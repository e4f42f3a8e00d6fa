"""LPIPS (Zhang et al. 2018, v0.1) with AlexNet / VGG16 trunks defined here (no torchvision), from local weights.

Weights: a torchvision-format trunk state dict (``features.N.weight`` / ``.bias``; the ``classifier.*`` keys are
ignored), e.g. ``alexnet-owt-7be5be79.pth`` / ``vgg16-397923af.pth``, plus the LPIPS v0.1 linear layers
``alex.pth`` / ``vgg.pth`` (keys ``lin{0..4}.model.1.weight``). See :mod:`evaluation.metrics.weights` for where
they are looked up. Nothing is downloaded; missing weights raise :class:`~camo_base.errors.CamoError`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import torch
import torch.nn as nn

from camo_base.errors import CamoError

from evaluation.metrics._common import ImageLike, Metric, prepare_pair
from evaluation.metrics.weights import (cached_model, file_key, find_lpips_lin_weights, find_trunk_weights,
                                        load_state_dict, take, weights_sha256)

PathLike = Union[str, os.PathLike]

#: LPIPS ScalingLayer constants (applied to inputs in [-1, 1]).
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)
LPIPS_VERSION = "0.1"

#: Conv layers of torchvision's ``features`` Sequential: index -> (out, in, kernel, stride, padding).
_ALEX_CONVS = {0: (64, 3, 11, 4, 2), 3: (192, 64, 5, 1, 2), 6: (384, 192, 3, 1, 1), 8: (256, 384, 3, 1, 1),
               10: (256, 256, 3, 1, 1)}
_ALEX_POOLS = (2, 5, 12)
_VGG_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")

#: Index (in ``features``) of the ReLU whose output LPIPS taps, and the channels there.
LPIPS_TAPS = {"alex": (1, 4, 7, 9, 11), "vgg": (3, 8, 15, 22, 29)}
LPIPS_CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}


def alexnet_features() -> nn.Sequential:
    """torchvision's ``AlexNet.features`` layer for layer (same indices, so its state dict loads)."""
    layers: list[nn.Module] = []
    for i in range(13):
        if i in _ALEX_CONVS:
            o, c, k, s, p = _ALEX_CONVS[i]
            layers.append(nn.Conv2d(c, o, k, stride=s, padding=p))
        elif i in _ALEX_POOLS:
            layers.append(nn.MaxPool2d(kernel_size=3, stride=2))
        else:
            layers.append(nn.ReLU(inplace=False))
    return nn.Sequential(*layers)


def vgg16_features() -> nn.Sequential:
    """torchvision's ``vgg16().features`` layer for layer (configuration "D", no batch norm)."""
    layers: list[nn.Module] = []
    c = 3
    for v in _VGG_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(c, int(v), kernel_size=3, padding=1), nn.ReLU(inplace=False)]
            c = int(v)
    return nn.Sequential(*layers)


def _unit_normalise(f: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """LPIPS ``normalize_tensor``: divide each position's feature vector by its L2 norm (+ eps)."""
    return f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + eps)


class LPIPSNet(nn.Module):
    """LPIPS v0.1 network: scaling layer, trunk, per-layer unit normalisation, 1x1 linear layers.

    Built empty; :func:`load_lpips` fills it from local weights. ``forward(x, y)`` takes sRGB ``[0, 1]`` batches.
    """

    def __init__(self, net: str = "alex") -> None:
        super().__init__()
        if net not in LPIPS_TAPS:
            raise ValueError(f"net must be 'alex' or 'vgg', got {net!r}")
        self.net = net
        self.features = alexnet_features() if net == "alex" else vgg16_features()
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in LPIPS_CHANNELS[net])
        self.register_buffer("shift", torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1))
        self.weights_sha256: dict[str, str] = {}
        self.weight_paths: dict[str, str] = {}

    def taps(self, z: torch.Tensor) -> list[torch.Tensor]:
        """Trunk activations at the five LPIPS layers for a scaled input ``z``."""
        out, taps = [], set(LPIPS_TAPS[self.net])
        last = LPIPS_TAPS[self.net][-1]
        for i, layer in enumerate(self.features):
            z = layer(z)
            if i in taps:
                out.append(z)
            if i == last:
                break
        return out

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        n = x.shape[0]
        z = torch.cat([x, y], dim=0).to(self.shift.dtype)
        z = ((2.0 * z - 1.0) - self.shift) / self.scale
        total = torch.zeros(n, dtype=z.dtype, device=z.device)
        for f, lin in zip(self.taps(z), self.lins):
            f = _unit_normalise(f)
            d = (f[:n] - f[n:]) ** 2
            total = total + lin(d).mean(dim=(1, 2, 3))
        return total


def load_lpips(net: str = "alex", trunk: Optional[PathLike] = None, lin: Optional[PathLike] = None) -> LPIPSNet:
    """Build an LPIPS v0.1 network from local files (cached per file path, size and mtime).

    Args:
        net: ``"alex"`` (the LPIPS default, and GANmouflage's) or ``"vgg"``.
        trunk: torchvision state dict of AlexNet / VGG16; ``None`` searches ``$TORCH_HOME/hub/checkpoints``.
        lin: LPIPS v0.1 ``alex.pth`` / ``vgg.pth``; ``None`` takes the copy inside an installed ``lpips`` or
            ``torchmetrics`` wheel.

    Returns:
        The network in eval mode, gradients off, with ``weights_sha256 = {"trunk": ..., "lin": ...}`` and
        ``weight_paths`` recorded.

    Raises:
        CamoError: weights missing, unreadable, or with wrong keys/shapes.
    """
    if net not in LPIPS_TAPS:
        raise CamoError(f"LPIPS net must be 'alex' or 'vgg', got {net!r}")
    trunk_path = find_trunk_weights(net, trunk)
    lin_path = find_lpips_lin_weights(net, lin)
    return cached_model(("lpips", net, file_key(trunk_path), file_key(lin_path)),
                        lambda: _build_lpips(net, trunk_path, lin_path))


def _build_lpips(net: str, trunk_path: Path, lin_path: Path) -> LPIPSNet:
    model = LPIPSNet(net)
    sd = load_state_dict(trunk_path, f"{net} trunk")
    what = f"{net} trunk"
    for i, layer in enumerate(model.features):
        if isinstance(layer, nn.Conv2d):
            o, c, kh, kw = layer.weight.shape
            layer.weight.data.copy_(take(sd, f"features.{i}.weight", (o, c, kh, kw), what, trunk_path))
            layer.bias.data.copy_(take(sd, f"features.{i}.bias", (o,), what, trunk_path))
    lsd = load_state_dict(lin_path, f"LPIPS {net} linear-layer")
    for k, layer in enumerate(model.lins):
        shape = tuple(layer.weight.shape)
        layer.weight.data.copy_(take(lsd, f"lin{k}.model.1.weight", shape, f"LPIPS {net} linear-layer", lin_path))
    model.weights_sha256 = {"trunk": weights_sha256(trunk_path), "lin": weights_sha256(lin_path)}
    model.weight_paths = {"trunk": str(trunk_path), "lin": str(lin_path)}
    return model


def lpips(
    x: ImageLike,
    y: ImageLike,
    model: Optional[LPIPSNet] = None,
    net: str = "alex",
    trunk: Optional[PathLike] = None,
    lin: Optional[PathLike] = None,
) -> torch.Tensor:
    r"""LPIPS distance of each image pair (lower is better), exact v0.1 math of the ``lpips`` package.

    Input sRGB :math:`[0, 1]` is mapped to :math:`[-1, 1]`, then :math:`(z - \text{shift}) / \text{scale}` with
    shift ``(-0.030, -0.088, -0.188)`` and scale ``(0.458, 0.448, 0.450)``; at each of the 5 ReLU layers
    (AlexNet relu1..5, VGG16 relu1_2..relu5_3) the features are unit-normalised along channels, the squared
    difference is weighted by the 1x1 linear layer, averaged over space, and the 5 layers are summed.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, 1]`` (or NumPy ``(H, W, 3)``); H, W >= 32.
        y: images of the same shape.
        model: a network from :func:`load_lpips`; if ``None`` it is loaded from ``net``, ``trunk``, ``lin``.

    Returns:
        ``(N,)`` float32, dimensionless, >= 0 (typically < 1); exactly 0 for identical images.
    """
    x, y = prepare_pair(x, y, "lpips")
    if model is None:
        model = load_lpips(net, trunk, lin)
    with torch.no_grad() if not (x.requires_grad or y.requires_grad) else torch.enable_grad():
        return model(x, y)


def _compute(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
    net = weights.get("lpips_net", "alex")
    model = load_lpips(net, weights.get("lpips_trunk"), weights.get("lpips_lin"))
    sha = f"trunk:{model.weights_sha256['trunk']};lin:{model.weights_sha256['lin']}"
    return lpips(x, y, model), {"variant": f"{net}-v{LPIPS_VERSION}", "weights_sha256": sha}


def _unavailable(weights: Mapping[str, Any]) -> Optional[str]:
    net = weights.get("lpips_net", "alex")
    find_trunk_weights(net, weights.get("lpips_trunk"))
    find_lpips_lin_weights(net, weights.get("lpips_lin"))
    return None


#: The metric of this module (collected by :mod:`evaluation.metrics.registry`).
METRICS = (Metric("lpips", _compute, False, "1", "[0, ~1]", "LPIPS v0.1 (AlexNet by default), local weights", "LPIPS",
                  needs_weights=True, order=2, table_order=0, variant=True, weights_key="lpips_trunk",
                  unavailable=_unavailable),)
