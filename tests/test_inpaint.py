"""Stage-2 inpainting: the interface contract and the offline ``patch`` backend.

Texture images are scikit-image's bundled grass/gravel/brick photographs
(shipped with the wheel, no download), tinted to colour.
"""

from __future__ import annotations

import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
import skimage.data

from camo_base.errors import CamoError
from optimizer.optimise.inpaint import DEFAULT_INPAINTER, INPAINTERS, get_inpainter
from optimizer.optimise.inpainting.patch import PatchInpainter, log_depth, telea_fill

H = W = 256


def texture(name: str, tint, size: int = H, off: int = 0) -> np.ndarray:
    g = getattr(skimage.data, name)()[off : off + size, off : off + size].astype(np.float32) / 255.0
    return np.clip(g[..., None] * np.asarray(tint, np.float32), 0.0, 1.0).astype(np.float32)


def square_mask(y0, y1, x0, x1, shape=(H, W)) -> np.ndarray:
    m = np.zeros(shape, bool)
    m[y0:y1, x0:x1] = True
    return m


def grey_square_scene(name: str, tint, lo: int, hi: int, size: int = H, depth: float = 5.0):
    """``(img, mask, bg, depth)``, as ``inpaint`` takes them: a ``texture(name, tint, size)`` background with a grey
    (0.5) square object over rows and columns ``lo:hi``, everything at the constant ``depth``."""
    bg = texture(name, tint, size=size)
    mask = square_mask(lo, hi, lo, hi, (size, size))
    img = bg.copy()
    img[mask] = 0.5
    return img, mask, bg, np.full((size, size), depth, np.float32)


def laplacian_var(img: np.ndarray, region: np.ndarray) -> float:
    lap = cv2.Laplacian(img.mean(axis=-1).astype(np.float32), cv2.CV_32F)
    return float(lap[region].var())


def local_std(img: np.ndarray, region: np.ndarray, k: int = 7) -> float:
    g = img.mean(axis=-1).astype(np.float32)
    mu = cv2.blur(g, (k, k))
    sd = np.sqrt(np.maximum(cv2.blur(g * g, (k, k)) - mu * mu, 0.0))
    return float(sd[region].mean())


@pytest.fixture(scope="module")
def patch():
    return get_inpainter("patch")


# ----------------------------------------------------------------------------- registry / contract


def test_registry_names_and_default():
    assert DEFAULT_INPAINTER == "patch"
    assert set(INPAINTERS) == {"patch", "diffusers"}
    assert isinstance(get_inpainter(), PatchInpainter)
    assert isinstance(get_inpainter(" Patch "), PatchInpainter)


def test_unknown_backend_is_camoerror():
    with pytest.raises(CamoError, match="unknown Stage-2 inpainting backend") as ei:
        get_inpainter("stable-diffusion-9")
    assert "\n" not in str(ei.value)


def test_bad_patch_options_are_camoerror():
    with pytest.raises(CamoError, match="bad option|unexpected"):
        get_inpainter("patch", no_such_option=3)
    with pytest.raises(CamoError, match="patch_size"):
        get_inpainter("patch", patch_size=4)
    # None-valued options (e.g. CLI flags not given) are ignored; given ones are rejected by "patch"
    assert isinstance(get_inpainter("patch", sdxl_path=None, controlnet_path=None), PatchInpainter)
    with pytest.raises(CamoError):
        get_inpainter("patch", sdxl_path="/somewhere")


def test_import_is_light():
    code = "import sys, optimizer.optimise.inpaint; print('torch' in sys.modules, 'diffusers' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]


def _scene(seed=0, shape=(96, 112)):
    rng = np.random.default_rng(seed)
    bg = rng.random((*shape, 3), dtype=np.float32)
    img = bg.copy()
    mask = np.zeros(shape, bool)
    mask[30:60, 40:75] = True
    img[mask] = 0.25
    depth = np.full(shape, 3.0, np.float32)
    return img, mask, bg, depth


def test_unmasked_pixels_bit_exact(patch):
    img, mask, bg, depth = _scene()
    # values a renderer may produce outside the mask: > 1, negative, NaN, -0.0 -- all must come back untouched
    img[0, 0] = [np.nan, 1.5, -0.0]
    img[5, 7] = [-0.25, 2.0, np.inf]
    img[~mask] += np.float32(1e-7)
    out = patch.inpaint(img, mask, bg, depth, strength=1.0, seed=3)
    assert out.dtype == np.float32 and out.shape == img.shape
    assert np.array_equal(out[~mask].view(np.uint32), img[~mask].view(np.uint32))
    assert np.isfinite(out[mask]).all() and out[mask].min() >= 0.0 and out[mask].max() <= 1.0
    assert not np.allclose(out[mask], img[mask])  # something was synthesised


def test_mask_on_image_border_and_odd_size(patch):
    img, _, bg, depth = _scene(shape=(77, 91))
    mask = np.zeros((77, 91), bool)
    mask[:20, 60:] = True  # touches two image borders
    out = patch.inpaint(img, mask, bg, depth, 1.0, 0)
    assert np.array_equal(out[~mask].view(np.uint32), img[~mask].view(np.uint32))
    assert np.isfinite(out).all()


def test_deterministic_for_fixed_seed(patch):
    img, mask, bg, depth = grey_square_scene("gravel", (1.0, 0.9, 0.8), 44, 84, size=128, depth=4.0)
    a = patch.inpaint(img, mask, bg, depth, 1.0, seed=7)
    b = get_inpainter("patch").inpaint(img.copy(), mask.copy(), bg.copy(), depth.copy(), 1.0, seed=7)
    c = patch.inpaint(img, mask, bg, depth, 1.0, seed=8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_empty_mask_returns_copy_and_full_mask_is_error(patch):
    img, _, bg, depth = _scene()
    out = patch.inpaint(img, np.zeros(img.shape[:2], bool), bg, depth, 0.5, 0)
    assert np.array_equal(out, img) and out is not img
    with pytest.raises(CamoError, match="whole image"):
        patch.inpaint(img, np.ones(img.shape[:2], bool), bg, depth, 0.5, 0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(strength=0.0), "strength"),
        (dict(strength=1.5), "strength"),
        (dict(strength="lots"), "strength"),
        (dict(seed=-1), "seed"),
        (dict(depth=np.zeros((5, 5), np.float32)), "depth"),
        (dict(background_srgb=np.zeros((10, 10, 3), np.float32)), "background_srgb"),
        (dict(mask=np.zeros((3, 3), bool)), "mask"),
        (dict(image_srgb=np.zeros((96, 112), np.float32)), "image_srgb"),
    ],
)
def test_bad_inputs_are_one_line_camoerrors(patch, kwargs, match):
    img, mask, bg, depth = _scene()
    args = dict(image_srgb=img, mask=mask, background_srgb=bg, depth=depth, strength=1.0, seed=0)
    args.update(kwargs)
    with pytest.raises(CamoError, match=match) as ei:
        patch.inpaint(**args)
    assert "\n" not in str(ei.value)


# ----------------------------------------------------------------------------- texture synthesis


@pytest.mark.parametrize("name, tint", [("grass", (0.6, 1.0, 0.5)), ("gravel", (1.0, 0.9, 0.8))])
def test_fill_has_texture_not_blur(patch, name, tint):
    img, mask, bg, depth = grey_square_scene(name, tint, 108, 148)
    t0 = time.perf_counter()
    out = patch.inpaint(img, mask, bg, depth, strength=1.0, seed=0)
    seconds = time.perf_counter() - t0
    ring = ~mask
    lap_ratio = laplacian_var(out, mask) / laplacian_var(bg, ring)
    std_ratio = local_std(out, mask) / local_std(bg, ring)
    assert 0.5 < lap_ratio < 2.0, lap_ratio
    assert 0.7 < std_ratio < 1.4, std_ratio
    # the colour statistics of the fill match the background
    assert np.abs(out[mask].mean(0) - bg[ring].mean(0)).max() < 0.05
    # the check is discriminative: a smooth (Telea) fill fails it by far
    smooth = np.where(mask[..., None], telea_fill(img, mask), img)
    assert laplacian_var(smooth, mask) / laplacian_var(bg, ring) < 0.2
    assert local_std(smooth, mask) / local_std(bg, ring) < 0.5
    assert seconds < 20.0  # ~1 s on 2 cores; generous for a loaded CI machine


def test_fill_never_reads_background_inside_mask(patch):
    img, mask, bg, depth = grey_square_scene("grass", (0.6, 1.0, 0.5), 40, 80, size=128)
    a = patch.inpaint(img, mask, bg, depth, 1.0, 0)
    bg2 = bg.copy()
    bg2[mask] = 1.0  # what is behind the object must not matter
    b = patch.inpaint(img, mask, bg2, depth, 1.0, 0)
    assert np.array_equal(a, b)


def _two_depth(near_px):
    near = texture("grass", (0.5, 1.0, 0.4))
    far = texture("gravel", (1.0, 0.75, 0.6), off=100)
    bg = np.where(near_px[..., None], near, far).astype(np.float32)
    depth = np.where(near_px, 2.0, 40.0).astype(np.float32)
    return near, far, bg, depth


def _classify(out, region, near_mean, far_mean):
    """Fraction of region pixels (5x5 mean colour) nearer to the near-texture mean than to the far one."""
    sm = cv2.blur(out, (5, 5))[region]
    return float((np.linalg.norm(sm - near_mean, axis=1) < np.linalg.norm(sm - far_mean, axis=1)).mean())


def test_fill_copies_from_matching_depth_band(patch):
    """Near textured ground (grass, depth 2) below far gravel (depth 40); the hole straddles the depth edge."""
    near_px = np.zeros((H, W), bool)
    near_px[150:] = True
    near, far, bg, depth = _two_depth(near_px)
    mask = square_mask(110, 180, 100, 170)
    img = bg.copy()
    img[mask] = 0.5
    out = patch.inpaint(img, mask, bg, depth, 1.0, 0)
    mn, mf = near[~mask & near_px].mean(0), far[~mask & ~near_px].mean(0)
    fill_near = out[mask & near_px].mean(0)
    fill_far = out[mask & ~near_px].mean(0)
    assert np.linalg.norm(fill_near - mn) < 0.25 * np.linalg.norm(fill_near - mf)
    assert np.linalg.norm(fill_far - mf) < 0.25 * np.linalg.norm(fill_far - mn)
    assert _classify(out, mask & near_px, mn, mf) > 0.9
    assert _classify(out, mask & ~near_px, mn, mf) < 0.2


def test_depth_alone_decides_the_texture():
    """A near surface hidden entirely behind the object, in the middle of far gravel; near grass is only
    visible in a strip at the bottom. Only the depth map says the hidden part is near: it must get grass."""
    near_px = np.zeros((H, W), bool)
    near_px[210:] = True
    near_px[140:170, 110:160] = True  # inside the hole
    near, far, bg, depth = _two_depth(near_px)
    mask = square_mask(120, 190, 95, 175)
    img = bg.copy()
    img[mask] = 0.5
    mn, mf = near[~mask & near_px].mean(0), far[~mask & ~near_px].mean(0)
    island = mask & near_px
    out = get_inpainter("patch").inpaint(img, mask, bg, depth, 1.0, 0)
    assert _classify(out, island, mn, mf) > 0.9
    assert _classify(out, mask & ~near_px, mn, mf) < 0.2
    # texture is kept in the island too
    assert local_std(out, island) > 0.6 * local_std(near, ~mask & near_px)
    # without the depth term the island is filled with the surrounding gravel
    blind = get_inpainter("patch", depth_weight=0.0).inpaint(img, mask, bg, depth, 1.0, 0)
    assert _classify(blind, island, mn, mf) < 0.3


def test_sky_and_smooth_gradient(patch):
    """Sky (depth 0) with a smooth gradient above noisy ground: the sky part is filled smoothly and correctly."""
    h = w = 128
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    sky = np.stack([0.3 + 0.4 * yy / h, 0.5 + 0.3 * yy / h, 0.9 - 0.1 * xx / w], -1)
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 1.5)
    ground = np.clip(0.35 + 0.15 * noise[..., None] * np.array([1.0, 0.8, 0.5]), 0, 1)
    gpx = yy >= 80
    bg = np.where(gpx[..., None], ground, sky).astype(np.float32)
    depth = np.where(gpx, 200.0 / np.maximum(yy - 70.0, 1.0), 0.0).astype(np.float32)
    mask = square_mask(50, 100, 40, 90, (h, w))
    img = bg.copy()
    img[mask] = [0.9, 0.1, 0.1]
    out = patch.inpaint(img, mask, bg, depth, 1.0, 0)
    s = mask & ~gpx
    assert np.abs(out[s] - bg[s]).mean() < 0.02  # the gradient is continued
    g = mask & gpx
    ratio = out[g].std(0) / bg[~mask & gpx].std(0)
    assert np.all((ratio > 0.6) & (ratio < 1.6))  # the ground keeps its grain


def test_log_depth_puts_sky_beyond_everything():
    d = np.array([[1.0, 10.0, 0.0]], np.float32)
    z = log_depth(d, 8.0)
    assert z[0, 0] == 0.0 and np.isclose(z[0, 1], np.log(10.0)) and np.isclose(z[0, 2], np.log(80.0))
    assert np.all(log_depth(np.zeros((2, 2), np.float32), 8.0) == 0.0)


# ----------------------------------------------------------------------------- strength (t_start)


def test_strength_maps_like_t_start(patch):
    bg = texture("grass", (0.6, 1.0, 0.5), size=128)
    mask = square_mask(44, 84, 44, 84, (128, 128))
    depth = np.full((128, 128), 5.0, np.float32)
    stage1 = bg.copy()
    stage1[mask] = np.clip(bg[mask] * 0.5 + 0.3, 0, 1)  # a Stage-1 render: right layout, washed-out colours
    dist = []
    for s in (0.05, 0.3, 0.6, 1.0):
        out = patch.inpaint(stage1, mask, bg, depth, s, 0)
        dist.append(float(np.abs(out[mask] - stage1[mask]).mean()))
    assert dist[0] < 0.01  # small t_start: stays at the Stage-1 render
    assert all(a < b for a, b in zip(dist, dist[1:]))  # more noise, further from it
    # strength 1 ignores the Stage-1 render inside the mask entirely
    other = stage1.copy()
    other[mask] = 0.0
    assert np.array_equal(patch.inpaint(stage1, mask, bg, depth, 1.0, 0), patch.inpaint(other, mask, bg, depth, 1.0, 0))


def test_tiny_image_falls_back_to_smooth_fill(patch):
    rng = np.random.default_rng(1)
    img = rng.random((12, 12, 3), dtype=np.float32)
    mask = square_mask(3, 9, 3, 9, (12, 12))
    out = patch.inpaint(img, mask, img, np.ones((12, 12), np.float32), 1.0, 0)
    assert np.array_equal(out[~mask], img[~mask]) and np.isfinite(out).all()


def test_renoise_mix_limits_and_scales():
    from optimizer.optimise.inpainting.patch import renoise_mix

    rng = np.random.default_rng(0)
    img = rng.random((40, 40, 3), dtype=np.float32)
    syn = rng.random((40, 40, 3), dtype=np.float32)
    assert np.array_equal(renoise_mix(img, syn, 1.0, 2.0), syn)
    np.testing.assert_allclose(renoise_mix(img, syn, 1e-3, 2.0), 0.999 * img + 0.001 * syn, atol=1e-6)
    # constant images: no detail, the result is the plain blend of the levels
    a, b = np.full((20, 20, 3), 0.2, np.float32), np.full((20, 20, 3), 0.6, np.float32)
    np.testing.assert_allclose(renoise_mix(a, b, 0.5, 2.0), 0.4, atol=1e-6)
    # a 1-px defect in the image at strength 0.5: almost gone (the linear blend keeps half of it)
    spot = a.copy()
    spot[10, 10] = 1.0
    out = renoise_mix(spot, b, 0.5, 2.0)
    assert out[10, 10, 0] - 0.4 < 0.05 < 0.5 * (1.0 - 0.2)


def test_sparkle_in_the_stage1_render_is_replaced_by_texture(patch):
    """Stage 2's point (paper Fig. 14): isolated Stage-1 defects do not survive into the pseudo ground truth."""
    bg = texture("grass", (0.6, 1.0, 0.5), size=96)
    mask = square_mask(30, 66, 30, 66, (96, 96))
    stage1 = bg.copy()
    spots = [(40, 40), (50, 57), (60, 35)]
    for y, x in spots:
        stage1[y, x] = 1.0  # specular sparkles on an otherwise perfect Stage-1 result
    out = patch.inpaint(stage1, mask, bg, np.full((96, 96), 5.0, np.float32), 0.5, 0)
    hi = np.quantile(bg.mean(axis=-1), 0.99)
    for y, x in spots:
        assert out[y, x].mean() < hi, (y, x, out[y, x])  # no brighter than the brightest 1 % of the grass
