"""Scene packs: one TOML file describing one camouflage problem.

A pack names the object, the environment, the cameras, the render settings and
the object's initial material. Coordinates are Z-up, in scene units (metres by
convention); the ground is the plane z = 0. Example::

    name = "chair-in-the-yard"

    [object]
    mesh = "chair.obj"          # or: primitive = "chair"
    size = 1.0                  # largest bounding-box side after normalisation (S)
    rotation = [0.0, 0.0, 30.0] # XYZ Euler angles in degrees (R)
    translation = [0.5, -0.2]   # x, y on the ground (T_t); a third value lifts it
    target_vertices = 30000     # remeshing target (paper: ~30k)

    [environment]
    builtin = "meadow"          # or: xml = "room.xml"  or: panorama = "yard.exr"
    # panorama only: capture_height = 1.6, ground = true, ground_extent = 30.0, rotation = 0.0

    [cameras]
    mode = "orbit"              # or "list" with positions = [[x, y, z], ...]
    views = 16
    radius = 4.0
    elevation = 20.0            # degrees above the horizon
    fov = 30.0                  # horizontal field of view, degrees

    [render]
    resolution = 128            # or [width, height]
    spp = 16

    [material]                  # initial values (paper Sec. IV-A)
    albedo = 0.5                # or [r, g, b], linear
    metallic = 0.0
    roughness = 0.0
    transmittance = 0.5
    eta = 1.5

Every problem is reported by :func:`load_pack` as a one-line :class:`CamoError`.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

from camo_base.documents import read_toml
from camo_base.errors import CamoError
from optimizer.scenes.bsdf_maps import MAPS


@dataclasses.dataclass
class ObjectSpec:
    primitive: str | None = None
    mesh: str | None = None  # absolute path once loaded
    size: float = 1.0
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target_vertices: int = 30000


@dataclasses.dataclass
class EnvironmentSpec:
    builtin: str | None = None
    xml: str | None = None
    panorama: str | None = None
    capture_height: float = 1.6
    ground: bool = True
    ground_extent: float = 30.0
    rotation: float = 0.0  # panorama rotation about the up axis, degrees


@dataclasses.dataclass
class CameraSpec:
    mode: str = "orbit"
    views: int = 16
    radius: float = 4.0
    elevation: float = 20.0
    fov: float = 30.0
    azimuth_offset: float = 0.0
    positions: list[tuple[float, float, float]] | None = None
    targets: list[tuple[float, float, float]] | None = None


@dataclasses.dataclass
class RenderSpec:
    resolution: tuple[int, int] = (128, 128)  # width, height
    spp: int = 16


#: ``[material]``: the object's initial material, one field per BSDF map (:data:`optimizer.scenes.bsdf_maps.MAPS`,
#: default the paper's starting value; a colour map an RGB triple, linear) and the index of refraction ``eta``.
MaterialSpec = dataclasses.make_dataclass(
    "MaterialSpec",
    [(m.name, tuple[float, float, float] if m.colour else float,
      dataclasses.field(default=(float(m.initial),) * 3 if m.colour else float(m.initial))) for m in MAPS.values()]
    + [("eta", float, dataclasses.field(default=1.5))],
    namespace={"__doc__": "The initial material of a scene pack ([material]): one field per BSDF map and eta.",
               "__module__": __name__})


@dataclasses.dataclass
class ScenePack:
    name: str
    object: ObjectSpec
    environment: EnvironmentSpec
    cameras: CameraSpec
    render: RenderSpec
    material: MaterialSpec
    source: str | None = None  # the pack file, or "builtin:NAME"

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return _drop_none(d)


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, (list, tuple)):
        return [_drop_none(v) for v in d]
    return d


_SECTIONS = {
    "object": ObjectSpec,
    "environment": EnvironmentSpec,
    "cameras": CameraSpec,
    "render": RenderSpec,
    "material": MaterialSpec,
}


def _num(where: str, v: Any, lo: float | None = None, hi: float | None = None, integer: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise CamoError(f"{where} must be a number, got {v!r}")
    if not math.isfinite(v):
        raise CamoError(f"{where} must be finite, got {v!r}")
    if integer and int(v) != v:
        raise CamoError(f"{where} must be an integer, got {v!r}")
    if lo is not None and v < lo:
        raise CamoError(f"{where} must be >= {lo}, got {v!r}")
    if hi is not None and v > hi:
        raise CamoError(f"{where} must be <= {hi}, got {v!r}")
    return int(v) if integer else float(v)


def _vec(where: str, v: Any, n: tuple[int, ...], lo: float | None = None, hi: float | None = None) -> tuple[float, ...]:
    if not isinstance(v, (list, tuple)) or len(v) not in n:
        raise CamoError(f"{where} must be a list of {' or '.join(map(str, n))} numbers, got {v!r}")
    return tuple(_num(f"{where}[{i}]", x, lo, hi) for i, x in enumerate(v))


def parse_pack(data: dict[str, Any], base_dir: Path | None = None, source: str | None = None) -> ScenePack:
    """Validate a pack given as a dict (the parsed TOML). Paths are resolved against ``base_dir``."""
    from optimizer.scenes import environments, primitives

    unknown = set(data) - set(_SECTIONS) - {"name"}
    if unknown:
        raise CamoError(f"unknown key(s) at top level: {', '.join(sorted(unknown))}")
    sections: dict[str, Any] = {}
    for sec, cls in _SECTIONS.items():
        raw = data.get(sec, {})
        if not isinstance(raw, dict):
            raise CamoError(f"[{sec}] must be a table")
        fields = {f.name for f in dataclasses.fields(cls)}
        bad = set(raw) - fields
        if bad:
            raise CamoError(f"unknown key(s) in [{sec}]: {', '.join(sorted(bad))} (allowed: {', '.join(sorted(fields))})")
        sections[sec] = raw

    o = sections["object"]
    obj = ObjectSpec()
    if ("mesh" in o) == ("primitive" in o):
        raise CamoError("[object] needs exactly one of `mesh` (a file) or `primitive` (a built-in shape)")
    if "mesh" in o:
        p = Path(str(o["mesh"]))
        if base_dir is not None and not p.is_absolute():
            p = base_dir / p
        if not p.is_file():
            raise CamoError(f"[object] mesh file not found: {p}")
        obj.mesh = str(p.resolve())
    else:
        if o["primitive"] not in primitives.PRIMITIVES:
            raise CamoError(
                f"[object] unknown primitive {o['primitive']!r}; choose one of: {', '.join(sorted(primitives.PRIMITIVES))}"
            )
        obj.primitive = o["primitive"]
    if "size" in o:
        obj.size = _num("[object] size", o["size"], lo=1e-4, hi=1e4)
    if "rotation" in o:
        obj.rotation = _vec("[object] rotation", o["rotation"], (3,))
    if "translation" in o:
        t = _vec("[object] translation", o["translation"], (2, 3))
        obj.translation = (t[0], t[1], t[2] if len(t) == 3 else 0.0)
    if "target_vertices" in o:
        obj.target_vertices = _num("[object] target_vertices", o["target_vertices"], lo=100, hi=2_000_000, integer=True)

    e = sections["environment"]
    env = EnvironmentSpec()
    given = [k for k in ("builtin", "xml", "panorama") if k in e]
    if len(given) != 1:
        raise CamoError("[environment] needs exactly one of `builtin`, `xml` or `panorama`")
    if "builtin" in e:
        if e["builtin"] not in environments.ENVIRONMENTS:
            raise CamoError(
                f"[environment] unknown builtin {e['builtin']!r}; choose one of: {', '.join(sorted(environments.ENVIRONMENTS))}"
            )
        env.builtin = e["builtin"]
    else:
        key = given[0]
        p = Path(str(e[key]))
        if base_dir is not None and not p.is_absolute():
            p = base_dir / p
        if not p.is_file():
            raise CamoError(f"[environment] {key} file not found: {p}")
        if key == "panorama" and p.suffix.lower() not in (".exr", ".hdr"):
            raise CamoError(f"[environment] panorama must be an .exr or .hdr equirect image, got {p.name}")
        if key == "xml" and p.suffix.lower() != ".xml":
            raise CamoError(f"[environment] xml must be a Mitsuba .xml scene, got {p.name}")
        setattr(env, key, str(p.resolve()))
    for k in ("capture_height", "ground_extent", "rotation"):
        if k in e:
            setattr(env, k, _num(f"[environment] {k}", e[k], lo=0.0 if k != "rotation" else None))
    if "ground" in e:
        if not isinstance(e["ground"], bool):
            raise CamoError("[environment] ground must be true or false")
        env.ground = e["ground"]

    c = sections["cameras"]
    cams = CameraSpec()
    if "mode" in c:
        if c["mode"] not in ("orbit", "list"):
            raise CamoError(f"[cameras] mode must be 'orbit' or 'list', got {c['mode']!r}")
        cams.mode = c["mode"]
    if "views" in c:
        cams.views = _num("[cameras] views", c["views"], lo=1, hi=1024, integer=True)
    if "radius" in c:
        cams.radius = _num("[cameras] radius", c["radius"], lo=1e-3)
    if "elevation" in c:
        cams.elevation = _num("[cameras] elevation", c["elevation"], lo=-89.0, hi=89.0)
    if "fov" in c:
        cams.fov = _num("[cameras] fov", c["fov"], lo=1.0, hi=170.0)
    if "azimuth_offset" in c:
        cams.azimuth_offset = _num("[cameras] azimuth_offset", c["azimuth_offset"])
    if cams.mode == "list":
        pos = c.get("positions")
        if not isinstance(pos, list) or not pos:
            raise CamoError("[cameras] mode = 'list' needs a non-empty `positions` list")
        cams.positions = [_vec(f"[cameras] positions[{i}]", p, (3,)) for i, p in enumerate(pos)]
        if "targets" in c:
            tg = c["targets"]
            if not isinstance(tg, list) or len(tg) != len(cams.positions):
                raise CamoError("[cameras] targets must list one [x, y, z] per position")
            cams.targets = [_vec(f"[cameras] targets[{i}]", t, (3,)) for i, t in enumerate(tg)]
        cams.views = len(cams.positions)
    elif "positions" in c or "targets" in c:
        raise CamoError("[cameras] positions/targets are only allowed with mode = 'list'")

    r = sections["render"]
    ren = RenderSpec()
    if "resolution" in r:
        res = r["resolution"]
        if isinstance(res, (list, tuple)):
            w, h = _vec("[render] resolution", res, (2,), lo=8, hi=8192)
        else:
            w = h = _num("[render] resolution", res, lo=8, hi=8192, integer=True)
        ren.resolution = (int(w), int(h))
    if "spp" in r:
        ren.spp = _num("[render] spp", r["spp"], lo=1, hi=1 << 16, integer=True)

    m = sections["material"]
    mat = MaterialSpec()
    for k, bm in MAPS.items():
        if k not in m:
            continue
        a = m[k]
        if bm.colour:
            a = _vec(f"[material] {k}", a, (3,), 0.0, 1.0) if isinstance(a, list) else (_num(f"[material] {k}", a, 0.0, 1.0),) * 3
        else:
            a = _num(f"[material] {k}", a, 0.0, 1.0)
        setattr(mat, k, a)
    if "eta" in m:
        mat.eta = _num("[material] eta", m["eta"], 1.0001, 4.0)

    name = data.get("name", Path(source).stem if source else "scene")
    if not isinstance(name, str) or not name.strip():
        raise CamoError("`name` must be a non-empty string")
    pack = ScenePack(name=name, object=obj, environment=env, cameras=cams, render=ren, material=mat, source=source)
    _check_cameras_outside_object(pack)
    return pack


def _check_cameras_outside_object(pack: ScenePack) -> None:
    """Refuse cameras inside the object's bounding sphere (a camera there sees nothing useful)."""
    from optimizer.scenes.cameras import camera_positions, object_centre

    centre = object_centre(pack)
    reach = pack.object.size * math.sqrt(3) / 2  # bounding sphere of a cube of side `size`
    for i, p in enumerate(camera_positions(pack)):
        d = math.dist(p, centre)
        if d <= reach:
            raise CamoError(
                f"camera {i} at {tuple(round(x, 3) for x in p)} is inside the object (distance {d:.3f} <= {reach:.3f}); "
                "increase [cameras] radius or reduce [object] size"
            )


def load_pack(path: str | Path) -> ScenePack:
    """Read and validate a scene pack TOML file."""
    path = Path(path)
    return parse_pack(read_toml(path, "scene pack"), base_dir=path.parent, source=str(path))
