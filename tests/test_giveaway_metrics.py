"""The give-away measures (evaluation/metrics/detail_ratio.py, tint.py): known images, an independent reference
(SciPy's convolution, scikit-image's CIELAB), the mask's handling and the input checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import convolve
from skimage.color import deltaE_cie76, rgb2lab

from camo_base.errors import CamoError
from evaluation.metrics import METRICS, WEIGHT_FREE, compute_metrics
from evaluation.metrics.detail_ratio import EPS, LUMA, detail_ratio, interior
from evaluation.metrics.tint import tint

KERNEL = np.array([[1, 1, 1], [1, -8, 1], [1, 1, 1]], np.float64)


def _energy(img, m):
    y = img @ np.array(LUMA)
    lap = np.abs(convolve(y, KERNEL, mode="mirror"))  # scipy "mirror" = kornia / torch "reflect"
    return lap[m].mean()


def _ref_interior(mask):
    inner = np.zeros_like(mask)
    padded = np.pad(mask, 1, constant_values=True)
    h, w = mask.shape
    inner[:] = True
    for dy in range(3):
        for dx in range(3):
            inner &= padded[dy:dy + h, dx:dx + w]
    return inner


def test_detail_ratio_matches_a_scipy_reference_inside_the_eroded_mask():
    rng = np.random.default_rng(3)
    bg = rng.uniform(0.3, 0.7, (40, 48, 3))
    obj = bg.copy()
    mask = np.zeros((40, 48), bool)
    mask[10:30, 12:36] = True
    obj[mask] = rng.uniform(0, 1, (int(mask.sum()), 3))  # a speckled body
    inner = _ref_interior(mask)
    assert inner.sum() == 18 * 22
    np.testing.assert_array_equal(interior(__import__("torch").from_numpy(mask)[None, None])[0, 0].numpy(), inner)
    want = (EPS + _energy(obj, inner)) / (EPS + _energy(bg, inner))
    got = float(detail_ratio(obj.astype(np.float32), bg.astype(np.float32), mask))
    assert got == pytest.approx(want, rel=1e-4)
    assert got > 2.0  # speckle reads as > 1


def test_detail_ratio_known_values():
    """Same texture: exactly 1; a flat body over a textured background: EPS / (EPS + E) < 1; flat over flat: 1;
    the silhouette's own edge does not count (a flat body of another colour over a flat ground is 1)."""
    rng = np.random.default_rng(0)
    tex = rng.uniform(0, 1, (32, 32, 3)).astype(np.float32)
    mask = np.zeros((32, 32), bool)
    mask[8:24, 8:24] = True
    assert float(detail_ratio(tex, tex, mask)) == 1.0
    flat = tex.copy()
    flat[mask] = 0.5
    inner = _ref_interior(mask)
    want = EPS / (EPS + _energy(tex.astype(np.float64), inner))
    assert float(detail_ratio(flat, tex, mask)) == pytest.approx(want, rel=1e-4) and want < 0.05
    ground = np.full((32, 32, 3), 0.2, np.float32)
    body = ground.copy()
    body[mask] = 0.9
    assert float(detail_ratio(body, ground, mask)) == pytest.approx(1.0)
    assert float(detail_ratio(body, ground, None)) > 5  # whole image: the edge is texture there


def test_detail_ratio_is_nan_without_interior_and_per_image_in_a_batch():
    x = np.full((2, 16, 16, 3), 0.5, np.float32)
    x[1, 4:12, 4:12] = np.indices((8, 8)).sum(0)[..., None] % 2
    m = np.zeros((2, 16, 16), bool)
    m[:, 4:12, 4:12] = True
    y = np.full((2, 16, 16, 3), 0.5, np.float32)
    v = detail_ratio(x, y, m).numpy()
    assert v[0] == 1.0 and v[1] > 100
    thin = np.zeros((16, 16), bool)
    thin[5:7, 3:12] = True  # 2 px tall: no pixel with its 3x3 neighbourhood inside
    assert math.isnan(float(detail_ratio(x[1], y[1], thin)))


def test_tint_matches_skimage_cielab():
    rng = np.random.default_rng(1)
    bg = rng.uniform(0.1, 0.9, (24, 24, 3))
    obj = bg.copy()
    mask = np.zeros((24, 24), bool)
    mask[4:20, 6:18] = True
    obj[mask] = np.clip(obj[mask] * [0.8, 1.05, 0.9] + [0.0, 0.05, 0.0], 0, 1)  # a greenish cast
    want = deltaE_cie76(rgb2lab(obj)[mask].mean(0), rgb2lab(bg)[mask].mean(0))
    got = float(tint(obj.astype(np.float32), bg.astype(np.float32), mask))
    assert got == pytest.approx(want, rel=2e-3)
    # texture that cancels in the means is not a tint: a body of the background's pixels shuffled
    perm = obj.copy()
    perm[mask] = rng.permutation(bg[mask])
    assert float(tint(perm.astype(np.float32), bg.astype(np.float32), mask)) < 0.5 < got
    assert float(tint(bg, bg, mask)) == 0.0
    assert math.isnan(float(tint(bg, bg, np.zeros((24, 24), bool))))


def test_registered_as_masked_weight_free_give_aways():
    for name, header in (("detail_ratio", "Detail→1"), ("tint", "Tint↓")):
        m = METRICS[name]
        assert m.masked and name in WEIGHT_FREE and m.header == header
    assert METRICS["detail_ratio"].badness(0.8) == pytest.approx(METRICS["detail_ratio"].badness(1.25))
    x = np.full((16, 16, 3), 0.5, np.float32)
    y = x.copy()
    y[..., 0] = 0.6
    m = np.zeros((16, 16), bool)
    m[2:14, 2:14] = True
    row = compute_metrics(x, y, ["tint", "detail_ratio", "psnr"], mask=m)
    assert row["tint"] == pytest.approx(float(tint(x, y, m))) and row["detail_ratio"] == 1.0


@pytest.mark.parametrize("fn", [detail_ratio, tint])
def test_input_checks(fn):
    x = np.full((16, 16, 3), 0.5, np.float32)
    with pytest.raises(CamoError, match="does not fit"):
        fn(x, x, np.ones((15, 16), bool))
    with pytest.raises(CamoError, match="shapes differ"):
        fn(x, x[:8], None)
    with pytest.raises(CamoError, match="linear_to_srgb"):
        fn(x * 3, x, None)
    with pytest.raises(CamoError, match="mask must be"):
        fn(x, x, [[1]])
