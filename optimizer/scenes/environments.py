"""Environments: everything in a scene except the object, the cameras and the integrator.

An :class:`Environment` builds *fresh* Mitsuba scene-element dicts on every
call (a dict holding an ``mi.TensorXf`` is consumed by ``mi.load_dict``) and
describes itself to the effect planner (which emitters exist, whether there is
geometry near the object that causes interreflection or occlusion).

Built-in environments (Z-up, ground at z = 0, the object near the origin):

========== =====================================================================
meadow     grass ground under a sun-and-sky model (``sunsky``): hard shadows
gravel     gravel yard under a low, hazy sun (long shadows)
split      bright marble / dark asphalt split under the sun (the paper's hard case)
room       indoor room, brick walls, plank floor, ceiling area light
occluded   gravel yard with a wall and a crate that hide the object from some views
panorama   lit only by an HDR equirect panorama (generated offline from a built-in
           plaza scene and cached), with the panorama projected onto the ground
========== =====================================================================

User environments: a Mitsuba XML scene (its shapes and emitters are used, its
sensors and integrator ignored) or an HDR panorama (EXR/HDR) with a ground
plane onto which the panorama is projected from its capture height.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

from optimizer.scenes import textures
from camo_base.errors import CamoError
from camo_base.imaging import REC709_LUMA


@dataclasses.dataclass
class Environment:
    name: str
    description: str
    build: Callable[[], dict[str, Any]]  # fresh scene elements: {id: plugin dict or object}
    emitters: tuple[str, ...]  # kinds present: "sun", "sky", "envmap", "area"
    nearby_geometry: bool = False  # walls/occluders close to the object (interreflection, occlusion)
    occluders: bool = False  # geometry that can hide the object from some views
    compact_envmap_light: bool = False  # the envmap holds a sun-like spot (see :func:`has_compact_spot`)


def _T():
    import mitsuba as mi

    return mi.ScalarTransform4f()


def _z_up():
    """Mitsuba's environment emitters are Y-up in their local frame; rotate them to Z-up."""
    return _T().rotate([1, 0, 0], 90)


def sun_direction(elevation_deg: float, azimuth_deg: float) -> list[float]:
    """World-space unit vector pointing *towards* the sun (Z-up; azimuth from +x towards +y)."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    return [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]


def sun_of(env: "Environment") -> np.ndarray | None:
    """The world unit vector towards ``env``'s sun: a ``sunsky`` or ``sun`` emitter's ``sun_direction``, or the reverse
    of a ``directional`` emitter's ``direction`` (the first found in ``env.build()``); None when it has none of those (an
    envmap's baked sun, an area light or a loaded Mitsuba scene's emitters are not read)."""
    for el in env.build().values():
        if not isinstance(el, dict):
            continue
        kind = el.get("type")
        if kind in ("sunsky", "sun") and "sun_direction" in el:
            d = np.asarray(el["sun_direction"], np.float64)
        elif kind == "directional" and "direction" in el:
            d = -np.asarray(el["direction"], np.float64)
        else:
            continue
        n = float(np.linalg.norm(d))
        if n > 0 and np.isfinite(n):
            return d / n
    return None


def sunsky(elevation_deg: float = 40.0, azimuth_deg: float = 30.0, turbidity: float = 3.0, scale: float = 1.0) -> dict:
    """Mitsuba's ``sunsky`` (Hosek-Wilkie sky + sun). Its local frame is already Z-up and
    ``sun_direction`` is a world-space vector towards the sun, so no ``to_world`` is needed."""
    return {
        "type": "sunsky",
        "sun_direction": sun_direction(elevation_deg, azimuth_deg),
        "turbidity": turbidity,
        "sun_scale": scale,
        "sky_scale": scale,
    }


def textured_diffuse(tex: np.ndarray, tiles: float = 1.0) -> dict:
    import mitsuba as mi

    return {
        "type": "diffuse",
        "reflectance": {
            "type": "bitmap",
            "data": mi.TensorXf(np.ascontiguousarray(tex, dtype=np.float32)),
            "raw": True,
            "to_uv": mi.ScalarTransform3f().scale([tiles, tiles]),
        },
    }


def plain_diffuse(rgb) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}}


def ground_rect(tex: np.ndarray, half: float = 200.0, tile: float = 2.5, centre=(0.0, 0.0),
                half_y: float | None = None) -> dict:
    """A textured ground rectangle on z = 0; ``tile`` is the size of one texture repeat in scene units.

    The default half-size of 200 units reaches (within 1 degree) the horizon of
    a camera 4 units away, so no black band below the horizon shows.
    """
    hy = half if half_y is None else half_y
    return {
        "type": "rectangle",
        "to_world": _T().translate([centre[0], centre[1], 0.0]).scale([half, hy, 1.0]),
        "bsdf": textured_diffuse(tex, 2.0 * half / tile) if half == hy else _aniso_tiled(tex, half, hy, tile),
    }


def _aniso_tiled(tex: np.ndarray, hx: float, hy: float, tile: float) -> dict:
    import mitsuba as mi

    d = textured_diffuse(tex)
    d["reflectance"]["to_uv"] = mi.ScalarTransform3f().scale([2.0 * hx / tile, 2.0 * hy / tile])
    return d


def box(centre, half_extents, bsdf: dict) -> dict:
    return {"type": "cube", "to_world": _T().translate(list(centre)).scale(list(half_extents)), "bsdf": bsdf}


# --- built-in environments ---------------------------------------------------


def _meadow() -> dict:
    return {"sky": sunsky(42.0, 35.0, turbidity=3.0), "ground": ground_rect(textures.texture("grass"), tile=2.5)}


def _gravel() -> dict:
    return {"sky": sunsky(22.0, -60.0, turbidity=5.0), "ground": ground_rect(textures.texture("gravel"), tile=2.0)}


def _split() -> dict:
    # Boundary along x = 0 through the object; the sun comes from the asphalt side.
    return {
        "sky": sunsky(38.0, 160.0, turbidity=3.0),
        "marble": ground_rect(textures.texture("marble"), 100.0, 4.0, centre=(-100.0, 0.0), half_y=200.0),
        "asphalt": ground_rect(textures.texture("asphalt"), 100.0, 2.0, centre=(100.0, 0.0), half_y=200.0),
    }


def _room() -> dict:
    half, height = 6.5, 4.0
    walls = textures.texture("brick")
    out: dict[str, Any] = {"floor": ground_rect(textures.texture("planks"), half, tile=2.2)}
    T = _T()
    # Rectangles span [-1, 1]^2 in their local xy plane and face +z; each wall is rotated to face the room's
    # inside. The scale is applied before the rotation, so it is given in the rectangle's own axes: a turn about
    # x keeps local x horizontal (width `half`) and makes local y vertical (`height / 2`); a turn about y makes
    # local x vertical and keeps local y horizontal (tests/test_render.py checks that the room is closed).
    for name, rot_axis, angle, pos, size in (
        ("wall_n", [1, 0, 0], 90, [0, half, height / 2], [half, height / 2, 1.0]),
        ("wall_s", [1, 0, 0], -90, [0, -half, height / 2], [half, height / 2, 1.0]),
        ("wall_e", [0, 1, 0], -90, [half, 0, height / 2], [height / 2, half, 1.0]),
        ("wall_w", [0, 1, 0], 90, [-half, 0, height / 2], [height / 2, half, 1.0]),
    ):
        out[name] = {
            "type": "rectangle",
            "to_world": T.translate(pos).rotate(rot_axis, angle).scale(size),
            "bsdf": textured_diffuse(walls, 4.0),
        }
    out["ceiling"] = {
        "type": "rectangle",
        "to_world": T.translate([0, 0, height]).rotate([1, 0, 0], 180).scale([half, half, 1.0]),
        "bsdf": plain_diffuse([0.8, 0.8, 0.78]),
    }
    out["lamp"] = {
        "type": "rectangle",
        "to_world": T.translate([1.0, -0.8, height - 0.01]).rotate([1, 0, 0], 180).scale([0.9, 0.9, 1.0]),
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [14.0, 12.5, 10.5]}},
        "bsdf": plain_diffuse([0.0, 0.0, 0.0]),
    }
    out["cabinet"] = box([-3.5, 3.0, 0.6], [1.2, 0.6, 0.6], plain_diffuse([0.35, 0.25, 0.18]))
    return out


def _occluded() -> dict:
    out = _gravel()
    out["sky"] = sunsky(45.0, 120.0, turbidity=3.0)
    # A low wall hides the lower part of the object from the +x views; a crate blocks some -y views.
    out["wall"] = box([1.0, 0.0, 0.2], [0.06, 0.9, 0.2], textured_diffuse(textures.texture("brick"), 1.0))
    out["crate"] = box([-0.75, -1.2, 0.25], [0.25, 0.25, 0.25], plain_diffuse([0.45, 0.33, 0.2]))
    return out


def _plaza() -> dict:
    """The scene the built-in panorama is captured in: gravel plaza, brick walls, pillars, sun."""
    out = _gravel()
    out["sky"] = sunsky(35.0, 70.0, turbidity=3.0)
    brick = textured_diffuse(textures.texture("brick"), 2.0)
    out["wall_a"] = box([0.0, 9.0, 1.5], [6.0, 0.3, 1.5], brick)
    out["wall_b"] = box([-8.0, -2.0, 1.0], [0.3, 5.0, 1.0], textured_diffuse(textures.texture("brick"), 2.0))
    for i, (x, y) in enumerate(((6.0, -5.0), (7.5, 2.0), (-3.0, -7.5))):
        out[f"pillar_{i}"] = {
            "type": "cylinder",
            "p0": [x, y, 0.0],
            "p1": [x, y, 3.0],
            "radius": 0.4,
            "bsdf": plain_diffuse([0.6, 0.58, 0.52]),
        }
    out["bench"] = box([3.0, 5.5, 0.25], [1.2, 0.3, 0.25], plain_diffuse([0.3, 0.2, 0.12]))
    return out


def cache_dir() -> Path:
    return Path(os.environ.get("CAMO_CACHE", Path.home() / ".cache" / "camo"))


def builtin_panorama(width: int = 1024, spp: int = 16) -> Path:
    """The built-in HDR panorama (EXR), rendered once from the plaza scene and cached."""
    from camo_base.imaging import save_exr
    from optimizer.scenes.panorama import render_equirect

    path = cache_dir() / "panoramas" / f"plaza_{width}x{width // 2}_{spp}spp_v1.exr"
    if not path.is_file():
        pano = render_equirect(_plaza(), origin=(0.0, 0.0, 1.6), width=width, spp=spp, seed=7)
        save_exr(path, pano)
    return path


#: An envmap texel this many times brighter than the map's median luminance is a compact light (a sun baked into
#: an outdoor HDR: ~3e4 in the built-in panorama); it mirrors as glints like the ``sunsky`` sun does.
COMPACT_SPOT_RATIO = 1000.0


def has_compact_spot(pano: np.ndarray) -> bool:
    """Whether an ``(H, W, 3)`` linear panorama holds a sun-like spot: peak luminance > ``COMPACT_SPOT_RATIO`` x median."""
    y = pano[..., :3] @ REC709_LUMA
    return bool(y.max() > COMPACT_SPOT_RATIO * max(float(np.median(y)), 1e-12))


def panorama_environment(path: str | Path, capture_height: float = 1.6, ground: bool = True,
                         ground_extent: float = 30.0, rotation_deg: float = 0.0, name: str = "panorama") -> Environment:
    """Lighting from an equirect HDR panorama; optional ground with the panorama projected on it."""
    from camo_base.imaging import load_hdr_image
    from optimizer.scenes.panorama import project_to_ground

    pano = load_hdr_image(path)
    if pano.ndim != 3 or pano.shape[1] != 2 * pano.shape[0]:
        raise CamoError(f"panorama {path} must be an equirect image with width = 2 x height, got {pano.shape[1]}x{pano.shape[0]}")
    if (pano < 0).any():
        raise CamoError(f"panorama {path} has negative radiance")
    ground_tex = project_to_ground(pano, capture_height, ground_extent, 1024, rotation_deg) if ground else None

    def build() -> dict:
        import mitsuba as mi

        out: dict[str, Any] = {
            "envmap": {
                "type": "envmap",
                "bitmap": mi.Bitmap(np.ascontiguousarray(pano, dtype=np.float32)),
                "to_world": _T().rotate([0, 0, 1], rotation_deg) @ _z_up(),
            }
        }
        if ground_tex is not None:
            out["ground"] = {
                "type": "rectangle",
                "to_world": _T().scale([ground_extent, ground_extent, 1.0]),
                "bsdf": textured_diffuse(ground_tex, 1.0),
            }
        return out

    return Environment(name, f"HDR panorama {Path(path).name}", build, ("envmap",),
                       compact_envmap_light=has_compact_spot(pano))


def xml_environment(path: str | Path) -> Environment:
    """Shapes and emitters of a Mitsuba XML scene (its sensors and integrator are ignored)."""
    from optimizer.backend import load_file

    try:
        loaded = load_file(path)
    except Exception as exc:
        msg = str(exc).strip().splitlines()
        raise CamoError(f"cannot load Mitsuba scene {path}: {msg[-1] if msg else type(exc).__name__}") from None
    shapes = list(loaded.shapes())
    env_emitters = [e for e in loaded.emitters() if e.get_shape() is None]
    kinds = {"area"} if any(s.emitter() is not None for s in shapes) else set()
    for e in env_emitters:
        cls = e.class_().name().lower() if hasattr(e, "class_") else type(e).__name__.lower()
        kinds.add("envmap" if "env" in cls else "sun" if "sun" in cls else cls)
    if not kinds:
        raise CamoError(f"Mitsuba scene {path} has no emitter: nothing would be lit")
    spot = any(has_compact_spot(m) for m in map(_envmap_data, env_emitters) if m is not None)

    def build() -> dict:
        out: dict[str, Any] = {f"shape_{i}": s for i, s in enumerate(shapes)}
        out.update({f"emitter_{i}": e for i, e in enumerate(env_emitters)})
        return out

    return Environment(Path(path).stem, f"Mitsuba scene {Path(path).name}", build, tuple(sorted(kinds)),
                       nearby_geometry=True, occluders=True, compact_envmap_light=spot)


def _envmap_data(emitter) -> np.ndarray | None:
    """An ``envmap`` emitter's texels ``(H, W, C)`` (linear radiance), or None for other emitters."""
    import mitsuba as mi

    params = mi.traverse(emitter)
    return np.asarray(params["data"]) if "data" in params.keys() else None


ENVIRONMENTS: dict[str, tuple[str, Callable[[], dict], tuple[str, ...], bool, bool]] = {
    # name: (description, build, emitters, nearby_geometry, occluders)
    "meadow": ("grass ground under a sun-and-sky model; hard shadows", _meadow, ("sun", "sky"), False, False),
    "gravel": ("gravel yard under a low, hazy sun; long shadows", _gravel, ("sun", "sky"), False, False),
    "split": ("bright marble / dark asphalt split ground under the sun (hard case)", _split, ("sun", "sky"), False, False),
    "room": ("indoor room: brick walls, plank floor, ceiling area light", _room, ("area",), True, False),
    "occluded": ("gravel yard with a wall and a crate hiding the object from some views", _occluded, ("sun", "sky"), True, True),
    "panorama": ("lit only by an HDR panorama (generated plaza), projected ground", None, ("envmap",), False, False),
}


def get_environment(spec) -> Environment:
    """The :class:`Environment` for a pack's ``[environment]`` section."""
    if spec.builtin:
        desc, build, emitters, nearby, occl = ENVIRONMENTS[spec.builtin]
        if spec.builtin == "panorama":
            # The plaza's nearest walls and pillars stand ~7.5 units from the capture point: a projected
            # ground reaching them would smear them over the floor, so it stops short (beyond it the
            # panorama itself is seen).
            env = panorama_environment(builtin_panorama(), spec.capture_height, True, min(spec.ground_extent, 5.0),
                                       spec.rotation, "panorama")
            env.description = desc
            return env
        return Environment(spec.builtin, desc, build, emitters, nearby, occl)
    if spec.panorama:
        return panorama_environment(spec.panorama, spec.capture_height, spec.ground, spec.ground_extent, spec.rotation,
                                    Path(spec.panorama).stem)
    return xml_environment(spec.xml)

