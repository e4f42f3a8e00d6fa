"""Correctness edges of the image metrics found from outside (issue 31): layouts and shapes, ``data_range``, and
Frechet distances of tiny covariances.

* The same pair given as a NumPy HWC image and a torch CHW tensor, or as NCHW and channels-last tensors, is the
  same pair: every metric gives the value of the plain NumPy pair (PSNR's fast path summed over memory order and
  gave 7.48 dB instead of 26.52).
* Shapes that differ -- (256, 512, 3) against (512, 256, 3) has the same number of values -- are a one-line error
  on every metric, never a number.
* ``data_range`` NaN / inf / 0 / negative is a one-line error (PSNR and SSIM returned NaN).
* ``frechet_distance`` of covariances with entries <= 1e-160 (whose products underflow) is exact, not 3x off.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import linalg

from camo_base.errors import CamoError
from evaluation.metrics import METRICS, compute_metrics, frechet_distance, haarpsi, lpips_proxy, psnr, ssim
from evaluation.metrics.psnr import _fast_mse


@pytest.fixture(scope="module")
def weights(tiny_metric_weights):
    return {k: v for k, v in tiny_metric_weights.items() if k != "lpips_dir"}


#: Every metric that runs here (dreamsim needs its optional package).
ALL = [n for n in METRICS if n != "dreamsim"]


def _pair(h: int = 64, w: int = 80, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    from skimage import data

    a = (data.astronaut()[100:100 + h, 150:150 + w] / 255.0).astype(np.float32)
    rng = np.random.default_rng(seed)
    b = np.clip(a + 0.05 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    return a, b


def _chw(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(a).permute(2, 0, 1).contiguous()


def test_psnr_of_the_issue_is_the_same_in_every_layout():
    a, b = _pair()
    want = float(psnr(a, b))
    assert 20 < want < 40
    assert float(psnr(a, _chw(b))) == pytest.approx(want, rel=1e-6)  # HWC numpy vs CHW torch
    assert float(psnr(_chw(a), b)) == pytest.approx(want, rel=1e-6)
    nchw, cl = _chw(a)[None], _chw(b)[None].contiguous(memory_format=torch.channels_last)
    assert cl.is_contiguous(memory_format=torch.channels_last) and not cl.is_contiguous()
    assert float(psnr(nchw, cl)) == pytest.approx(want, rel=1e-6)  # NCHW vs channels-last
    assert float(psnr(nchw.contiguous(memory_format=torch.channels_last), cl)) == pytest.approx(want, rel=1e-6)
    # the fast path is still taken where both layouts agree (and declines the mixed ones)
    assert _fast_mse(a, b, 1.0) is not None and _fast_mse(nchw, _chw(b)[None], 1.0) is not None
    assert _fast_mse(a, _chw(b), 1.0) is None and _fast_mse(nchw, cl, 1.0) is None


@pytest.mark.parametrize("name", ALL)
def test_every_metric_gives_the_same_value_in_every_layout(name, weights):
    a, b = _pair(64, 64)
    want = compute_metrics(a, b, [name], weights)[name]
    for x, y in ((a, _chw(b)), (_chw(a), b), (_chw(a)[None], _chw(b)[None].contiguous(memory_format=torch.channels_last))):
        got = compute_metrics(x, y, [name], weights)[name]
        assert got == pytest.approx(want, rel=1e-5, abs=1e-6), name


@pytest.mark.parametrize("name", ALL)
def test_every_metric_refuses_mismatched_shapes_in_one_line(name, weights):
    rng = np.random.default_rng(0)
    cases = [
        (rng.random((256, 512, 3), dtype=np.float32), rng.random((512, 256, 3), dtype=np.float32)),  # same size
        (rng.random((64, 64, 3)), rng.random((64, 72, 3))),
        (rng.random((2, 64, 64, 3)), rng.random((3, 64, 64, 3))),
        (torch.rand(3, 64, 64), torch.rand(3, 64, 80)),
    ]
    for x, y in cases:
        with pytest.raises(CamoError, match="differ") as err:
            compute_metrics(x, y, [name], weights)
        assert "\n" not in str(err.value)
    for bad in (torch.rand(64, 64, 3), np.zeros((3, 64, 64)), np.zeros((64, 64, 4)), np.zeros((64, 64))):
        with pytest.raises(CamoError, match="expected") as err:
            compute_metrics(bad, bad, [name], weights)
        assert "\n" not in str(err.value)


def test_psnr_refuses_the_transposed_float32_pair_of_the_issue():
    rng = np.random.default_rng(1)
    x = rng.random((256, 512, 3), dtype=np.float32)
    with pytest.raises(CamoError, match=r"image shapes differ: \(1, 3, 256, 512\) vs \(1, 3, 512, 256\)"):
        psnr(x, np.ascontiguousarray(x.reshape(512, 256, 3)))


@pytest.mark.parametrize("fn", [psnr, ssim, haarpsi, lpips_proxy])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 0.0, -1.0, "1"])
def test_bad_data_range_is_a_one_line_error(fn, bad):
    a, b = _pair(40, 40)
    with pytest.raises(CamoError, match="data_range must be a finite number > 0") as err:
        fn(a, b, data_range=bad)
    assert "\n" not in str(err.value)
    assert math.isfinite(float(fn(a, b, data_range=1.0)))


def _stats(d: int, seed: int):
    rng = np.random.default_rng(seed)
    a, b = rng.standard_normal((d, d)), rng.standard_normal((d, 2 * d))
    return rng.standard_normal(d), a @ a.T, rng.standard_normal(d), b @ b.T / (2 * d)


def _scipy_frechet(m1, s1, m2, s2) -> float:
    covmean = linalg.sqrtm(s1 @ s2).real
    return float((m1 - m2) @ (m1 - m2) + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


@pytest.mark.parametrize("c", [1e-320, 1e-300, 1e-200, 1e-160, 1e-100, 1.0, 1e100])
def test_frechet_distance_is_exact_at_every_scale(c):
    """Features scaled by sqrt(c) scale the squared distance by c; at c <= 1e-160 the covariance products
    underflowed and the cross term vanished (the issue measured a relative error of 3)."""
    m1, s1, m2, s2 = _stats(6, 3)
    want = _scipy_frechet(m1, s1, m2, s2)
    r = math.sqrt(c)
    got = frechet_distance(m1 * r, s1 * c, m2 * r, s2 * c)
    rel = 1e-6 if c > 1e-300 else 1e-3  # 1e-320 is subnormal: few significant bits left in the input itself
    assert got == pytest.approx(c * want, rel=rel)
    # rank-deficient tiny covariances stay exact too: diag(1, 0) vs diag(0, 1) scaled -> 2 c
    assert frechet_distance(np.zeros(2), np.diag([c, 0.0]), np.zeros(2), np.diag([0.0, c])) == pytest.approx(2 * c)
