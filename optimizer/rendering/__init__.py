"""Stage 2 of the flow, rendering: Mitsuba scene dicts (:mod:`~optimizer.rendering.scene`), the object's
appearance model (maps and displacement -> BSDF and geometry, :mod:`~optimizer.rendering.appearance`), the
planner that picks integrators and the effects a scene needs, the projective integrators, placement and texture
projection. Imports :mod:`optimizer.scenes`, :mod:`optimizer.backend` and :mod:`camo_base`.

Importing this package registers the projective integrators with :func:`optimizer.backend.init` (they need a
variant, so the backend calls them when it picks one)."""

from optimizer import backend as _backend
from optimizer.rendering import projective as _projective



def _register_integrators(info: _backend.BackendInfo) -> None:
    if "_ad_" in info.variant:
        _projective.register()  # camo_prb_projective / camo_direct_projective (training integrators)


_backend.on_init(_register_integrators)
