"""The run directory (output of ``camo optimize``; layout in CONTRIBUTING.md): the one owner of its files.

Writing: :class:`RunTransaction` (a run writes into a staging folder beside the run directory and moves it into
place when it finished; a resume continues a checkpoint), :func:`write_config` (``config.toml`` = the
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
import os
import shutil
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from camo_base import atomic
from optimizer.assets.asset import Asset, check_maps
from optimizer.scenes.bsdf_maps import MAPS
from camo_base.errors import CamoError, SettingError, literal

#: Files a run directory must have for its result to be read (besides config.toml).
RESULT_FILES = (*(f"maps/{name}.npy" for name, m in MAPS.items() if m.absent is None), "result.ply", "summary.json")
CONFIG = "config.toml"
SUMMARY = "summary.json"
LOG = "log.jsonl"
CHECKPOINT = "checkpoint.npz"
#: Layout version of config.toml written now (``spec_version``; the run spec's version).
CONFIG_VERSION = 2
#: Tables of config.toml that are provenance, not the run spec (``history``: one entry per start or resume).
PROVENANCE = ("versions", "history", "plan", "fingerprint", "baseline")


# --------------------------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------------------------


def staging_dir(out: str | Path) -> Path:
    """Where a run into ``out`` writes until it finished: the sibling ``.<name>.partial``."""
    out = Path(out)
    return out.parent / f".{out.name}.partial"


def _backup_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.old"


def _lock_file(out: Path) -> Path:
    return out.parent / f".{out.name}.lock"


def resumable(out: str | Path) -> Path | None:
    """The folder a ``--resume`` of ``out`` continues: its unfinished staging folder, else ``out`` itself, when it
    holds a checkpoint; None when neither does."""
    for d in (staging_dir(out), Path(out)):
        if (d / CHECKPOINT).is_file():
            return d
    return None


def major_version(version: str) -> str:
    """The part of a version that says compatibility: ``3`` of ``3.9.1``, ``0.1`` of ``0.1.0`` (0.y: y breaks)."""
    parts = str(version).split(".")
    return ".".join(parts[:2]) if parts[0] == "0" and len(parts) > 1 else parts[0]


#: Libraries whose major version a resumed run must share with the run it continues.
RESUME_VERSIONS = ("camo", "mitsuba")


def resume_mismatch(cfg: dict[str, Any] | None, current: dict[str, str]) -> str | None:
    """Why a run recorded with ``cfg`` (its parsed config.toml; None: none) should not be continued by software of
    versions ``current``: another (or no) ``spec_version``, or another major version of camo or Mitsuba than its
    first attempt recorded; None when it may."""
    if cfg is None:
        return "it has no config.toml"
    if cfg.get("spec_version") != CONFIG_VERSION:
        v = cfg.get("spec_version")
        return (f"its config.toml has spec_version {v!r}, this camo writes {CONFIG_VERSION}" if v is not None else
                "its config.toml has no spec_version (written before run specs)")
    recorded = cfg.get("versions") if isinstance(cfg.get("versions"), dict) else {}
    diff = [f"{lib} {recorded.get(lib, 'unknown')} (now {current.get(lib)})" for lib in RESUME_VERSIONS
            if major_version(str(recorded.get(lib, "?"))) != major_version(str(current.get(lib)))]
    return f"it was recorded by {', '.join(diff)}" if diff else None


class RunTransaction:
    """A run directory written as one transaction: the run writes into :attr:`path` (the staging folder
    :func:`staging_dir`) and :meth:`commit` moves it to ``out`` in one rename, replacing an old run there
    (an atomic exchange where Linux offers it, else two renames with a recoverable ``.<name>.old``). Until then
    ``out`` is untouched, byte for byte: a run that fails (an exception, Ctrl-C, a kill) leaves the old run as it
    was. A failed run that wrote a checkpoint leaves its staging folder, which ``--resume`` continues (an unfinished
    attempt that a resume continued is always kept); otherwise the staging folder is removed.

    ``resume``: continue the unfinished staging folder when there is one (a crashed or killed earlier attempt),
    else a copy of ``out``'s finished run (a resume that fails leaves both as they were). A resume is refused
    (SettingError naming ``resume`` / ``accept_versions``) when the run was recorded by another spec layout or major
    version of camo or Mitsuba (:func:`resume_mismatch`), unless ``accept_versions``. One writer at a time: a lock
    file ``.<name>.lock`` beside ``out``.
    """

    def __init__(self, out: str | Path, resume: bool = False, overwrite: bool = False,
                 accept_versions: bool = False, current_versions: dict[str, str] | None = None):
        self.out = Path(out)
        self.path = staging_dir(self.out)
        self.resume, self.overwrite, self.accept_versions = resume, overwrite, accept_versions
        self.current_versions = current_versions
        self.previous: dict[str, Any] | None = None  # the config.toml of the run a resume continues
        self._lock_fd: int | None = None
        self._continued = False
        self._checkpoint_at_start: tuple[int, int] | None = None
        self.committed = False

    # ------------------------------------------------------------------------------------------------------
    def __enter__(self) -> "RunTransaction":
        self.begin()
        return self

    def __exit__(self, kind, exc, tb) -> bool:
        if kind is None:
            self.commit()
        else:
            self.abort()
        return False

    def begin(self) -> Path:
        """Check ``out``, take the lock and make the staging folder (module doc); returns it."""
        out = self.out
        if out.exists() and not out.is_dir():
            raise SettingError(f"{{0}} {literal(out)} exists and is not a folder", "out")
        out.parent.mkdir(parents=True, exist_ok=True)
        self._lock()
        try:
            self._recover()
            if self.resume:
                self._begin_resume()
            else:
                self._begin_fresh()
        except BaseException:
            self._unlock()
            raise
        return self.path

    def _lock(self) -> None:
        import fcntl

        fd = os.open(_lock_file(self.out), os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 128, 0).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise SettingError(f"{literal(self.out)} is being written by {literal(holder)}; wait for it or use "
                               "another {0}", "out") from None
        except OSError:  # a file system without locks: run unlocked
            pass
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"camo (pid {os.getpid()})".encode(), 0)
        self._lock_fd = fd

    def _unlock(self) -> None:
        if self._lock_fd is not None:
            _lock_file(self.out).unlink(missing_ok=True)
            os.close(self._lock_fd)
            self._lock_fd = None

    def _recover(self) -> None:
        """Finish a commit a kill interrupted between its two renames (systems without an atomic exchange)."""
        old = _backup_dir(self.out)
        if old.exists():
            if not self.out.exists():
                os.rename(old, self.out)  # the new run never arrived: the old one goes back
            else:
                shutil.rmtree(old, ignore_errors=True)  # the new run is in place: drop the old one

    def _begin_resume(self) -> None:
        source = resumable(self.out)
        if source is None:
            raise SettingError(f"{{0}}: no {CHECKPOINT} in {literal(self.out)} (nor an unfinished run beside it)",
                               "resume")
        cfg = None
        if (source / CONFIG).is_file():
            try:
                cfg = read_config(source)
            except CamoError:
                cfg = None
        if cfg is not None and "spec_version" not in cfg and isinstance(cfg.get("run"), dict):
            raise SettingError(f"{{0}}: {literal(self.out)} was written by camo before run specs (config.toml layout "
                               "1); it cannot be resumed: start a new run (its finished files still evaluate)", "resume")
        if not self.accept_versions:
            from camo_base.provenance import versions

            why = resume_mismatch(cfg, self.current_versions or versions())
            if why is not None:
                raise SettingError(f"{{0}}: {literal(self.out)} is not resumed: {literal(why)}; start a new run, or "
                                   "add {1} to continue it anyway", "resume", "accept_versions")
        self.previous = cfg
        self._continued = source == self.path  # an unfinished attempt: kept whatever happens
        if not self._continued:  # a finished run: continue a copy of it (out stays as it is until the end)
            shutil.rmtree(self.path, ignore_errors=True)
            shutil.copytree(source, self.path, symlinks=True)
        self._checkpoint_at_start = _stat(self.path / CHECKPOINT)

    def _begin_fresh(self) -> None:
        if self.path.exists():
            if (self.path / CHECKPOINT).is_file() and not self.overwrite:
                raise SettingError(f"{literal(self.out)} has an unfinished run (its checkpoint is in "
                                   f"{literal(self.path)}); use {{0}} to continue it, {{1}} to start again, or another "
                                   "{2}", "resume", "overwrite", "out")
            shutil.rmtree(self.path)
        if self.out.is_dir() and any(self.out.iterdir()) and not self.overwrite:
            raise SettingError(f"run directory {literal(self.out)} is not empty; use {{0}} to continue it, {{1}} to "
                               "replace it, or another {2}", "resume", "overwrite", "out")
        self.path.mkdir(parents=True)

    def commit(self) -> Path:
        """Move the finished run into place (replacing an old run there); returns ``out``."""
        try:
            _fsync_dir(self.path)
            if self.out.is_dir() and not any(self.out.iterdir()):
                self.out.rmdir()
            if not self.out.exists():
                os.rename(self.path, self.out)
            elif _exchange(self.path, self.out):
                shutil.rmtree(self.path, ignore_errors=True)  # (now the old run)
            else:
                old = _backup_dir(self.out)
                os.rename(self.out, old)
                os.rename(self.path, self.out)
                shutil.rmtree(old, ignore_errors=True)
            _fsync_dir(self.out.parent)
            self.committed = True
        finally:
            self._unlock()
        return self.out

    def abort(self) -> None:
        """After a failure: keep the staging folder when it is an unfinished run a resume continued, or when this
        attempt wrote a checkpoint into it (``--resume`` continues it); else remove it. ``out`` is never
        touched."""
        try:
            progressed = _stat(self.path / CHECKPOINT) not in (None, self._checkpoint_at_start)
            if self.path.exists() and not self._continued and not progressed:
                shutil.rmtree(self.path, ignore_errors=True)
        finally:
            self._unlock()


def _stat(path: Path) -> tuple[int, int] | None:
    """``(size, mtime_ns)`` of a file, or None: whether a checkpoint was rewritten."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two directories in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``); False where unsupported."""
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


def provenance(current: dict[str, str], previous: dict[str, Any] | None, event: str,
               **more: Any) -> dict[str, Any]:
    """The ``[versions]`` and ``[[history]]`` tables of a config.toml: a new run records ``current`` as its versions;
    a resumed one keeps the versions it recorded first and appends this attempt to the history (``event``: start,
    resume; ``current`` versions, the time, ``more``). Provenance is appended, never rewritten."""
    import datetime

    entry = {"event": event, "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
             **{k: current[k] for k in ("camo", "mitsuba", "drjit", "threads") if k in current}, **more}
    if previous is None:
        return {"versions": current, "history": [entry]}
    versions = previous.get("versions") if isinstance(previous.get("versions"), dict) else current
    history = [h for h in previous.get("history", []) if isinstance(h, dict)]
    if not history:  # a run recorded before histories: its first attempt is what [versions] says
        history = [{"event": "start", **{k: versions[k] for k in ("camo", "mitsuba", "drjit", "threads")
                                         if k in versions}}]
    return {"versions": versions, "history": [*history, entry]}


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


def result_appearance(app, run_dir: Path):
    """The appearance the run's *result* renders with: its spec's (``config.toml``), except the shared index of
    refraction when the run's clear-glass search (``stage1.clear_candidate``, issue 29) kept clear glass: then
    ``summary.json``'s ``clear_search.chosen_eta`` (the spec holds the search's settings, not its outcome; the exported
    ``result.glb`` / ``result.obj`` carry the same value). CamoError (one line) for an unreadable record."""
    p = run_dir / SUMMARY
    try:
        summary = json.loads(p.read_text(encoding="utf-8")) if p.is_file() else {}
    except (OSError, ValueError):
        raise CamoError(f"{p}: not readable JSON") from None
    clear = summary.get("clear_search") if isinstance(summary, dict) else None
    if not clear:
        return app
    try:
        eta = float(clear["chosen_eta"])
        if not (math.isfinite(eta) and eta > 1.0):
            raise ValueError(eta)
    except (TypeError, KeyError, ValueError):
        raise CamoError(f"{p}: clear_search.chosen_eta must be an index of refraction > 1") from None
    return dataclasses.replace(app, eta=eta)


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
        maps = {}
        for name, m in MAPS.items():
            if m.absent is not None and not (self.path / "maps" / f"{name}.npy").is_file():
                maps[name] = np.float32(m.absent)  # a run written before the map existed: the renderer's default
            else:
                maps[name] = read_map(self.path, name, m.channels)
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
        raise CamoError(f"{run_dir}: incomplete run directory, missing {', '.join(missing)} (the run did not finish)")
    _check_complete(run_dir, cfg)
    app = result_appearance(app, run_dir)
    ablate = run.get("ablate", [])
    if isinstance(ablate, str):
        ablate = [a for a in ablate.split(",") if a]
    return RunDir(run_dir, run_dir.resolve().name, cfg, pack, app, str(run.get("method", "ours")),
                  tuple(sorted(str(a) for a in ablate)))


def _check_complete(run_dir: Path, cfg: dict[str, Any]) -> None:
    """CamoError (one line) for a run directory whose files are of different runs: ``summary.json`` written for
    another spec than ``config.toml`` (its fingerprint), or ``log.jsonl`` holding other iterations than
    ``summary.json`` counts -- what an interrupted ``--overwrite`` left before runs were transactions."""
    try:
        summary = json.loads((run_dir / SUMMARY).read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError, OSError) as exc:
        raise CamoError(f"{run_dir / SUMMARY}: not valid JSON ({exc})") from None
    if not isinstance(summary, dict):
        raise CamoError(f"{run_dir / SUMMARY}: not a JSON object")
    fp = (cfg.get("fingerprint") or {}).get("value") if isinstance(cfg.get("fingerprint"), dict) else None
    if cfg.get("spec_version") == CONFIG_VERSION and summary.get("fingerprint") and fp and summary["fingerprint"] != fp:
        raise CamoError(f"{run_dir}: incomplete run directory: summary.json is of another run than config.toml "
                        "(an interrupted overwrite?); run it again")
    counts = summary.get("iterations")
    log = run_dir / LOG
    if isinstance(counts, dict) and log.is_file():
        logged = {1: 0, 2: 0}
        for line in log.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if isinstance(rec, dict) and rec.get("stage", 1) in logged:
                logged[rec.get("stage", 1)] += 1
        expected = {st: int(counts.get(f"stage{st}", 0) or 0) for st in (1, 2)}
        if logged != expected:
            raise CamoError(f"{run_dir}: incomplete run directory: log.jsonl holds {logged[1]} + {logged[2]} "
                            f"iterations, summary.json says {expected[1]} + {expected[2]} (an interrupted run?); "
                            "run it again")


def is_run_dir(path: str | Path) -> bool:
    p = Path(path)
    return p.is_dir() and (p / "config.toml").is_file()
