"""Stage-2 inpainting (paper Sec. III-C, Eq. 12-14): the public entry point.

    from optimizer.optimise.inpaint import get_inpainter
    inp = get_inpainter("patch")                      # or "diffusers", sdxl_path=..., controlnet_path=...
    target = inp.inpaint(image_srgb, mask, background_srgb, depth, strength=0.6, seed=0)

The implementation lives in the package :mod:`optimizer.optimise.inpainting`
(``base`` = interface and contract, ``patch`` = offline depth-aware PatchMatch,
``diffusers_backend`` = SDXL inpainting + depth ControlNet).
"""

from optimizer.optimise.inpainting import DEFAULT_INPAINTER, INPAINTERS, Inpainter, diffusers_status, get_inpainter

__all__ = ["DEFAULT_INPAINTER", "INPAINTERS", "Inpainter", "diffusers_status", "get_inpainter"]
