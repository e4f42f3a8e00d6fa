"""Input checks shared by the image metrics.

Every metric takes a batch ``(N, 3, H, W)`` of **sRGB-encoded** values in ``[0, 1]`` (``float32``; ``float64``
is kept as it is). :func:`to_batch` also accepts NumPy images ``(H, W, 3)`` / ``(N, H, W, 3)`` and ``uint8``
(divided by 255).

Range policy (HDR input): values in ``[-RANGE_TOL, data_range + RANGE_TOL]`` are clamped to
``[0, data_range]`` (float round-off of :func:`camo_base.imaging.linear_to_srgb`); anything further outside,
NaN or infinity raises :class:`~camo_base.errors.CamoError`. Linear HDR radiance is never clipped silently:
encode it first with ``camo_base.imaging.linear_to_srgb`` (which tone-clips to ``[0, 1]``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
from typing import Any, Callable, Iterator, Mapping, Optional, TypeVar, Union

import numpy as np
import torch

from camo_base.errors import CamoError

ImageLike = Union[torch.Tensor, np.ndarray]

#: Out-of-range values up to this far outside ``[0, data_range]`` are clamped; further ones are rejected.
RANGE_TOL = 1e-4

#: Smallest image side (pixels) each metric accepts; smaller images raise CamoError.
#: psnr: any size. ssim: the 11x11 window must fit once. haarpsi / lpips_proxy: the coarsest Haar filter
#: (8x8 after the 2x subsampling). lpips: AlexNet needs 31 px to reach relu5 (32 for both nets).
#: sifid: the Inception stem (stride 2, two valid 3x3 convs) must leave at least 2x2 positions; the proxy
#: uses the same floor so both SIFIDs accept the same crops. dreamsim resizes to 224 px.
MIN_SIZE = {
    "psnr": 1,
    "ssim": 11,
    "haarpsi": 16,
    "lpips_proxy": 16,
    "lpips": 32,
    "lpips_vgg": 32,
    "sifid": 32,
    "sifid_proxy": 32,
    "dreamsim": 32,
    "detail_ratio": 3,
    "tint": 1,
}


def metric_threads() -> int:
    """Torch intra-op threads of the weight-free metrics: ``$CAMO_METRIC_THREADS``, default **1**.

    One image pair of the benchmark is a few hundred kB: torch's intra-op threads gain little on it and lose badly
    as soon as another process shares the cores (each op's parallel region waits for a descheduled thread): on the
    2-core reference machine, busy, SSIM took 0.50 s for 32 pairs of 256x256 with 2 threads and 0.15 s with 1
    (``bench/bench_metrics.py``). Set ``CAMO_METRIC_THREADS`` (e.g. to the core count) on an idle many-core machine.
    """
    try:
        return max(1, int(os.environ.get("CAMO_METRIC_THREADS", "1")))
    except ValueError:
        return 1


@contextlib.contextmanager
def torch_threads(n: int):
    """Run the block with ``n`` torch intra-op threads (restored afterwards; cheap: ~50 us)."""
    old = torch.get_num_threads()
    if old == n:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


F_ = TypeVar("F_", bound=Callable)


def metric_thread_policy(fn: F_) -> F_:
    """Decorator: run ``fn`` with :func:`metric_threads` torch threads."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with torch_threads(metric_threads()):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def to_batch(x: ImageLike, name: str = "image", data_range: float = 1.0) -> torch.Tensor:
    """Return ``x`` as a ``(N, 3, H, W)`` float tensor in ``[0, data_range]`` (see the module's range policy).

    Accepted: torch ``(N, 3, H, W)`` or ``(3, H, W)``; NumPy ``(H, W, 3)`` or ``(N, H, W, 3)`` (float, or
    ``uint8`` which is divided by 255 and then scaled to ``data_range``). Float tensors keep their dtype if it is
    ``float64``, anything else becomes ``float32``. Gradients flow through (the clamp is the only op).
    """
    if isinstance(x, np.ndarray):
        arr = x
        if arr.dtype == np.uint8:
            arr = arr.astype(np.float32) * np.float32(data_range / 255.0)
        elif arr.dtype == bool or not np.issubdtype(arr.dtype, np.number):
            raise CamoError(f"{name}: expected a numeric image array, got dtype {arr.dtype}")
        if arr.ndim == 3:
            arr = arr[None]
        if arr.ndim != 4 or arr.shape[-1] != 3:
            raise CamoError(f"{name}: expected a NumPy image (H, W, 3) or (N, H, W, 3), got shape {tuple(x.shape)}")
        t = torch.from_numpy(np.ascontiguousarray(arr)).permute(0, 3, 1, 2)
    elif isinstance(x, torch.Tensor):
        t = x
        if t.ndim == 3:
            t = t[None]
        if t.ndim != 4 or t.shape[1] != 3:
            raise CamoError(f"{name}: expected a tensor (N, 3, H, W) or (3, H, W), got shape {tuple(x.shape)}")
        if t.dtype == torch.uint8:
            t = t.float() * (data_range / 255.0)
    else:
        raise CamoError(f"{name}: expected a torch.Tensor or numpy.ndarray, got {type(x).__name__}")
    if t.dtype != torch.float64:
        t = t.float()
    if t.numel() == 0:
        raise CamoError(f"{name}: empty image, shape {tuple(t.shape)}")
    with torch.no_grad():
        lo, hi = float(t.amin()), float(t.amax())  # NaN propagates into both; 10x faster than aminmax
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise CamoError(f"{name}: contains NaN or infinite values")
    if lo < -RANGE_TOL or hi > data_range + RANGE_TOL:
        raise CamoError(
            f"{name}: values in [{lo:.4g}, {hi:.4g}] are outside [0, {data_range:g}]; metrics take sRGB-encoded "
            "images (encode HDR/linear radiance with camo_base.imaging.linear_to_srgb, which tone-clips)"
        )
    if lo < 0.0 or hi > data_range:
        t = t.clamp(0.0, data_range)
    return t


def check_data_range(data_range: float, metric: str) -> None:
    """CamoError (one line) unless ``data_range`` is a finite number > 0 (NaN, inf, 0, negatives, non-numbers)."""
    ok = (isinstance(data_range, (int, float, np.number)) and not isinstance(data_range, (bool, np.bool_))
          and math.isfinite(float(data_range)) and float(data_range) > 0)
    if not ok:
        raise CamoError(f"{metric}: data_range must be a finite number > 0, got {data_range!r}")


def check_size(t: torch.Tensor, metric: str, name: str = "image", min_size: Optional[int] = None) -> None:
    """Raise CamoError when ``t``'s smaller side is below ``min_size`` (default ``MIN_SIZE[metric]``, else 1)."""
    need = min_size if min_size is not None else MIN_SIZE.get(metric, 1)
    h, w = int(t.shape[-2]), int(t.shape[-1])
    if min(h, w) < need:
        raise CamoError(f"{metric}: {name} is {h}x{w} px; this metric needs at least {need}x{need} px")


def prepare_pair(
    x: ImageLike, y: ImageLike, metric: str, data_range: float = 1.0, same_size: bool = True,
    min_size: Optional[int] = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Convert and check an image pair for ``metric``: same batch size (and size unless ``same_size=False``),
    at least ``min_size`` px (default ``MIN_SIZE[metric]``, else 1), values in ``[0, data_range]``. Both get the
    wider of the two dtypes."""
    check_data_range(data_range, metric)
    tx = to_batch(x, "x", data_range)
    ty = to_batch(y, "y", data_range)
    if same_size and tx.shape != ty.shape:
        raise CamoError(f"{metric}: image shapes differ: {tuple(tx.shape)} vs {tuple(ty.shape)}")
    if tx.shape[0] != ty.shape[0]:
        raise CamoError(f"{metric}: batch sizes differ: {tx.shape[0]} vs {ty.shape[0]}")
    check_size(tx, metric, "x", min_size)
    check_size(ty, metric, "y", min_size)
    if tx.dtype != ty.dtype:
        tx, ty = tx.double(), ty.double()
    if tx.device != ty.device:
        raise CamoError(f"{metric}: images are on different devices ({tx.device} vs {ty.device})")
    return tx, ty


#: Images are processed in chunks of about this many pixels: a 256x256 image's filtered maps then stay in the
#: CPU cache, which makes the depthwise convolutions 5-8x faster than one pass over a large batch.
CHUNK_PIXELS = 1 << 16


def chunks(t: torch.Tensor, pixels: int = CHUNK_PIXELS) -> Iterator[slice]:
    """Slices of the batch dimension of ``t`` ``(N, C, H, W)`` holding about ``pixels`` pixels each (>= 1 image)."""
    n, per = int(t.shape[0]), max(1, pixels // max(1, int(t.shape[-2]) * int(t.shape[-1])))
    for i in range(0, n, per):
        yield slice(i, min(n, i + per))


# --------------------------------------------------------------------------------------------------------------
# the record every metric module declares
# --------------------------------------------------------------------------------------------------------------

#: ``compute(x, y, weights) -> (values (N,), extra)``: a metric on a checked batch pair (``extra``: ``variant`` and
#: ``weights_sha256`` strings, written as the ``{name}_variant`` / ``{name}_weights_sha256`` columns).
Compute = Callable[[torch.Tensor, torch.Tensor, Mapping[str, Any]], "tuple[torch.Tensor, dict[str, Any]]"]


@dataclasses.dataclass(frozen=True)
class Metric:
    """One image metric of the benchmark, as its module declares it in ``METRICS`` (collected by
    :mod:`evaluation.metrics.registry`; the metrics table's columns, the report's Table II columns and the
    ``--metrics`` help are made from these records).

    ``label``: the column header without its arrow (``"PSNR"``); ``decimals``: digits in report tables;
    ``order``: position among the columns of ``metrics.parquet`` (new metrics: after the built-in ones);
    ``table_order``: position in Table II (the paper's five first); ``variant``: its rows carry
    ``{name}_variant``; ``weights_key``: the weights entry whose presence asks for a learned metric;
    ``unavailable(weights)``: why it cannot run with these weights (None: it can; raise CamoError or return a
    reason); ``needs``: one line saying what a user needs to compute it (printed where it is skipped and in the
    docs table; "" for weight-free metrics); ``by_default``: computed without ``--metrics`` whenever it can run
    (False: only when asked for by name, e.g. ``lpips_vgg``); ``cross_check``: a weight-free stand-in on its own
    scale (reports label its column "(cross-check)"; it is not the metric it approximates); ``from_path(path)``:
    the weights entries of the path a user gives for this metric (``camo evaluate --weights NAME=PATH``, a grid's
    ``[evaluate] weights``; CamoError, one line, when the path does not hold them): a learned metric's weights
    option is this function, no flag or settings field elsewhere."""

    name: str
    compute: Compute
    higher_is_better: bool
    units: str
    value_range: str
    description: str
    label: str
    needs_weights: bool = False
    decimals: int = 4
    order: float = 100.0
    table_order: float = 100.0
    variant: bool = False
    weights_key: str = ""
    unavailable: Optional[Callable[[Mapping[str, Any]], Optional[str]]] = None
    #: a give-away measure of the object's own pixels: ``compute(x, y, weights, mask)`` also takes the object's
    #: mask ``(N, 1, H, W)`` bool (:func:`masked`); without a mask it measures the whole image
    masked: bool = False
    #: the ideal value when it is neither end of the range (a ratio: 1); ``higher_is_better`` is then ignored and
    #: "better" means closer to it in log ratio (:meth:`badness`)
    target: Optional[float] = None
    needs: str = ""
    by_default: bool = True
    cross_check: bool = False
    from_path: Optional[Callable[[str], dict[str, str]]] = None

    @property
    def header(self) -> str:
        """The column header with the better direction: ``"PSNR↑"``, ``"LPIPS↓"``, ``"Detail→1"``."""
        if self.target is not None:
            return f"{self.label}→{self.target:g}"
        return f"{self.label}{'↑' if self.higher_is_better else '↓'}"

    def badness(self, value: float) -> float:
        """How far ``value`` is from the best (smaller is better): ``-value`` / ``value`` for a directed metric,
        ``|log(value / target)|`` for one with a :attr:`target` (0.8 and 1.25 are equally far from 1)."""
        if self.target is not None:
            return abs(math.log(max(value, 1e-12) / self.target))
        return -value if self.higher_is_better else value


def masked(fn: Callable[..., torch.Tensor]) -> Compute:
    """The ``compute`` of a weight-free give-away measure ``fn(x, y, mask)`` (``mask`` ``(N, 1, H, W)`` bool or
    None for the whole image); declare its :class:`Metric` with ``masked=True``."""
    def run(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any],
            mask: Optional[torch.Tensor] = None) -> "tuple[torch.Tensor, dict[str, Any]]":
        return fn(x, y, mask), {}

    return run


def to_mask(mask: Any, like: torch.Tensor, metric: str) -> torch.Tensor:
    """``mask`` (NumPy or torch, ``(H, W)``, ``(N, H, W)`` or ``(N, 1, H, W)``, bool or 0/1 or 0/255) as a
    ``(N, 1, H, W)`` bool tensor matching the image batch ``like``; None gives all True. CamoError on a shape that
    does not fit."""
    n, _, h, w = like.shape
    if mask is None:
        return torch.ones((n, 1, h, w), dtype=torch.bool)
    m = torch.from_numpy(np.ascontiguousarray(mask)) if isinstance(mask, np.ndarray) else mask
    if not isinstance(m, torch.Tensor):
        raise CamoError(f"{metric}: mask must be a NumPy array or torch tensor, got {type(mask).__name__}")
    if m.ndim == 2:
        m = m[None, None]
    elif m.ndim == 3:
        m = m[:, None]
    if m.ndim != 4 or m.shape[1] != 1 or tuple(m.shape[-2:]) != (h, w) or m.shape[0] not in (1, n):
        raise CamoError(f"{metric}: mask shape {tuple(mask.shape)} does not fit images of shape {tuple(like.shape)}")
    return (m != 0).expand(n, 1, h, w)


def plain(fn: Callable[..., torch.Tensor], variant: str = "") -> Compute:
    """The ``compute`` of a weight-free metric function ``fn(x, y)`` (with a fixed ``variant`` string, if any)."""
    def run(x: torch.Tensor, y: torch.Tensor, weights: Mapping[str, Any]) -> "tuple[torch.Tensor, dict[str, Any]]":
        extra = {"variant": variant} if variant else {}
        return fn(x, y), extra

    return run
