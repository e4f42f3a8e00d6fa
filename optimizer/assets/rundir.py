"""The run directory (output of ``camo optimize``; layout in CONTRIBUTING.md): the one owner of its files.

Writing: :func:`prepare_run_dir` (a new, empty or resumable folder), :func:`write_config` (``config.toml`` = the
run spec's dict + provenance tables), :func:`config_fingerprint` (what a checkpoint must match to be resumed),
:func:`write_log` (``log.jsonl``) and :func:`write_summary` (``summary.json``, for every method). The result files
(maps, meshes, scene.xml, previews, renders.npz) are :mod:`optimizer.assets.result`'s.

``config.toml`` has two layouts, both read here:

* version 2 (``spec_version = 2``): the run spec (:class:`optimizer.optimise.spec.RunSpec`) at the top level --
  ``scene``, ``method``, ``seed``, ``[spp]``, ``[stage1]``, ``[stage2]``, ``[appearance]``, ``[options]``, ``[pack]``
  -- plus the provenance tables :data:`PROVENANCE` (``[versions]``, ``[plan]``, ``[fingerprint]``, ``[baseline]``);
* version 1 (no ``spec_version``; written before run specs): a ``[run]`` table (method, ablate, ``[run.stage1]``,
  ``[run.stage2]``, ``[run.appearance]``) beside ``[pack]`` and the same provenance tables. Such a run directory
  still evaluates; it cannot be resumed or re-run from its config (run it again with the same flags).

Reading: :func:`open_run` returns a :class:`RunDir`: its parsed ``config.toml`` (the resolved scene pack ``[pack]``,
the appearance config, method and ablation), its cost in seconds (:meth:`RunDir.seconds`, from
``summary.json`` and ``log.jsonl``) and its result as an :class:`optimizer.assets.asset.Asset` (:meth:`RunDir.asset`):
the world-space displaced, posed mesh of ``result.ply`` and the maps of ``maps/*.npy`` **as rendered**
(``maps/roughness.npy`` holds the roughness after the renderer's safe minimum,
``optimizer.rendering.appearance.rendered_maps``); :meth:`optimizer.assets.asset.Asset.values` gives them back as optimised
(roughness inverted once), which is what :func:`optimizer.rendering.appearance.object_bsdf` takes.

Every problem (no config.toml, bad TOML, missing or corrupt maps, a malformed PLY) is a one-line CamoError.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from camo_base import atomic
from optimizer.assets.asset import Asset, check_maps
from camo_base.errors import CamoError

#: Files a run directory must have for its result to be read (besides config.toml).
RESULT_FILES = ("maps/albedo.npy", "maps/metallic.npy", "maps/roughness.npy", "maps/transmittance.npy", "result.ply")
CONFIG = "config.toml"
SUMMARY = "summary.json"
LOG = "log.jsonl"
CHECKPOINT = "checkpoint.npz"
#: Layout version of config.toml written now (``spec_version``; the run spec's version).
CONFIG_VERSION = 2
#: Tables of config.toml that are provenance, not the run spec.
PROVENANCE = ("versions", "plan", "fingerprint", "baseline")


# --------------------------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------------------------


def prepare_run_dir(out: Path, resume: bool, overwrite: bool) -> None:
    """Make ``out`` ready for a run: new or empty (or ``overwrite``); with ``resume`` it must hold a checkpoint
    written with this config layout. CamoError (one line) otherwise; nothing in ``out`` changes."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CamoError(f"--out {out} exists and is not a folder")
    if resume:
        if not (out / CHECKPOINT).is_file():
            raise CamoError(f"--resume: no {CHECKPOINT} in {out}")
        if (out / CONFIG).is_file():
            try:
                layout = config_layout(read_config(out), out)
            except CamoError:
                layout = CONFIG_VERSION  # unreadable: the checkpoint's fingerprint decides
            if layout != CONFIG_VERSION:
                raise CamoError(f"--resume: {out} was written by camo before run specs (config.toml layout {layout}); "
                                "it cannot be resumed: start a new run (its finished files still evaluate)")
        return
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise CamoError(f"run directory {out} is not empty; use --resume to continue it, --overwrite to replace it, or another --out")
    out.mkdir(parents=True, exist_ok=True)


def write_config(out: Path, spec: dict[str, Any], provenance: dict[str, Any]) -> None:
    """``out/config.toml`` = the run spec's dict (``RunSpec.to_dict``) + provenance tables (:data:`PROVENANCE`)."""
    import tomli_w

    bad = sorted(set(provenance) - set(PROVENANCE)) or sorted(set(provenance) & set(spec))
    if bad:
        raise ValueError(f"config.toml: {', '.join(bad)} is not a provenance table (or clashes with the spec)")
    if spec.get("spec_version") != CONFIG_VERSION:
        raise ValueError(f"config.toml: the spec must carry spec_version = {CONFIG_VERSION}")
    atomic.write_text(Path(out) / CONFIG, tomli_w.dumps({**spec, **_toml_plain(provenance)}))


def _toml_plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _toml_plain(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_toml_plain(v) for v in obj]
    return obj


def config_fingerprint(spec: dict[str, Any], ignore: tuple[str, ...] = ()) -> str:
    """16 hex digits of the SHA-256 of a run spec's dict without the dotted fields ``ignore`` (those a resumed run
    may change); a checkpoint records it and ``--resume`` requires the same."""
    d = json.loads(json.dumps(spec))
    for path in ignore:
        *parents, last = path.split(".")
        node = d
        for p in parents:
            node = node.get(p, {}) if isinstance(node, dict) else {}
        if isinstance(node, dict):
            node.pop(last, None)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def write_log(out: Path, history: list[dict[str, Any]]) -> None:
    """``out/log.jsonl``: one JSON object per iteration (a run appends to it as it goes)."""
    atomic.write_text(Path(out) / LOG, "".join(json.dumps(h) + "\n" for h in history))


def write_summary(out: Path, *, scene: str, method: str, loss: str, initial_per_view: list[float],
                  final_per_view: list[float], history: list[dict[str, Any]], seconds: dict[str, float],
                  final_render: dict[str, Any], extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write ``out/summary.json`` (every method; the only writer) and return it.

    ``initial_per_view`` / ``final_per_view``: the loss of the initial render and of the final render of each view
    at the target spp; ``seconds``: named wall-clock seconds, written as ``seconds_<name>`` (``setup`` always;
    ``ours``: ``warm_start``, ``stage1``, ``stage2``, ``optimisation``; baselines: ``method``);
    ``final_render``: integrator, spp and seed of the final render; ``extra``: method-specific keys."""
    doc: dict[str, Any] = {
        "scene": scene,
        "method": method,
        "iterations": {f"stage{st}": sum(1 for h in history if h.get("stage", 1) == st) for st in (1, 2)},
        "loss": loss,
        "initial_loss_high_spp": float(np.mean(initial_per_view)),
        "final_loss_high_spp": float(np.mean(final_per_view)),
        "final_loss_per_view": [float(x) for x in final_per_view],
        **{f"seconds_{k}": float(v) for k, v in seconds.items()},
        # seconds of the gradient steps only (Stage 2: without its pseudo-ground-truth renders and inpainting)
        "seconds_iterations": float(sum(h.get("seconds", 0.0) for h in history)),
        "nonfinite_grads_total": int(sum(h.get("nonfinite_grads", 0) for h in history)),
        "final_render": final_render,
        **(extra or {}),
    }
    atomic.write_json(Path(out) / SUMMARY, doc)
    return doc


# --------------------------------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------------------------------

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


def config_layout(cfg: dict[str, Any], run_dir: Path) -> int:
    """The layout version of a parsed config.toml (module doc): 2 (run spec) or 1 (``[run]`` table)."""
    if "spec_version" in cfg:
        v = cfg["spec_version"]
        if v != CONFIG_VERSION:
            raise CamoError(f"{run_dir / CONFIG}: spec_version {v!r} is not {CONFIG_VERSION} (written by another camo "
                            "version; use that version or run it again)")
        return v
    if isinstance(cfg.get("run"), dict):
        return 1
    raise CamoError(f"{run_dir / CONFIG}: neither spec_version nor a [run] table (not a config.toml of camo optimize)")


def spec_of_config(cfg: dict[str, Any], run_dir: Path) -> dict[str, Any]:
    """The run spec's dict of a version-2 config.toml (the provenance tables removed); CamoError for version 1."""
    if config_layout(cfg, run_dir) != CONFIG_VERSION:
        raise CamoError(f"{run_dir / CONFIG} was written by camo before run specs; its run directory evaluates but "
                        "cannot be re-run from it: run `camo optimize` again with the same flags")
    return {k: v for k, v in cfg.items() if k not in PROVENANCE}


def _run_table(cfg: dict[str, Any], run_dir: Path) -> dict[str, Any]:
    """Method, ablate and appearance as one table, for either layout."""
    return cfg if config_layout(cfg, run_dir) == CONFIG_VERSION else cfg["run"]


def appearance_from_config(cfg: dict[str, Any], run_dir: Path):
    from optimizer.rendering.appearance import AppearanceConfig

    raw = _run_table(cfg, run_dir).get("appearance", {})
    if not isinstance(raw, dict):
        raise CamoError(f"{run_dir / 'config.toml'}: [{'run.' if 'run' in cfg else ''}appearance] must be a table")
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

    @property
    def condition(self):
        """The run's condition (:mod:`optimizer.assets.conditions`): its id and label in every table."""
        from optimizer.assets.conditions import condition

        return condition(self.method, self.ablation)

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

    def recorded_plan(self) -> "RecordedPlan":
        """What the run recorded about its effect plan (:func:`recorded_plan`)."""
        return recorded_plan(self.config, self.summary())

    def asset(self) -> Asset:
        """The result: ``result.ply`` (world space, pose and displacement applied) and ``maps/*.npy`` as rendered."""
        verts, faces, uvs = read_ply(self.path / "result.ply")
        maps = {"albedo": read_map(self.path, "albedo", 3)}
        for name in ("metallic", "roughness", "transmittance"):
            maps[name] = read_map(self.path, name, 1)
        a = Asset(str(self.path), verts, faces, uvs, maps, float(self.app.eta), not self.app.bsdf, "clamp", "scene")
        check_maps(a, self.name, "{label}: maps/{name}.npy")
        return a


@dataclasses.dataclass(frozen=True)
class RecordedPlan:
    """A run's effect plan as recorded, whatever layout wrote it (read by :func:`recorded_plan`).

    ``training``: the integrator the run optimised with (``config.toml`` ``[plan].integrator``); ``render``: the
    integrator of its final render (``summary.json`` ``final_render.integrator``, or a per-purpose integrator of a
    ``plan`` record in ``summary.json``); ``reasons``: the planner's lines; ``raw``: every plan record found, by
    source (``config`` / ``summary``), for readers that want more. ``None`` / empty where the run recorded none."""

    training: dict[str, Any] | None
    render: dict[str, Any] | None
    reasons: tuple[str, ...]
    raw: dict[str, Any]

    @property
    def max_depth(self) -> int | None:
        """The deepest ``max_depth`` any recorded integrator names (None: none names one; -1 = unbounded)."""
        depths = [_int(i.get("max_depth")) for i in (self.training, self.render) if isinstance(i, dict)]
        depths = [d for d in depths if d is not None]
        if not depths:
            return None
        return -1 if -1 in depths else max(depths)


#: Keys a per-purpose plan record may use for the render of results (newest layouts first).
_RENDER_PURPOSES = ("evaluate", "evaluation", "render", "final_render")


def recorded_plan(config: dict[str, Any], summary: dict[str, Any]) -> RecordedPlan:
    """The plan a run recorded, from its parsed ``config.toml`` and ``summary.json``: one reader, so a change of
    what runs record (a measured planner adding its own ``plan`` record to ``summary.json``) is handled here.

    ``summary.json``'s ``plan`` record (when present) wins over ``config.toml``'s ``[plan]`` table: it may name an
    ``integrator`` and per-purpose records (``{"evaluate": {"integrator": {...}}, ...}``); the render integrator is
    the first of those purposes found, else ``final_render.integrator``."""
    cfg_plan = config.get("plan") if isinstance(config.get("plan"), dict) else {}
    sum_plan = summary.get("plan") if isinstance(summary.get("plan"), dict) else {}
    raw = {k: v for k, v in (("config", cfg_plan), ("summary", sum_plan)) if v}

    def integrator_of(rec: Any) -> dict[str, Any] | None:
        if isinstance(rec, dict) and isinstance(rec.get("integrator"), dict) and rec["integrator"].get("type"):
            return dict(rec["integrator"])
        if isinstance(rec, dict) and isinstance(rec.get("type"), str):
            return dict(rec)
        return None

    training = integrator_of(sum_plan) or integrator_of(cfg_plan)
    render = next((i for i in (integrator_of(sum_plan.get(p)) for p in _RENDER_PURPOSES) if i), None)
    if render is None:
        render = integrator_of(summary.get("final_render"))
    reasons = sum_plan.get("reasons") or cfg_plan.get("reasons") or ()
    reasons = tuple(str(r) for r in reasons) if isinstance(reasons, (list, tuple)) else (str(reasons),)
    return RecordedPlan(training, render, reasons, raw)


def _int(v: Any) -> int | None:
    try:
        return int(v) if v is not None and not isinstance(v, bool) else None
    except (TypeError, ValueError):
        return None


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
    run = _run_table(cfg, run_dir)
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
