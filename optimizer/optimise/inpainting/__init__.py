"""Stage-2 inpainting backends behind one interface (see :mod:`optimizer.optimise.inpainting.base`).

``get_inpainter(name, **options)`` with ``name`` in :data:`INPAINTERS`:

* ``"patch"`` (default, offline): depth-aware multi-scale PatchMatch texture
  synthesis, :class:`optimizer.optimise.inpainting.patch.PatchInpainter`.
* ``"diffusers"``: SDXL inpainting + depth ControlNet from local weights,
  :class:`optimizer.optimise.inpainting.diffusers_backend.DiffusersInpainter`.

Importing this package imports neither torch nor diffusers.
"""

from __future__ import annotations

from camo_base.errors import CamoError
from optimizer.optimise.inpainting.base import Inpainter, validate_inputs

INPAINTERS = ("patch", "diffusers")
DEFAULT_INPAINTER = "patch"


def get_inpainter(name: str = DEFAULT_INPAINTER, **options) -> Inpainter:
    """The Stage-2 inpainter called ``name`` (``--stage2-backend``), built with ``options``.

    Options whose value is ``None`` are dropped, so a CLI can always pass
    ``sdxl_path=args.sdxl_path, controlnet_path=args.controlnet_path`` (they
    only matter to ``"diffusers"``; given a value, ``"patch"`` rejects them).
    Unknown names or options raise :class:`CamoError`. For ``"diffusers"`` the
    weights are loaded here, so a missing or broken folder fails early.
    """
    key = str(name).strip().lower()
    options = {k: v for k, v in options.items() if v is not None}
    if key == "patch":
        from optimizer.optimise.inpainting.patch import PatchInpainter as cls
    elif key == "diffusers":
        from optimizer.optimise.inpainting.diffusers_backend import DiffusersInpainter as cls
    else:
        raise CamoError(f"unknown Stage-2 inpainting backend {name!r}; choose one of: {', '.join(INPAINTERS)}")
    try:
        return cls(**options)
    except TypeError as exc:
        raise CamoError(f"{key} inpainter: bad option ({' '.join(str(exc).split())})") from None


def diffusers_status(sdxl_path=None, controlnet_path=None, *, load: bool = False) -> str:
    """One line for ``camo doctor``: can the ``diffusers`` backend load? (see diffusers_backend)."""
    from optimizer.optimise.inpainting.diffusers_backend import diffusers_status as _status

    return _status(sdxl_path, controlnet_path, load=load)


__all__ = ["CamoError", "DEFAULT_INPAINTER", "INPAINTERS", "Inpainter", "diffusers_status", "get_inpainter", "validate_inputs"]
