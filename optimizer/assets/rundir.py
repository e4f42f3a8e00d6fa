"""Reading a run directory (output of ``camo optimize``; layout in CONTRIBUTING.md) back: the one place that does.

:func:`open_run` returns a :class:`RunDir`: its parsed ``config.toml`` (the resolved scene pack ``[pack]``, the
appearance config ``[run.appearance]``, method and ablation), its cost in seconds (:meth:`RunDir.seconds`, from
``summary.json`` and ``log.jsonl``) and its result as an :class:`optimizer.assets.asset.Asset` (:meth:`RunDir.asset`):
the world-space displaced, posed mesh of ``result.ply`` and the maps of ``maps/*.npy`` **as rendered**
(``maps/roughness.npy`` holds the roughness after the renderer's safe minimum,
``optimizer.rendering.appearance.rendered_maps``); :meth:`optimizer.assets.asset.Asset.values` gives them back as optimised
(roughness inverted once), which is what :func:`optimizer.rendering.appearance.object_bsdf` takes.

Every problem (no config.toml, bad TOML, missing or corrupt maps, a malformed PLY) is a one-line CamoError.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from optimizer.assets.asset import Asset, check_maps
from camo_base.errors import CamoError

#: Files a run directory must have for its result to be read (besides config.toml).
RESULT_FILES = ("maps/albedo.npy", "maps/metallic.npy", "maps/roughness.npy", "maps/transmittance.npy", "result.ply")

_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "int": "<i4", "int32": "<i4",
              "uint": "<u4", "uint32": "<u4", "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1",
              "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2"}


def read_config(run_dir: Path) -> dict[str, Any]:
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
    from optimizer.scenes import primitives
    from optimizer.scenes.scenepack import parse_pack

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
    from optimizer.rendering.appearance import AppearanceConfig

    raw = (cfg.get("run") or {}).get("appearance", {})
    if not isinstance(raw, dict):
        raise CamoError(f"{run_dir / 'config.toml'}: [run.appearance] must be a table")
    known = {f.name for f in dataclasses.fields(AppearanceConfig)}
    return AppearanceConfig(**{k: v for k, v in raw.items() if k in known})


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices ``(N, 3)``, triangle faces ``(F, 3)`` and ``u, v`` ``(N, 2)`` (or None) of a binary
    little-endian PLY as :func:`optimizer.assets.export.write_ply` writes it (read unchanged, like Mitsuba's plugin)."""
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
    try:
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
    except (KeyError, IndexError, ValueError) as exc:
        raise CamoError(f"{path}: malformed PLY header ({exc})") from None
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


def read_map(run_dir: Path, name: str, channels: int) -> np.ndarray:
    """``maps/<name>.npy`` as float32 ``(H, W, channels)``."""
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


@dataclasses.dataclass
class RunDir:
    """One run directory, read back (see the module docstring)."""

    path: Path
    name: str  # the directory's name
    config: dict[str, Any]  # parsed config.toml
    pack: Any  # optimizer.scenes.scenepack.ScenePack
    app: Any  # optimizer.rendering.appearance.AppearanceConfig
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

    def summary(self) -> dict[str, Any]:
        """``summary.json`` ({} when absent; CamoError when unreadable)."""
        p = self.path / "summary.json"
        if not p.is_file():
            return {}
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError) as exc:
            raise CamoError(f"{p}: not valid JSON ({exc})") from None
        return data if isinstance(data, dict) else {}

    def log(self) -> list[dict[str, Any]]:
        """The records of ``log.jsonl`` (torn lines skipped)."""
        p = self.path / "log.jsonl"
        out = []
        if p.is_file():
            for line in p.read_text(encoding="utf-8", errors="replace").splitlines():
                try:
                    rec = json.loads(line)
                except ValueError:
                    continue
                if isinstance(rec, dict):
                    out.append(rec)
        return out

    def seconds(self) -> dict[str, float]:
        """What the run cost, in seconds: ``setup`` (``summary.json`` ``seconds_setup``), ``stage1`` and ``stage2``
        (``summary.json`` ``seconds_stage1`` / ``seconds_stage2``: wall clock of the stage, Stage 1 with its warm
        start; runs written before those keys existed: the sum of ``log.jsonl``'s per-iteration ``seconds_total``,
        else ``seconds``, of that stage) and ``total`` (setup + both stages). A baseline's run (``summary.json`` with
        ``seconds_method`` and no stage keys) has no stages: ``total`` is setup + ``seconds_method``. NaN for what the
        run does not record."""
        s = self.summary()
        out = {"setup": _num(s.get("seconds_setup"))}
        if "seconds_method" in s and not any(f"seconds_stage{st}" in s for st in (1, 2)):
            return {**out, "stage1": math.nan, "stage2": math.nan, "total": out["setup"] + _num(s["seconds_method"])}
        log = self.log()
        for st in (1, 2):
            key = f"seconds_stage{st}"
            if key in s:
                out[f"stage{st}"] = _num(s[key])
            elif log:
                out[f"stage{st}"] = float(sum(_num(r.get("seconds_total", r.get("seconds")), 0.0)
                                              for r in log if r.get("stage", 1) == st))
            else:
                out[f"stage{st}"] = math.nan
        parts = [out["setup"], out["stage1"], out["stage2"]]
        out["total"] = float(sum(parts)) if all(math.isfinite(p) for p in parts) else math.nan
        return out

    def asset(self) -> Asset:
        """The result: ``result.ply`` (world space, pose and displacement applied) and ``maps/*.npy`` as rendered."""
        verts, faces, uvs = read_ply(self.path / "result.ply")
        maps = {"albedo": read_map(self.path, "albedo", 3)}
        for name in ("metallic", "roughness", "transmittance"):
            maps[name] = read_map(self.path, name, 1)
        a = Asset(str(self.path), verts, faces, uvs, maps, float(self.app.eta), not self.app.bsdf, "clamp", "scene")
        check_maps(a, self.name, "{label}: maps/{name}.npy")
        return a


def _num(v: Any, default: float = math.nan) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return f if math.isfinite(f) else default


def open_run(path: str | Path) -> RunDir:
    """Read a run directory's config and check its result files; CamoError (one line) for anything missing."""
    run_dir = Path(path)
    if not run_dir.exists():
        raise CamoError(f"run directory not found: {run_dir}")
    if not run_dir.is_dir():
        raise CamoError(f"not a run directory (not a folder): {run_dir}")
    cfg = read_config(run_dir)
    run = cfg.get("run")
    if not isinstance(run, dict):
        raise CamoError(f"{run_dir / 'config.toml'}: no [run] table")
    pack = pack_from_config(cfg, run_dir)
    app = appearance_from_config(cfg, run_dir)
    missing = [f for f in RESULT_FILES if not (run_dir / f).is_file()]
    if missing:
        raise CamoError(f"{run_dir}: incomplete run directory, missing {', '.join(missing)}")
    ablate = run.get("ablate", [])
    if isinstance(ablate, str):
        ablate = [a for a in ablate.split(",") if a]
    return RunDir(run_dir, run_dir.resolve().name, cfg, pack, app, str(run.get("method", "ours")),
                  tuple(sorted(str(a) for a in ablate)))


def is_run_dir(path: str | Path) -> bool:
    p = Path(path)
    return p.is_dir() and (p / "config.toml").is_file()
