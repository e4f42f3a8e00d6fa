"""Helpers the ``camo`` commands share (a leaf module: it imports no command module, and none imports
:mod:`camo.cli` back)."""

from __future__ import annotations

from camo_base.errors import CamoError


def _apply_overrides(pack, args):
    """``camo scenes render``'s ``--resolution``, ``--spp`` (the render's own spp: the pack's ``[render] spp``) and
    ``--views`` on a pack (their ranges are the flags' types)."""
    import dataclasses

    if getattr(args, "resolution", None) is not None:
        pack.render = dataclasses.replace(pack.render, resolution=(args.resolution, args.resolution))
    if getattr(args, "spp", None) is not None:
        pack.render = dataclasses.replace(pack.render, spp=args.spp)
    if getattr(args, "views", None) is not None:
        if pack.cameras.mode == "list":
            raise CamoError("--views only applies to orbit cameras")
        pack.cameras = dataclasses.replace(pack.cameras, views=args.views)
    return pack


def load_scene_arg(name: str, args=None):
    """Resolve a SCENE argument (built-in name or pack file) and apply ``camo scenes render``'s overrides."""
    from optimizer.scenes.builtin_scenes import resolve_scene

    pack = resolve_scene(name)
    return _apply_overrides(pack, args) if args is not None else pack
