"""A tiny, randomly initialised SDXL ControlNet inpainting pipeline (test and bench fixture).

It has exactly the component classes of the real ``diffusers`` backend
(``UNet2DConditionModel`` with ``addition_embed_type="text_time"``,
``ControlNetModel``, ``AutoencoderKL``, ``CLIPTextModel`` +
``CLIPTextModelWithProjection``, two ``CLIPTokenizer``) but a few hundred
thousand random weights, so the production loading and inference code path
can be exercised on a CPU in seconds. Nothing is downloaded: the CLIP BPE
vocabulary (``vocab.json``/``merges.txt``) is written here from the byte
alphabet.

:func:`build_tiny_sdxl_controlnet_inpaint` writes two folders in diffusers
format, ``<root>/sdxl-inpaint`` (a pipeline with ``model_index.json``) and
``<root>/controlnet-depth`` (a ``ControlNetModel``), i.e. what a user passes as
``--sdxl-path`` and ``--controlnet-path``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

# Must match CLIPTextConfig.max_position_embeddings below.
_MAX_LEN = 77


def _bytes_to_unicode() -> dict[int, str]:
    """The GPT-2/CLIP byte -> printable unicode character table."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, [chr(c) for c in cs]))


def write_tiny_clip_vocab(folder: str | os.PathLike) -> tuple[Path, Path]:
    """Write a minimal CLIP BPE ``vocab.json`` + ``merges.txt`` (byte alphabet, a few merges)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    chars = list(_bytes_to_unicode().values())
    tokens = chars + [c + "</w>" for c in chars]
    merges = ["b a", "ba c", "bac k", "g r", "gr o", "gro u", "grou n", "groun d</w>", "back groun", "backgroun d</w>"]
    for m in merges:
        tokens.append(m.replace(" ", ""))
    tokens += ["<|startoftext|>", "<|endoftext|>"]
    vocab = {}
    for t in tokens:
        vocab.setdefault(t, len(vocab))
    vocab_path = folder / "vocab.json"
    merges_path = folder / "merges.txt"
    vocab_path.write_text(json.dumps(vocab), encoding="utf-8")
    merges_path.write_text("#version: 0.2\n" + "\n".join(merges) + "\n", encoding="utf-8")
    return vocab_path, merges_path


def build_tiny_sdxl_controlnet_inpaint(root: str | os.PathLike, *, seed: int = 0, unet_in_channels: int = 9) -> tuple[Path, Path]:
    """Build, randomly initialise and ``save_pretrained`` a tiny pipeline; return ``(sdxl_path, controlnet_path)``.

    ``unet_in_channels=9`` mirrors real SDXL inpainting checkpoints (latents +
    mask + masked-image latents); ``4`` mirrors a plain SDXL UNet used for
    inpainting by latent blending. Both are supported by the pipeline.
    """
    import torch
    from diffusers import (
        AutoencoderKL,
        ControlNetModel,
        EulerDiscreteScheduler,
        StableDiffusionXLInpaintPipeline,
        UNet2DConditionModel,
    )
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection, CLIPTokenizer

    root = Path(root)
    torch.manual_seed(seed)
    common = dict(
        block_out_channels=(16, 32),
        layers_per_block=1,
        down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
        attention_head_dim=(2, 4),
        use_linear_projection=True,
        addition_embed_type="text_time",
        addition_time_embed_dim=8,
        transformer_layers_per_block=(1, 1),
        projection_class_embeddings_input_dim=6 * 8 + 32,  # 6 add_time_ids * 8 + text_encoder_2 projection
        cross_attention_dim=64,  # hidden sizes of text_encoder (32) + text_encoder_2 (32) concatenated
        norm_num_groups=8,
    )
    unet = UNet2DConditionModel(
        sample_size=16,
        in_channels=unet_in_channels,
        out_channels=4,
        up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"),
        **common,
    )
    controlnet = ControlNetModel(in_channels=4, conditioning_embedding_out_channels=(8, 16), **common)
    # A fresh ControlNet has zero-initialised output ("zero") convolutions, i.e. no effect at all;
    # randomise them so that the depth conditioning visibly reaches the UNet, as in a trained one.
    with torch.no_grad():
        for name, param in controlnet.named_parameters():
            if name.startswith(("controlnet_down_blocks", "controlnet_mid_block", "controlnet_cond_embedding.conv_out")):
                param.normal_(0.0, 0.1)
    vae = AutoencoderKL(
        block_out_channels=(16, 32),
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D", "DownEncoderBlock2D"),
        up_block_types=("UpDecoderBlock2D", "UpDecoderBlock2D"),
        latent_channels=4,
        norm_num_groups=8,
        sample_size=32,
    )
    scheduler = EulerDiscreteScheduler(
        beta_start=0.00085,
        beta_end=0.012,
        steps_offset=1,
        beta_schedule="scaled_linear",
        timestep_spacing="leading",
    )
    vocab_path, merges_path = write_tiny_clip_vocab(root / "_clip_vocab")
    with open(vocab_path, encoding="utf-8") as fh:
        n_vocab = len(json.load(fh))
    text_cfg = CLIPTextConfig(
        bos_token_id=n_vocab - 2,
        eos_token_id=n_vocab - 1,
        pad_token_id=n_vocab - 1,
        hidden_size=32,
        intermediate_size=37,
        layer_norm_eps=1e-05,
        num_attention_heads=4,
        num_hidden_layers=2,
        vocab_size=n_vocab,
        max_position_embeddings=_MAX_LEN,
        hidden_act="gelu",
        projection_dim=32,
    )
    text_encoder = CLIPTextModel(text_cfg)
    text_encoder_2 = CLIPTextModelWithProjection(text_cfg)
    def clip_tokenizer():
        try:  # transformers >= 5
            return CLIPTokenizer(vocab=str(vocab_path), merges=str(merges_path), model_max_length=_MAX_LEN)
        except TypeError:  # transformers 4.x
            return CLIPTokenizer(vocab_file=str(vocab_path), merges_file=str(merges_path), model_max_length=_MAX_LEN)

    tokenizer = clip_tokenizer()
    tokenizer_2 = clip_tokenizer()

    # The real layout: an SDXL *inpainting* pipeline folder (like
    # diffusers/stable-diffusion-xl-1.0-inpainting-0.1, no ControlNet inside) and
    # a separate ControlNet folder (like diffusers/controlnet-depth-sdxl-1.0).
    pipe = StableDiffusionXLInpaintPipeline(
        vae=vae,
        text_encoder=text_encoder,
        text_encoder_2=text_encoder_2,
        tokenizer=tokenizer,
        tokenizer_2=tokenizer_2,
        unet=unet,
        scheduler=scheduler,
        requires_aesthetics_score=False,
        force_zeros_for_empty_prompt=True,
        add_watermarker=False,
    )
    sdxl_path = root / "sdxl-inpaint"
    cn_path = root / "controlnet-depth"
    from optimizer.optimise.inpainting.diffusers_backend import _quiet

    with _quiet():
        pipe.save_pretrained(sdxl_path, safe_serialization=True)
        controlnet.save_pretrained(cn_path, safe_serialization=True)
    return sdxl_path, cn_path
