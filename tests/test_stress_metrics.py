"""Stress tests of the image metrics (evaluation.metrics): degenerate images, range policy, rank deficiency.

Every metric of the registry runs: the weight-free ones as they are, ``lpips``, ``lpips_vgg`` and ``sifid`` with tiny
random weights in the torchvision key layout (tests/conftest.py ``tiny_metric_weights``, as
tests/test_metrics_learned.py builds them),
``dreamsim`` only when its optional package and a local weights folder exist (never here: skipped).

Extends tests/test_metrics.py (which checks constant 40 px images for the weight-free metrics, sizes below
the minimum, and the range policy for psnr / ssim) to every metric, to images exactly at the minimum size,
to random pairs (hypothesis) and to rank-deficient Frechet statistics at extreme scales.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evaluation.metrics import METRICS, MIN_SIZE, RANGE_TOL, compute_metrics, frechet_distance
from camo_base.errors import CamoError

#: the value each metric gives an image compared with itself
IDEAL = {"psnr": math.inf, "ssim": 1.0, "lpips": 0.0, "lpips_vgg": 0.0, "lpips_proxy": 0.0, "sifid": 0.0,
         "sifid_proxy": 0.0}
#: documented value ranges (registry ``value_range``)
RANGES = {"psnr": (0.0, math.inf), "ssim": (-1.0, 1.0), "lpips": (0.0, math.inf), "lpips_vgg": (0.0, math.inf),
          "lpips_proxy": (0.0, 1.0),
          "sifid": (0.0, math.inf), "sifid_proxy": (0.0, math.inf)}


@pytest.fixture(scope="module")
def weights(tiny_metric_weights):
    """Tiny random AlexNet trunk, LPIPS v0.1 linear layers and Inception v3 stem files (tests/conftest.py)."""
    return {k: tiny_metric_weights[k] for k in ("lpips_trunk", "lpips_lin", "lpips_vgg_trunk", "lpips_vgg_lin", "sifid")}


#: the image distances (the give-away measures, masked and not symmetric, have their own tests)
ALL = [n for n in METRICS if n != "dreamsim" and not METRICS[n].masked]


def test_dreamsim_is_not_silently_computed_without_weights():
    """DreamSim needs an optional package and a local weights folder: asked for without them it is a
    one-line CamoError, never a download or a NaN (the stress cases below run every other metric)."""
    with pytest.raises(CamoError, match="local weights folder"):
        compute_metrics(np.zeros((32, 32, 3)), np.zeros((32, 32, 3)), ["dreamsim"], {})


def _row(x, y, name, weights):
    return compute_metrics(x, y, [name], weights)[name]


def _check_range(name, value):
    lo, hi = RANGES[name]
    assert not math.isnan(value), name
    assert lo - 1e-9 <= value <= hi + 1e-9 or (name == "psnr" and value == math.inf), (name, value)


@pytest.mark.parametrize("name", ALL)
def test_identical_constant_and_black_images_at_the_minimum_size(name, weights):
    """Hard case: images exactly at the metric's minimum size (psnr: 1x1; ssim 11; haarpsi 16; LPIPS / SIFID
    32): identical random images, identical constants, identical all-black images; then black vs white and
    two different constants (flat images: zero variance, rank-0 feature covariances, zero Haar responses).

    Expected: an image against itself gets the ideal value (psnr inf, ssim 1, the distances 0) even when it is
    flat or black; flat pairs give finite values inside the documented range (no NaN from 0 / 0).
    """
    n = MIN_SIZE[name]
    rng = np.random.default_rng(1)
    rand = rng.random((n, n, 3))
    for img in (rand, np.full((n, n, 3), 0.37), np.zeros((n, n, 3))):
        v = _row(img, img.copy(), name, weights)
        assert v == IDEAL[name], (name, v)
    for a, b in ((0.0, 1.0), (0.2, 0.8), (0.5, 0.5 + 1 / 255)):
        v = _row(np.full((n, n, 3), a), np.full((n, n, 3), b), name, weights)
        _check_range(name, v)
        if name not in ("ssim",):
            assert v != IDEAL[name], (name, a, b)  # a visible difference is not "identical"
    wide = np.zeros((n, 4 * n + 3, 3))  # non-square at the minimum height
    _check_range(name, _row(wide, rng.random(wide.shape), name, weights))


@pytest.mark.parametrize("name", [n for n in ALL if MIN_SIZE[n] > 1])
def test_one_pixel_below_the_minimum_is_a_camo_error(name, weights):
    """Hard case: an image one pixel below the metric's minimum in one dimension only (e.g. 31 x 200).

    Expected: CamoError naming the minimum (never a cryptic torch error or a NaN)."""
    n = MIN_SIZE[name]
    x = np.full((n - 1, max(200, 4 * n), 3), 0.5)
    with pytest.raises(CamoError, match=f"at least {n}"):
        compute_metrics(x, x, [name], weights)


@pytest.mark.parametrize("name", ALL)
def test_hdr_input_is_rejected_and_round_off_is_clamped(name, weights):
    """Hard case: linear HDR radiance (values up to 1e4, negative values, NaN, +-Inf) given where sRGB in
    [0, 1] is required, and sRGB with float round-off just outside [0, 1] (+-RANGE_TOL / 2).

    Expected (documented policy, _common.to_batch): anything further than RANGE_TOL outside [0, 1], NaN or
    Inf is a one-line CamoError pointing at linear_to_srgb; round-off is clamped, so the score equals the
    score of the clipped image exactly.
    """
    n = max(MIN_SIZE[name], 16)
    rng = np.random.default_rng(2)
    x = rng.random((n, n, 3)).astype(np.float32)
    y = rng.random((n, n, 3)).astype(np.float32)
    for bad, match in ((1e4, "linear_to_srgb"), (1.0 + 10 * RANGE_TOL, "outside"), (-0.5, "outside"),
                       (np.nan, "NaN"), (np.inf, "NaN or infinite"), (-np.inf, "NaN or infinite")):
        hdr = x.copy()
        hdr[n // 2, n // 3, 1] = bad
        for a, b in ((hdr, y), (y, hdr)):
            with pytest.raises(CamoError, match=match) as err:
                compute_metrics(a, b, [name], weights)
            assert "\n" not in str(err.value)
    nudged = x.copy()
    nudged[0, 0] = [1.0 + RANGE_TOL / 2, -RANGE_TOL / 2, 1.0]
    expect = _row(np.clip(nudged, 0.0, 1.0), y, name, weights)
    assert _row(nudged, y, name, weights) == expect


def _image(kind: str, seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "noise":
        return rng.random((n, n, 3))
    if kind == "binary":  # extreme contrast: 0/1 pixels
        return (rng.random((n, n, 3)) > 0.5).astype(np.float64)
    if kind == "ramp":
        r = np.linspace(0, 1, n)
        return np.stack(np.broadcast_arrays(r[None, :], r[:, None], 0.5 * np.ones((n, n))), -1)
    if kind == "flat":
        return np.full((n, n, 3), rng.random(3))
    if kind == "one_channel":  # rank-1 colour statistics
        img = np.zeros((n, n, 3))
        img[..., 1] = rng.random((n, n))
        return img
    return np.where(rng.random((n, n, 1)) < 0.02, 1.0, 0.0) * np.ones(3)  # sparse: mostly black


KINDS = ["noise", "binary", "ramp", "flat", "one_channel", "sparse"]


@settings(max_examples=15, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(ka=st.sampled_from(KINDS), kb=st.sampled_from(KINDS), sa=st.integers(0, 50), sb=st.integers(0, 50),
       extra=st.integers(0, 5))
def test_every_metric_is_finite_in_range_and_symmetric_on_hard_pairs(weights, ka, kb, sa, sb, extra):
    """Hard case: pairs of flat, binary (0/1), sparse (98 % black), single-channel, ramp and noise images
    at 32-37 px (every metric's minimum or just above it).

    Expected for every metric: a finite value inside the documented range (psnr may be inf only for
    identical images); every metric is symmetric in its two arguments (to 1e-5 relative).
    """
    n = 32 + extra
    a, b = _image(ka, sa, n), _image(kb, sb, n)
    ab = compute_metrics(a, b, ALL, weights)
    ba = compute_metrics(b, a, ALL, weights)
    same = np.array_equal(a, b)
    for name in ALL:
        _check_range(name, ab[name])
        if name == "psnr" and not same:
            assert math.isfinite(ab[name])
        assert ab[name] == pytest.approx(ba[name], rel=1e-5, abs=1e-9), (name, ka, kb)


# ----------------------------------------------------------------------------------- Frechet distance


def _psd(rng, d, rank, scale):
    a = rng.standard_normal((d, rank)) * scale
    return a @ a.T


def _frechet_reference(m1, s1, m2, s2) -> float:
    """Float64 reference through symmetric square roots: tr sqrt(S1^1/2 S2 S1^1/2) with eigh (PSD-safe)."""

    def sqrtm_psd(s):
        w, v = np.linalg.eigh((s + s.T) / 2)
        return (v * np.sqrt(np.clip(w, 0, None))) @ v.T

    r1 = sqrtm_psd(s1)
    w = np.linalg.eigvalsh(r1 @ s2 @ r1)
    tr = np.sqrt(np.clip(w, 0, None)).sum()
    return max(float(np.sum((m1 - m2) ** 2) + np.trace(s1) + np.trace(s2) - 2 * tr), 0.0)


@settings(max_examples=80, deadline=None)
@given(d=st.integers(1, 12), r1=st.integers(0, 12), r2=st.integers(0, 12), log_scale=st.integers(-6, 6),
       seed=st.integers(0, 10_000), shared=st.booleans())
def test_frechet_distance_on_rank_deficient_covariances(d, r1, r2, log_scale, seed, shared):
    """Hard case: covariances of rank 0 .. d (fewer samples than dimensions, dead channels, flat images) at
    scales 1e-12 .. 1e12 (scale^2), optionally sharing their column space.

    Expected: a finite value >= 0, equal to a float64 reference through symmetric PSD square roots (to
    1e-6 of the total variance), symmetric in its arguments, and exactly 0 for identical statistics.
    """
    rng = np.random.default_rng(seed)
    scale = 10.0**log_scale
    r1, r2 = min(r1, d), min(r2, d)
    s1 = _psd(rng, d, r1, scale)
    s2 = 0.25 * s1 if shared else _psd(rng, d, r2, scale)  # shared: same column space, sqrt is exact
    m1 = rng.standard_normal(d) * scale
    m2 = m1 + rng.standard_normal(d) * scale * rng.choice([0.0, 1e-3, 1.0])
    value = frechet_distance(m1, s1, m2, s2)
    total = np.trace(s1) + np.trace(s2) + np.sum((m1 - m2) ** 2) + scale**2 * 1e-12
    assert math.isfinite(value) and value >= 0
    assert value == pytest.approx(_frechet_reference(m1, s1, m2, s2), abs=1e-6 * total)
    assert value == pytest.approx(frechet_distance(m2, s2, m1, s1), abs=1e-6 * total)
    assert frechet_distance(m1, s1, m1.copy(), s1.copy()) == 0.0
