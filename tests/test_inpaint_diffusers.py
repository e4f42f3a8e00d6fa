"""Stage-2 inpainting, ``diffusers`` backend, through the production loading path.

A tiny randomly initialised SDXL inpainting pipeline and depth ControlNet of
the real classes are built and saved to a temporary folder (no download; the
CLIP vocabulary is written locally), then loaded by ``get_inpainter``.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from camo_base.errors import CamoError  # noqa: E402
from optimizer.optimise.inpaint import diffusers_status, get_inpainter  # noqa: E402
from optimizer.optimise.inpainting.diffusers_backend import DiffusersInpainter, depth_control_image, pipeline_size


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from optimizer.optimise.inpainting._tiny import build_tiny_sdxl_controlnet_inpaint

    root = tmp_path_factory.mktemp("tiny_sdxl")
    sdxl, cn = build_tiny_sdxl_controlnet_inpaint(root)
    return root, sdxl, cn


@pytest.fixture(scope="module")
def inpainter(tiny):
    _, sdxl, cn = tiny
    return get_inpainter("diffusers", sdxl_path=str(sdxl), controlnet_path=str(cn), resolution=64, num_inference_steps=2)


def _inputs(h=64, w=64, seed=0):
    rng = np.random.default_rng(seed)
    img = rng.random((h, w, 3), dtype=np.float32)
    bg = img.copy()
    mask = np.zeros((h, w), bool)
    mask[h // 4 : h // 2 + 8, w // 4 : w // 2 + 10] = True
    img[mask] = 0.5
    depth = np.linspace(1.0, 20.0, h * w, dtype=np.float32).reshape(h, w)
    depth[:4] = 0.0  # sky
    return img, mask, bg, depth


def test_loads_through_production_path(inpainter, tiny):
    assert isinstance(inpainter, DiffusersInpainter)
    assert type(inpainter.pipe).__name__ == "StableDiffusionXLControlNetInpaintPipeline"
    assert inpainter.device == "cpu"
    assert inpainter.prompt == "background"


def test_inpaint_shape_finite_and_unmasked_bit_exact(inpainter):
    img, mask, bg, depth = _inputs()
    img[0, 0, 0] = np.nan  # outside the mask: untouched
    out = inpainter.inpaint(img, mask, bg, depth, strength=0.8, seed=0)
    assert out.shape == (64, 64, 3) and out.dtype == np.float32
    assert np.array_equal(out[~mask].view(np.uint32), img[~mask].view(np.uint32))
    assert np.isfinite(out[mask]).all() and 0.0 <= out[mask].min() and out[mask].max() <= 1.0
    assert np.abs(out[mask] - img[mask]).mean() > 1e-3  # the pipeline changed the masked pixels


def test_deterministic_for_fixed_seed(inpainter):
    img, mask, bg, depth = _inputs()
    a = inpainter.inpaint(img, mask, bg, depth, 0.8, seed=5)
    b = inpainter.inpaint(img, mask, bg, depth, 0.8, seed=5)
    c = inpainter.inpaint(img, mask, bg, depth, 0.8, seed=6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_odd_size_is_resized_to_pipeline_and_back(inpainter):
    img, mask, bg, depth = _inputs(50, 70, seed=2)
    # small strength with 2 steps would leave no denoising step; the backend raises the step count
    out = inpainter.inpaint(img, mask, bg, depth, strength=0.1, seed=1)
    assert out.shape == (50, 70, 3)
    assert np.array_equal(out[~mask], img[~mask]) and np.isfinite(out).all()


def test_pipeline_size_and_depth_control_image():
    assert pipeline_size(64, 64, 64) == (64, 64)
    assert pipeline_size(600, 800, 1024) == (768, 1024)
    assert pipeline_size(50, 70, 64) == (48, 64)
    assert pipeline_size(3, 1000, 64) == (8, 64)
    d = np.array([[1.0, 2.0, 4.0, 0.0]], np.float32)
    c = depth_control_image(d)
    assert c.shape == (1, 4, 3) and np.array_equal(c[..., 0], c[..., 2])
    np.testing.assert_allclose(c[0, :, 0], [1.0, 1.0 / 3.0, 0.0, 0.0], atol=1e-6)  # near bright, sky black
    assert np.all(depth_control_image(np.full((2, 2), 3.0, np.float32)) == 1.0)


def test_mask_resize_is_conservative():
    from optimizer.optimise.inpainting.diffusers_backend import _resize_mask

    m = np.zeros((50, 70), bool)
    m[17, 33] = True  # one object pixel must never vanish
    small = _resize_mask(m, (24, 32))
    big = _resize_mask(m, (100, 140))
    assert small.sum() >= 1 and big.sum() >= 4
    assert big[34:36, 66:68].all()


def _camo_error(**kw) -> str:
    with pytest.raises(CamoError) as ei:
        get_inpainter("diffusers", **kw)
    msg = str(ei.value)
    assert "\n" not in msg and "Traceback" not in msg
    return msg


def test_missing_and_broken_folders_are_one_line_camoerrors(tiny, tmp_path, monkeypatch):
    root, sdxl, cn = tiny
    assert "not found" in _camo_error(sdxl_path=str(tmp_path / "nope"), controlnet_path=str(cn))
    assert "not found" in _camo_error(sdxl_path=str(sdxl), controlnet_path=str(tmp_path / "nope"))
    assert "model_index.json" in _camo_error(sdxl_path=str(tmp_path), controlnet_path=str(cn))
    assert "ControlNet" in _camo_error(sdxl_path=str(sdxl), controlnet_path=str(sdxl))
    broken = tmp_path / "broken"
    shutil.copytree(sdxl, broken)
    (broken / "unet" / "diffusion_pytorch_model.safetensors").write_bytes(b"not a safetensors file")
    assert "cannot load" in _camo_error(sdxl_path=str(broken), controlnet_path=str(cn))
    missing_part = tmp_path / "no_vae"
    shutil.copytree(sdxl, missing_part)
    shutil.rmtree(missing_part / "vae")
    assert "vae" in _camo_error(sdxl_path=str(missing_part), controlnet_path=str(cn))
    # a file instead of a folder
    f = tmp_path / "file.txt"
    f.write_text("x")
    assert "not a folder" in _camo_error(sdxl_path=str(f), controlnet_path=str(cn))
    # nothing given and nothing in the offline cache (a repo id no cache holds, so a real cached SDXL is never loaded)
    import optimizer.optimise.inpainting.diffusers_backend as backend

    monkeypatch.setattr(backend, "DEFAULT_SDXL_REPO", "camo-tests/no-such-sdxl-inpainting")
    msg = _camo_error(sdxl_path=None, controlnet_path=None)
    assert "offline Hugging Face cache" in msg and "--sdxl-path" in msg
    msg = _camo_error(sdxl_path=str(sdxl), controlnet_path="camo-tests/no-such-controlnet")
    assert "offline Hugging Face cache" in msg and "--controlnet-path" in msg


def test_bad_diffusers_option_is_camoerror(tiny):
    _, sdxl, cn = tiny
    assert "option" in _camo_error(sdxl_path=str(sdxl), controlnet_path=str(cn), not_an_option=1)
    assert "dtype" in _camo_error(sdxl_path=str(sdxl), controlnet_path=str(cn), dtype="float7")


def test_diffusers_status(tiny, tmp_path):
    _, sdxl, cn = tiny
    assert diffusers_status(str(sdxl), str(cn)).startswith("ok")
    assert diffusers_status(str(sdxl), str(cn), load=True).startswith("ok (loaded)")
    st = diffusers_status(str(tmp_path / "nope"), str(cn))
    assert st.startswith("unavailable") and "not found" in st and "\n" not in st
    assert diffusers_status(str(sdxl), str(tmp_path)).startswith("unavailable")


def test_depth_conditioning_reaches_the_pipeline(inpainter):
    img, mask, bg, depth = _inputs()
    a = inpainter.inpaint(img, mask, bg, depth, 0.8, seed=0)
    b = inpainter.inpaint(img, mask, bg, depth[::-1].copy() * 3.0, 0.8, seed=0)
    assert not np.array_equal(a[mask], b[mask])  # the ControlNet sees the depth map


def test_plain_4_channel_unet_layout(tmp_path):
    """An SDXL base UNet (4 input channels, inpainting by latent blending) loads and runs too."""
    from optimizer.optimise.inpainting._tiny import build_tiny_sdxl_controlnet_inpaint

    sdxl, cn = build_tiny_sdxl_controlnet_inpaint(tmp_path, unet_in_channels=4)
    inp = get_inpainter("diffusers", sdxl_path=str(sdxl), controlnet_path=str(cn), resolution=64, num_inference_steps=2)
    img, mask, bg, depth = _inputs()
    out = inp.inpaint(img, mask, bg, depth, 0.6, seed=0)
    assert out.shape == img.shape and np.isfinite(out).all()
    assert np.array_equal(out[~mask], img[~mask])
