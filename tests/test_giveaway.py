"""Where the object gives itself away (evaluation.giveaway): the noise-aware cast-shadow mask and the object /
shadow / rest split of the squared error and of LPIPS (Shapley parts), on synthetic images with a known shadow."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evaluation.giveaway import (MAD_TO_SIGMA, SHADOW_MIN_STEP, SHADOW_SIGMAS, object_region, shadow_mask,
                                 split_region)


def _scene(noise: float, seed: int = 0, shadow_factor: float = 0.7):
    """A 96 x 96 textured background; the object a 20 x 20 square; its shadow a 16 x 30 band right of and below it,
    darkened by ``shadow_factor``; independent render noise of ``noise`` (sRGB units) in both images. Returns
    ``(obj8, bg8, mask, true_shadow)``."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:96, 0:96] / 95.0
    base = np.stack([0.35 + 0.2 * xx, 0.45 + 0.1 * np.sin(6 * yy), 0.3 + 0.15 * xx * yy], axis=-1)
    mask = np.zeros((96, 96), bool)
    mask[30:50, 30:50] = True
    shadow = np.zeros((96, 96), bool)
    shadow[40:56, 50:80] = True
    obj = base.copy()
    obj[shadow] *= shadow_factor
    obj[mask] = [0.8, 0.2, 0.2]
    bg = base + noise * rng.standard_normal(base.shape)
    obj = obj + noise * rng.standard_normal(base.shape)
    to8 = lambda a: np.clip(np.round(a * 255), 0, 255).astype(np.uint8)  # noqa: E731
    return to8(obj), to8(bg), mask, shadow


@pytest.mark.parametrize("noise", [0.0, 0.01, 0.03])
def test_shadow_mask_finds_the_cast_shadow_and_adapts_to_noise(noise):
    obj8, bg8, mask, truth = _scene(noise)
    found, tau = shadow_mask(obj8, bg8, mask)
    assert tau >= SHADOW_MIN_STEP
    outside = ~object_region(mask)
    true_out = truth & outside
    recall = (found & true_out).sum() / true_out.sum()
    near = object_region(truth)  # the true shadow and its 1-px ring (the 3x3 average reaches one pixel beyond)
    false_pos = (found & ~near).sum() / (outside & ~near).sum()
    assert recall > 0.9, recall
    assert false_pos < 0.005, false_pos
    assert not (found & object_region(mask)).any()  # never on the object or its 1-px ring
    if noise >= 0.03:  # the threshold follows the noise: 3 sigma of the 3x3-averaged difference of two renders
        luma_noise = noise * float(np.linalg.norm([0.2126, 0.7152, 0.0722]))  # independent channel noise
        expected = SHADOW_SIGMAS * luma_noise * math.sqrt(2) / 3  # two renders, averaged over 9 pixels
        assert tau == pytest.approx(expected, rel=0.15) and tau > 2 * SHADOW_MIN_STEP


def test_shadow_mask_ignores_pure_noise_and_brightening():
    obj8, bg8, mask, _ = _scene(0.02, shadow_factor=1.0)  # no shadow at all
    found, tau = shadow_mask(obj8, bg8, mask)
    assert found.mean() < 0.003 and tau > SHADOW_MIN_STEP
    obj8, bg8, mask, _ = _scene(0.0, shadow_factor=1.3)  # light thrown on the ground: brighter, not a shadow
    found, _ = shadow_mask(obj8, bg8, mask)
    assert not found.any()
    # robust estimate: 1.4826 * median(|x|) of a half-normal sample is its sigma
    assert MAD_TO_SIGMA == pytest.approx(1 / 0.6745, rel=1e-3)


def test_noise_near_the_object_only_is_measured_there():
    """camo renders both images with the same sampler seed: far from the object they are identical, noise differs
    only where paths meet the object. The threshold must follow that local noise, not the exact zeros around it."""
    rng = np.random.default_rng(4)
    obj8, bg8, mask, _ = _scene(0.0, shadow_factor=1.0)  # no shadow
    near = np.zeros(mask.shape, bool)
    near[15:65, 15:65] = True
    noisy = obj8.astype(float) + np.where(near[..., None], 0.03 * 255 * rng.standard_normal(obj8.shape), 0)
    obj_n = np.clip(np.round(noisy), 0, 255).astype(np.uint8)
    found, tau = shadow_mask(obj_n, bg8, mask)
    luma_noise = 0.03 * float(np.linalg.norm([0.2126, 0.7152, 0.0722]))  # one image noisy, averaged over 9 px
    assert tau == pytest.approx(SHADOW_SIGMAS * luma_noise / 3, rel=0.15)  # not the floor of the identical pixels
    assert tau > 2.5 * SHADOW_MIN_STEP
    assert found.sum() < 0.005 * (near & ~object_region(mask)).sum()
    # and a real shadow in that noise is still found
    obj_s, _, _, truth = _scene(0.0, shadow_factor=0.6)
    obj_s = np.clip(np.round(obj_s.astype(float) + (noisy - obj8)), 0, 255).astype(np.uint8)
    found, _ = shadow_mask(obj_s, bg8, mask)
    t = truth & ~object_region(mask)
    assert (found & t).sum() > 0.8 * t.sum()


def test_light_thrown_by_the_object_raises_the_threshold_without_becoming_shadow():
    obj8, bg8, mask, _ = _scene(0.01)
    lit = obj8.astype(float)
    lit[60:90, 5:30] *= 1.25  # a reflection on the ground
    found, tau = shadow_mask(np.clip(lit, 0, 255).astype(np.uint8), bg8, mask)
    _, tau0 = shadow_mask(obj8, bg8, mask)
    assert not found[60:90, 5:30].any() and tau >= tau0


def test_split_adds_up_and_shapley_equals_the_pixel_split_for_an_additive_metric():
    obj8, bg8, mask, _ = _scene(0.01)
    shadow, _ = shadow_mask(obj8, bg8, mask)
    a, b = obj8 / 255.0, bg8 / 255.0

    def mse(xs, ys):  # a metric that is a sum over pixels
        return [float(((x / 255.0 - y / 255.0) ** 2).mean()) for x, y in zip(xs, ys)]

    out = split_region(obj8, bg8, mask, shadow, mse)
    assert out["pixels_object"] + out["pixels_shadow"] + out["pixels_rest"] == 96 * 96
    assert out["pixels_object"] == object_region(mask).sum()
    total = float(((a - b) ** 2).mean())
    assert out["sqerr_object"] + out["sqerr_shadow"] + out["sqerr_rest"] == pytest.approx(total, rel=1e-12)
    for p in ("object", "shadow", "rest"):  # Shapley of an additive metric = the per-part sums
        assert out[f"lpips_{p}"] == pytest.approx(out[f"sqerr_{p}"], rel=1e-9, abs=1e-15)
    assert out["sqerr_shadow"] > 0.1 * total and out["sqerr_object"] > out["sqerr_shadow"]
    assert math.isnan(split_region(obj8, bg8, mask, shadow)["lpips_object"])  # no LPIPS function: NaN


def test_shapley_parts_of_a_non_additive_metric_sum_to_its_value():
    obj8, bg8, mask, _ = _scene(0.0)
    shadow, _ = shadow_mask(obj8, bg8, mask)

    def peak(xs, ys):  # max abs difference: not additive over pixels
        return [float(np.abs(x.astype(float) - y.astype(float)).max()) for x, y in zip(xs, ys)]

    out = split_region(obj8, bg8, mask, shadow, peak)
    full = peak([obj8], [bg8])[0]
    assert out["lpips_object"] + out["lpips_shadow"] + out["lpips_rest"] == pytest.approx(full)
    assert out["lpips_object"] > out["lpips_shadow"] >= 0  # the red square differs most
    # the same image: every part 0
    same = split_region(bg8, bg8, mask, np.zeros_like(mask), peak)
    assert all(same[f"{w}_{p}"] == 0 for w in ("sqerr", "lpips") for p in ("object", "shadow", "rest"))


def test_real_lpips_split_puts_a_shadow_in_the_shadow(installed_lpips):
    from evaluation.metrics import load_lpips, lpips

    model = load_lpips("alex")
    obj8, bg8, mask, _ = _scene(0.005)
    shadow, _ = shadow_mask(obj8, bg8, mask)
    out = split_region(obj8, bg8, mask, shadow, lambda x, y: lpips(x, y, model).tolist())
    value = float(lpips(obj8, bg8, model))
    assert out["lpips_object"] + out["lpips_shadow"] + out["lpips_rest"] == pytest.approx(value, rel=1e-5)
    assert out["lpips_shadow"] > 0.1 * value and out["lpips_object"] > 0.1 * value
    assert abs(out["lpips_rest"]) < 0.1 * value
