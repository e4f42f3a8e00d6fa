"""The BSDF maps of the appearance model: the one registry.

Each :class:`BsdfMap` is one spatially varying parameter of the object's principled BSDF, stored as a texture over
the object's UV atlas: its name (a key of the parameter ``values``, of a scene pack's ``[material]``, of ``camo
optimize --init``, and the file ``maps/<name>.npy`` of a run directory), its channels, the paper's starting value,
the Mitsuba principled-BSDF parameter it drives, the appearance switches it needs to be optimised and its value
when they are off, what a painted baseline gives it, and how the asset formats store it (glTF, MTL). Every part of
the tool that handles maps loops over :data:`MAPS` (the scene pack's :class:`~optimizer.scenes.scenepack.
MaterialSpec`, :func:`optimizer.rendering.appearance.initial_values`, the BSDF dict, the optimiser's parameters,
the run directory's files, the GLB/OBJ writers and readers); adding a map is adding a record here
(CONTRIBUTING.md, "Adding a BSDF map").

    >>> list(MAPS)
    ['albedo', 'metallic', 'roughness', 'transmittance']
    >>> MAPS["roughness"].rendered(0.0)
    0.035
"""

from __future__ import annotations

import dataclasses
from typing import Any

#: Roughness maps in [0, 1] render with ``r_min + (1 - r_min) r``: Mitsuba clamps the GGX alpha = r^2 at 1e-3
#: (r ~ 0.032), below which the gradient is zero, and r = 0 yields unstable (NaN-prone) near-delta lobes. The
#: affine map keeps the gradient alive everywhere and makes the paper's initial roughness 0 safe.
ROUGHNESS_MIN = 0.035

#: Smallest albedo value a channel may take. Mitsuba's principled BSDF tints its specular transmission by
#: ``sqrt(base_color)``, whose slope is infinite at 0: with ``spec_trans > 0`` a channel at exactly 0 gets an
#: infinite (or NaN) gradient. The sanitiser zeroes it, so such a texel could never leave 0, and the NaN reached
#: the pose's gradient through the shared vertex graph (one step in two lost its rotation update on meadow; the
#: warm start clips 13 % of meadow's seen texels at 0). At 1e-3 the slope is ~16 and the colour is black in 8 bit.
ALBEDO_MIN = 1e-3


@dataclasses.dataclass(frozen=True)
class GltfSlot:
    """Where glTF 2.0 keeps a map: a texture of ``pbrMetallicRoughness`` (``extension`` "") or of a material
    extension, the image channel it sits in (``channel``; None: RGB colour), the factor key and the ``name`` of the
    image camo writes. Maps sharing a texture share one image (metallic and roughness: glTF's metallicRoughness)."""

    texture: str
    channel: int | None
    image: str
    extension: str = ""
    factor: str = ""
    default: float = 1.0  # the factor when a file does not give it (glTF's default for that factor)


@dataclasses.dataclass(frozen=True)
class BsdfMap:
    """One BSDF map (module doc).

    ``rendered_offset``: the map value ``v`` renders as ``offset + (1 - offset) v`` (roughness: the safe minimum);
    ``low``: the smallest value the optimiser keeps (albedo: :data:`ALBEDO_MIN`); ``switches``: the appearance
    switches (:class:`optimizer.rendering.appearance.AppearanceConfig`) that must all be on for the map to be
    optimised, else it is ``off``; ``painted``: its value on a painted baseline's object (None: the painting)."""

    name: str
    channels: int
    initial: float  # the paper's starting value (a grey for a colour map)
    principled: str  # the Mitsuba principled-BSDF parameter
    help: str
    switches: tuple[str, ...] = ()
    off: float = 0.0
    painted: float | None = 0.0
    low: float = 0.0
    rendered_offset: float = 0.0
    gltf: GltfSlot | None = None
    mtl: str = ""  # MTL key of the scalar (and map_<key> of its texture); "" for the colour (Kd / map_Kd)
    mtl_default: float = 0.0  # its value when an MTL file does not give it
    # the value a run directory or asset without this map renders with (the renderer's default): set it for a map
    # added after run directories were written (theirs lack maps/<name>.npy); None: the file is required
    absent: float | None = None

    @property
    def colour(self) -> bool:
        return self.channels == 3

    def rendered(self, value: Any) -> Any:
        """The value the renderer gets for map value ``value`` (array or scalar)."""
        if not self.rendered_offset:
            return value
        return self.rendered_offset + (1.0 - self.rendered_offset) * value

    def from_rendered(self, rendered: Any) -> Any:
        """The map value of a rendered value, float32 (inverse of :meth:`rendered`; not clipped)."""
        import numpy as np

        r = np.asarray(rendered, dtype=np.float32)
        if not self.rendered_offset:
            return r
        return (r - np.float32(self.rendered_offset)) / np.float32(1.0 - self.rendered_offset)


#: Every BSDF map, in the order of the parameters (albedo first).
MAPS: dict[str, BsdfMap] = {m.name: m for m in (
    BsdfMap("albedo", 3, 0.5, "base_color", "linear base colour", painted=None, low=ALBEDO_MIN,
            gltf=GltfSlot("baseColorTexture", None, "base_color", factor="baseColorFactor")),
    BsdfMap("metallic", 1, 0.0, "metallic", "metalness", switches=("bsdf",), off=0.0,
            gltf=GltfSlot("metallicRoughnessTexture", 2, "metallic_roughness", factor="metallicFactor"), mtl="Pm"),
    BsdfMap("roughness", 1, 0.0, "roughness", "GGX roughness (map value; rendered with the safe minimum "
            f"{ROUGHNESS_MIN})", switches=("bsdf",), off=1.0, painted=1.0, rendered_offset=ROUGHNESS_MIN,
            gltf=GltfSlot("metallicRoughnessTexture", 1, "metallic_roughness", factor="roughnessFactor"), mtl="Pr",
            mtl_default=1.0),
    BsdfMap("transmittance", 1, 0.5, "spec_trans", "specular transmission", switches=("bsdf", "transmittance"),
            off=0.0, gltf=GltfSlot("transmissionTexture", 0, "transmission", "KHR_materials_transmission",
                                   "transmissionFactor", default=0.0), mtl="Ptr"),
)}


def material_values(material: Any) -> dict[str, Any]:
    """``{map: value}`` of a :class:`~optimizer.scenes.scenepack.MaterialSpec` (a constant material)."""
    return {name: getattr(material, name) for name in MAPS}


def gltf_extensions() -> tuple[str, ...]:
    """The glTF material extensions the maps live in (in map order, each once)."""
    return tuple(dict.fromkeys(m.gltf.extension for m in MAPS.values() if m.gltf and m.gltf.extension))


def maps_table() -> str:
    """The Markdown table of the maps (docs/optimizer.md, generated by ``python -m camo.docs``)."""
    rows = ["| map | channels | paper start | principled parameter | optimised when | glTF | MTL |",
            "|---|---|---|---|---|---|---|"]
    for m in MAPS.values():
        when = " and ".join(m.switches) + " on" if m.switches else "always"
        gltf = "-" if m.gltf is None else (f"{m.gltf.extension}." if m.gltf.extension else "") + m.gltf.texture
        rows.append(f"| `{m.name}` | {m.channels} | {m.initial:g} | `{m.principled}` | {when} | `{gltf}` | "
                    f"{m.mtl or 'Kd'} |")
    return "\n".join(rows)
