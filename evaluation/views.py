"""Novel evaluation views of run directories, rendered at evaluation quality (paper Sec. IV-B).

Three steps, each usable on its own:

* :func:`load_run` reads a run directory (see CONTRIBUTING.md) back: the resolved scene pack (``[pack]`` of
  ``config.toml``), the appearance config (``[run.appearance]``), the method and ablation, and the result
  (:func:`load_result`: the world-space displaced, posed mesh of ``result.ply`` and the *rendered* BSDF maps
  of ``maps/*.npy``).
* :func:`evaluation_cameras` moves each of the pack's training cameras by an independent uniform offset of up
  to ``+-jitter`` units per axis at radius 4 (scaled with the radius; :func:`optimizer.cameras.jitter`),
  seeded. No evaluation camera equals a training camera (checked, not assumed). The cameras depend only on
  the pack's rig, the resolution, ``jitter`` and ``seed``, so every run of one scene is evaluated on
  identical views.
* :class:`ViewRenderer` renders, per view, the background without the object (cached per scene, camera set,
  spp, resolution, integrator and seed: several runs of one scene render it once), the scene with the object,
  the object's visible mask (coverage >= 0.5, occlusion aware) and the background depth, with the effect
  planner's ``purpose="evaluate"`` path tracer.

Roughness: ``maps/roughness.npy`` holds the roughness *as rendered*
(``optimizer.appearance.rendered_maps``: ``r_min + (1 - r_min) r``), while
:func:`optimizer.appearance.object_bsdf` expects the map value ``r`` and applies that affine map itself. The
saved map is therefore inverted once (:func:`map_values_from_rendered`) before it goes through
``object_bsdf``; the BSDF then renders exactly the saved roughness.

Variance: the background and the with-object render of a view use the same sampler seed (common random
numbers). Paths that never meet the object then give identical radiance in both images, so the metrics see
the object's effect (and its shadow) rather than two independent noise patterns.

Images are linear float32 ``(V, H, W, 3)``; masks ``(V, H, W)`` bool; depth ``(V, H, W)`` float32 in scene
units (0 = miss).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from optimizer.cameras import Camera
from optimizer.errors import CamoError

#: The paper's evaluation jitter: up to +-0.25 units per axis at radius 4.
DEFAULT_JITTER = 0.25

#: Files a run directory must have for evaluation (besides config.toml).
RESULT_FILES = ("maps/albedo.npy", "maps/metallic.npy", "maps/roughness.npy", "maps/transmittance.npy")


# --------------------------------------------------------------------------------------------------------------
# run directories
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class RunInfo:
    """What evaluation needs to know about one run directory."""

    path: Path
    name: str  # the directory's name
    config: dict[str, Any]  # parsed config.toml
    pack: Any  # optimizer.scenepack.ScenePack
    app: Any  # optimizer.appearance.AppearanceConfig
    method: str
    ablation: tuple[str, ...]

    @property
    def scene(self) -> str:
        return self.pack.name

    @property
    def object(self) -> str:
        o = self.pack.object
        return o.primitive or (Path(o.mesh).stem if o.mesh else "object")

    @property
    def ablation_label(self) -> str:
        return ",".join(self.ablation) if self.ablation else "none"


def _read_config(run_dir: Path) -> dict[str, Any]:
    cfg_path = run_dir / "config.toml"
    if not cfg_path.is_file():
        raise CamoError(f"{run_dir}: no config.toml (is this a run directory from `camo optimize`?)")
    try:
        return tomllib.loads(cfg_path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CamoError(f"{cfg_path}: not valid TOML ({exc})") from None


def pack_from_config(cfg: dict[str, Any], run_dir: Path):
    """The resolved scene pack of a run (``[pack]`` of its config.toml).

    A mesh file that has moved since the run does not matter (the result's own mesh is ``result.ply``): the
    pack is validated with a placeholder shape and keeps the recorded mesh path.
    """
    from optimizer import primitives
    from optimizer.scenepack import parse_pack

    raw = cfg.get("pack")
    if not isinstance(raw, dict):
        raise CamoError(f"{run_dir / 'config.toml'}: no [pack] table")
    data = json.loads(json.dumps(raw))  # deep copy
    source = data.pop("source", None)
    obj = data.get("object")
    moved_mesh = None
    if isinstance(obj, dict) and "mesh" in obj and not Path(str(obj["mesh"])).is_file():
        moved_mesh = str(obj.pop("mesh"))
        obj["primitive"] = sorted(primitives.PRIMITIVES)[0]
    try:
        pack = parse_pack(data, base_dir=run_dir, source=source)
    except CamoError as exc:
        raise CamoError(f"{run_dir / 'config.toml'}: [pack]: {exc}") from None
    if moved_mesh is not None:
        pack.object = dataclasses.replace(pack.object, primitive=None, mesh=moved_mesh)
    return pack


def appearance_from_config(cfg: dict[str, Any], run_dir: Path):
    from optimizer.appearance import AppearanceConfig

    raw = (cfg.get("run") or {}).get("appearance", {})
    if not isinstance(raw, dict):
        raise CamoError(f"{run_dir / 'config.toml'}: [run.appearance] must be a table")
    known = {f.name for f in dataclasses.fields(AppearanceConfig)}
    return AppearanceConfig(**{k: v for k, v in raw.items() if k in known})


def load_run(path: str | Path) -> RunInfo:
    """Read a run directory's config; CamoError (one line) for anything missing or malformed."""
    run_dir = Path(path)
    if not run_dir.exists():
        raise CamoError(f"run directory not found: {run_dir}")
    if not run_dir.is_dir():
        raise CamoError(f"not a run directory (not a folder): {run_dir}")
    cfg = _read_config(run_dir)
    run = cfg.get("run")
    if not isinstance(run, dict):
        raise CamoError(f"{run_dir / 'config.toml'}: no [run] table")
    pack = pack_from_config(cfg, run_dir)
    app = appearance_from_config(cfg, run_dir)
    missing = [f for f in RESULT_FILES if not (run_dir / f).is_file()]
    if not (run_dir / "result.ply").is_file():
        missing.append("result.ply")
    if missing:
        raise CamoError(f"{run_dir}: incomplete run directory, missing {', '.join(missing)}")
    ablate = run.get("ablate", [])
    if isinstance(ablate, str):
        ablate = [a for a in ablate.split(",") if a]
    return RunInfo(run_dir, run_dir.resolve().name, cfg, pack, app, str(run.get("method", "ours")),
                   tuple(sorted(str(a) for a in ablate)))


# --------------------------------------------------------------------------------------------------------------
# the result: mesh and maps
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class ResultAssets:
    vertices: np.ndarray  # (N, 3) world space, displaced and posed
    faces: np.ndarray  # (F, 3)
    uvs: np.ndarray | None  # (N, 2), Mitsuba convention
    rendered: dict[str, np.ndarray]  # maps as rendered (roughness after the safe minimum)
    values: dict[str, np.ndarray]  # maps as object_bsdf takes them (roughness inverted once)
    warnings: list[str]


_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "int": "<i4", "int32": "<i4",
              "uint": "<u4", "uint32": "<u4", "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1",
              "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2"}


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices ``(N, 3)``, triangle faces ``(F, 3)`` and ``u, v`` ``(N, 2)`` (or None) of a binary
    little-endian PLY as :func:`optimizer.export.write_ply` writes it (read unchanged, like Mitsuba's plugin)."""
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise CamoError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii", "replace").splitlines()
    body = data[end + len(b"end_header\n"):]
    if "format binary_little_endian 1.0" not in header:
        raise CamoError(f"{path}: only binary little-endian PLY (as camo writes it) is supported")
    elements: list[list] = []  # [name, count, [(prop, dtype)] or ("list", count_t, item_t)]
    for line in header[1:]:
        parts = line.split()
        if not parts or parts[0] in ("format", "comment", "obj_info"):
            continue
        if parts[0] == "element":
            elements.append([parts[1], int(parts[2]), []])
        elif parts[0] == "property" and elements:
            if parts[1] == "list":
                elements[-1][2] = ("list", _PLY_TYPES[parts[2]], _PLY_TYPES[parts[3]], parts[4])
            else:
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    off = 0
    verts = faces = uvs = None
    try:
        for name, count, props in elements:
            if isinstance(props, tuple):  # a list property: camo writes triangles only
                _, ct, it, _ = props
                dt = np.dtype([("n", ct), ("i", it, (3,))])
                arr = np.frombuffer(body, dtype=dt, count=count, offset=off)
                if count and not np.all(arr["n"] == 3):
                    raise CamoError(f"{path}: only triangle faces are supported")
                if name == "face":
                    faces = arr["i"].astype(np.int64)
                off += dt.itemsize * count
            else:
                dt = np.dtype(props)
                arr = np.frombuffer(body, dtype=dt, count=count, offset=off)
                off += dt.itemsize * count
                if name == "vertex":
                    verts = np.stack([arr[k] for k in ("x", "y", "z")], axis=1).astype(np.float32)
                    if "u" in dt.names and "v" in dt.names:
                        uvs = np.stack([arr["u"], arr["v"]], axis=1).astype(np.float32)
    except (ValueError, KeyError) as exc:
        raise CamoError(f"{path}: malformed PLY ({exc})") from None
    if verts is None or faces is None or len(faces) == 0:
        raise CamoError(f"{path}: PLY without vertices or faces")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise CamoError(f"{path}: PLY face indices out of range")
    if not np.isfinite(verts).all():
        raise CamoError(f"{path}: PLY vertices contain NaN or infinite values")
    return verts, faces, uvs


def map_values_from_rendered(rendered_roughness: np.ndarray) -> tuple[np.ndarray, bool]:
    """Invert ``r_min + (1 - r_min) r`` (the rendered roughness) to the map value ``r`` that
    ``object_bsdf`` takes; returns ``(r, clipped)`` where ``clipped`` says a value lay below ``r_min``."""
    from optimizer.scene import ROUGHNESS_MIN

    rr = np.asarray(rendered_roughness, dtype=np.float32)
    r = (rr - np.float32(ROUGHNESS_MIN)) / np.float32(1.0 - ROUGHNESS_MIN)
    clipped = bool((r < -1e-5).any() or (r > 1.0 + 1e-5).any())
    return np.clip(r, 0.0, 1.0).astype(np.float32), clipped


def _map(run_dir: Path, name: str, channels: int) -> np.ndarray:
    p = run_dir / "maps" / f"{name}.npy"
    try:
        a = np.load(p, allow_pickle=False)
    except Exception as exc:  # ValueError/OSError/EOFError on corrupt files
        raise CamoError(f"{p}: cannot read ({type(exc).__name__})") from None
    a = np.asarray(a, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] != channels:
        raise CamoError(f"{p}: expected an (H, W{', 3' if channels == 3 else ''}) map, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise CamoError(f"{p}: contains NaN or infinite values")
    return a


def load_result(run: RunInfo) -> ResultAssets:
    """The run's result as evaluation renders it: ``result.ply`` (world-space mesh with pose and displacement
    applied) and the maps of ``maps/*.npy`` (roughness inverted once, see the module docstring)."""
    verts, faces, uvs = read_ply(run.path / "result.ply")
    rendered = {"albedo": _map(run.path, "albedo", 3)}
    for name in ("metallic", "roughness", "transmittance"):
        rendered[name] = _map(run.path, name, 1)
    warnings = []
    values = dict(rendered)
    values["roughness"], clipped = map_values_from_rendered(rendered["roughness"])
    if clipped:
        warnings.append(f"{run.name}: maps/roughness.npy lies outside the renderable range [0.035, 1]; clipped")
    for name in ("albedo", "metallic", "transmittance"):
        if rendered[name].min() < -1e-5 or rendered[name].max() > 1 + 1e-5:
            warnings.append(f"{run.name}: maps/{name}.npy lies outside [0, 1]; clipped")
            values[name] = np.clip(rendered[name], 0.0, 1.0)
    return ResultAssets(verts, faces, uvs, rendered, values, warnings)


def object_mesh_of(run: RunInfo, assets: ResultAssets):
    """A fresh ``mi.Mesh`` of the result with its BSDF (``optimizer.appearance.object_bsdf``)."""
    from optimizer import scene as scn
    from optimizer.appearance import object_bsdf

    return scn.object_mesh(assets.vertices, assets.faces, assets.uvs, object_bsdf(assets.values, run.app))


# --------------------------------------------------------------------------------------------------------------
# cameras
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class EvalCameras:
    cams: list[Camera]  # evaluation cameras (jittered)
    base: list[int]  # index of the training camera each one was moved from
    training: list[Camera]  # the pack's training cameras at the evaluation resolution
    amount: float  # jitter at radius 4
    bound: float  # the per-axis bound actually used: amount * radius / 4
    seed: int

    def key(self) -> str:
        """Short hash of the camera set (identical for every run of the same scene and settings)."""
        blob = json.dumps([dataclasses.astuple(c) for c in self.cams]).encode()
        return hashlib.sha256(blob).hexdigest()[:12]


def rig_radius(pack, training: list[Camera]) -> float:
    """The rig's radius: the orbit radius, or the mean camera-target distance of a camera list."""
    if pack.cameras.mode == "orbit":
        return float(pack.cameras.radius)
    return float(np.mean([math.dist(c.origin, c.target) for c in training]))


def evaluation_cameras(pack, views: int | None = None, jitter: float = DEFAULT_JITTER, seed: int = 0,
                       resolution: tuple[int, int] | None = None) -> EvalCameras:
    """Jittered novel views of ``pack``'s training cameras.

    ``views`` (default: the number of training cameras) below the training count takes evenly spaced
    cameras of the rig; above it the rig is jittered again (``repeats``), and the first ``views`` are kept.
    Every training camera's jitter is drawn in the same order whatever ``views`` is, so a smaller evaluation
    is a subset of a larger one.
    """
    from optimizer.cameras import cameras, jitter as jitter_cams

    if not (isinstance(jitter, (int, float)) and math.isfinite(jitter)) or jitter <= 0:
        raise CamoError(f"--jitter must be > 0 (evaluation never uses the training cameras), got {jitter}")
    training = cameras(pack, resolution)
    n_train = len(training)
    views = n_train if views is None else views
    if views < 1:
        raise CamoError(f"--views must be >= 1, got {views}")
    radius = rig_radius(pack, training)
    repeats = max(1, math.ceil(views / n_train))
    moved = jitter_cams(training, float(jitter), radius, int(seed), repeats=repeats)
    if views <= n_train:
        idx = sorted({int(round(i * n_train / views)) % n_train for i in range(views)})
    else:
        idx = list(range(views))
    cams = [moved[i] for i in idx]
    base = [i % n_train for i in idx]
    train_origins = {c.origin for c in training}
    bad = [i for i, c in enumerate(cams) if c in training or c.origin in train_origins]
    if bad:  # jitter() redraws such offsets; this must never happen
        raise RuntimeError(f"evaluation camera(s) {bad} coincide with a training camera")
    return EvalCameras(cams, base, training, float(jitter), float(jitter) * radius / 4.0, int(seed))


# --------------------------------------------------------------------------------------------------------------
# rendering
# --------------------------------------------------------------------------------------------------------------


def evaluation_plan(pack, env):
    """The planner's ``purpose="evaluate"`` path tracer, planned for a transmissive, metallic object.

    Every method of a scene must be rendered by the same integrator (the background is shared, and a
    shallower path tracer for an opaque result would bias the comparison), so the plan does not depend on
    the particular result: it is deep enough for the most demanding material any method may produce.
    """
    from optimizer.planner import plan

    worst = dataclasses.replace(pack, material=dataclasses.replace(pack.material, transmittance=1.0, metallic=1.0))
    return plan(worst, env, set(), "evaluate")


def render_seed(seed: int) -> int:
    """Sampler seed of every evaluation render for evaluation seed ``seed`` (same for all runs and for
    the background and with-object images: common random numbers)."""
    return (int(seed) * 7919 + 104729) & 0x7FFFFFFF


@dataclasses.dataclass
class Background:
    image: np.ndarray  # (V, H, W, 3) linear
    depth: np.ndarray  # (V, H, W)
    seconds: float
    key: str


@dataclasses.dataclass
class ObjectRenders:
    image: np.ndarray  # (V, H, W, 3) linear
    coverage: np.ndarray  # (V, H, W) float32
    mask: np.ndarray  # (V, H, W) bool (coverage >= 0.5)
    seconds: float


class ViewRenderer:
    """Evaluation renders with a background cache (one entry per scene, camera set, spp, integrator, seed)."""

    def __init__(self, spp: int, seed: int = 0, ss: int = 4):
        self.spp, self.seed, self.ss = int(spp), int(seed), int(ss)
        self.cache: dict[str, Background] = {}
        self.background_renders = 0  # how many times a background was actually rendered

    def _key(self, pack, cams: list[Camera], integrator: dict) -> str:
        blob = json.dumps({"env": dataclasses.asdict(pack.environment), "cams": [dataclasses.astuple(c) for c in cams],
                           "spp": self.spp, "integrator": integrator, "seed": self.seed}, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def background(self, pack, env, cams: list[Camera], integrator: dict) -> Background:
        from optimizer import scene as scn
        from optimizer.render import coverage_and_depth, render_shaded

        key = self._key(pack, cams, integrator)
        if key not in self.cache:
            t = time.perf_counter()
            img = render_shaded(env.build(), None, cams, integrator, self.spp, render_seed(self.seed))
            sc = scn.build_scene(env.build())
            depth = np.stack([coverage_and_depth(sc, c, None, self.ss)[1] for c in cams])
            self.cache[key] = Background(img, depth, time.perf_counter() - t, key)
            self.background_renders += 1
        return self.cache[key]

    def with_object(self, env, mesh_fn, cams: list[Camera], integrator: dict) -> ObjectRenders:
        from optimizer import scene as scn
        from optimizer.render import coverage_and_depth, render_shaded

        t = time.perf_counter()
        mesh = mesh_fn()
        img = render_shaded(env.build(), mesh, cams, integrator, self.spp, render_seed(self.seed))
        sc = scn.build_scene(env.build(), mesh)
        cov = np.stack([coverage_and_depth(sc, c, mesh, self.ss)[0] for c in cams]).astype(np.float32)
        return ObjectRenders(img, cov, cov >= 0.5, time.perf_counter() - t)
