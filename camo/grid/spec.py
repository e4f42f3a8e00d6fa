"""The grid file (TOML) and the cells it expands to.

Schema (every key but ``scenes`` is optional; unknown keys are errors)::

    name      = "table2"                       # free text, shown by `camo grid status`
    scenes    = ["gravel", "split:chair", "packs/yard.toml"]   # built-in ENV, ENV:OBJECT, or a pack file
    objects   = ["utility_box", "vase"]        # built-in primitives, crossed with the plain ENV scenes only
    methods   = ["ours", "transparent", "mean", "random"]      # `camo optimize --method` names (default ours)
    ablations = ["none", "pose", "displacement", "bsdf", "transmittance", "inpainting", "pose,displacement"]
                                               # crossed with method "ours" only (default ["none"])
    seeds     = [0, 1, 2]                      # `camo optimize --seed` (default [0])

    [optimize]                                 # any `camo optimize` option (long name, - or _): for every
    iterations = 50                            # method that uses it (one none of them uses gets a note)
    resolution = 128
    views = 16
    stages = "1,2"                             # lists are joined with commas: stages = [1, 2]
    no-planner = false                         # flags are booleans

    [optimize.ganmouflage]                     # per-method overrides (a table named after a method; an option
    iterations = 2000                          # the method does not use is an error)

    [evaluate]                                 # any `camo evaluate` option
    views = 16
    spp = 64
    jitter = 0.25
    metrics = ["psnr", "ssim", "lpips_proxy", "sifid_proxy"]
    seed = 0                                   # the evaluation seed: the same novel views for every cell

Cells = scenes (x objects for plain built-in names) x methods x (ablations for "ours") x seeds. Pack paths are
relative to the grid file. Options the grid sets itself are refused: ``out``, ``resume``, ``overwrite``,
``quiet``, ``threads`` (cores // workers), and the axes ``method``, ``ablate``, ``seed`` (use ``methods``,
``ablations``, ``seeds``).

The ``[optimize]`` options are run options (:mod:`optimizer.optimise.options`: the same names, types and ranges as
``camo optimize``'s flags): each cell's ``{option: value}`` mapping becomes its **run spec**
(:meth:`optimizer.optimise.spec.RunSpec.from_options`) once, when the grid is loaded; the cell stores the spec
(``Cell.spec``, its ``to_dict``) and its worker runs it as it is (:func:`optimizer.optimise.run.run`). The
``[evaluate]`` options are evaluation settings (:mod:`evaluation.settings`: the same names, types and ranges as
``camo evaluate``'s setting flags): the cell stores their ``{option: value}`` mapping (``Cell.evaluate``), and
:meth:`evaluation.settings.EvalSettings.from_options` makes the settings of it, once when the grid is loaded (a
bad key or value is one line naming the grid's key) and again in the worker, which passes them to
:func:`evaluation.evaluate.evaluate`. No command line is made or parsed in between.

Each cell has a **key**: the first 16 hex digits of the SHA-256 of its resolved options (scene as written plus
the pack file's SHA-256, method, ablation, seed, and the optimise and evaluate options the grid file sets, each
converted by its parser and left out when it equals its absent value; not the thread count). A cell with the same
key is the same work: a finished one is never redone. The key is computed as it was before cells held run specs,
so the keys of grid folders written then still match.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import tomllib
from pathlib import Path
from typing import Any

from camo_base.errors import CamoError

#: Version of the key derivation; bump it only if the meaning of a resolved config changes.
KEY_VERSION = 1
TOP_KEYS = ("name", "scenes", "objects", "methods", "ablations", "seeds", "optimize", "evaluate")
#: Options the grid manages itself, with the reason given to the user.
RESERVED = {
    "optimize": {
        "scene": "use `scenes = [...]`",
        "out": "the grid places every run under DIR/cells/<key>/",
        "method": "use `methods = [...]`",
        "ablate": "use `ablations = [...]`",
        "seed": "use `seeds = [...]`",
        "threads": "set by camo grid (cores // workers)",
        "resume": "camo grid resumes partial cells itself",
        "overwrite": "camo grid never overwrites finished cells",
        "quiet": "camo grid runs cells quietly",
    },
    "evaluate": {
        "run_dirs": "the grid evaluates each cell's run",
        **{k: "an input of `camo evaluate`, not a setting: the grid evaluates each cell's run"
           for k in ("asset", "triplets", "inputs", "scene", "method", "seconds", "placement")},
        "out": "the grid places every evaluation under DIR/cells/<key>/eval/",
        "threads": "set by camo grid (cores // workers)",
        "quiet": "camo grid runs cells quietly",
    },
}


@dataclasses.dataclass(frozen=True)
class Cell:
    """One optimise + evaluate job of a grid."""

    key: str
    name: str  # run directory name (the `run` column of the metrics), unique within the grid
    scene: str  # the `camo optimize` SCENE argument (pack paths absolute)
    scene_label: str  # the scene as written in the grid (ENV:OBJECT combined)
    method: str  # the method as the grid names it (ganmouflage-paper stays so; its spec says ganmouflage)
    ablation: str  # "none" or a sorted comma list
    seed: int
    spec: dict[str, Any]  # the run spec (RunSpec.to_dict()): what the cell's optimisation runs
    evaluate: tuple[tuple[str, Any], ...]  # the evaluation settings' options (evaluation.settings): (name, value), sorted

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["evaluate"] = dict(self.evaluate)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Cell":
        if "spec" not in d and "optimize_argv" in d:
            raise CamoError("this grid output was written by camo before cells held run specs (cells hold command "
                            "lines); convert it by running `camo grid run GRID --out DIR` once with its grid file "
                            "(finished cells keep their keys and are not run again)")
        return cls(key=d["key"], name=d["name"], scene=d["scene"], scene_label=d["scene_label"], method=d["method"],
                   ablation=d["ablation"], seed=int(d["seed"]), spec=dict(d["spec"]),
                   evaluate=tuple(sorted(d["evaluate"].items())))  # (an older cell.json's evaluate_argv: unused)

    def run_spec(self):
        """The cell's :class:`optimizer.optimise.spec.RunSpec` (CamoError when the stored spec is not valid)."""
        from optimizer.optimise.spec import RunSpec

        return RunSpec.from_dict(self.spec, where=f"cell {self.name}").validate()

    # ------------------------------------------------------------------------------------------------------
    # where the cell's results go, and its evaluation command line
    # ------------------------------------------------------------------------------------------------------

    def run_dir(self, cell_dir: Path) -> Path:
        return Path(cell_dir) / "run" / self.name

    def eval_dir(self, cell_dir: Path) -> Path:
        return Path(cell_dir) / "eval" / self.name  # named after the cell: the report's settings list it

    def evaluate_command(self, cell_dir: Path, threads: int | None) -> list[str]:
        """The ``camo evaluate`` command line equivalent to the cell's evaluation, for its log (the worker calls
        :func:`evaluation.evaluate.evaluate` with :meth:`evaluation_settings`, made from the options as data)."""
        from evaluation.settings import OPTIONS

        argv = ["evaluate", str(self.run_dir(cell_dir)), "--out", str(self.eval_dir(cell_dir))]
        argv += [OPTIONS[n].flag if v is True else f"{OPTIONS[n].flag}={v}" for n, v in self.evaluate]
        return argv + ["--quiet"] + (["--threads", str(threads)] if threads else [])

    def evaluation_settings(self, threads: int | None = None):
        """The cell's :class:`evaluation.settings.EvalSettings` (quiet, the worker's threads), made from its
        options (:meth:`~evaluation.settings.EvalSettings.from_options`, as ``camo evaluate`` makes them of its
        flags)."""
        from evaluation.settings import EvalSettings

        return EvalSettings.from_options({**dict(self.evaluate), "threads": threads, "quiet": True})


@dataclasses.dataclass
class Grid:
    path: Path
    name: str
    cells: list[Cell]
    source: str  # the grid file's text
    notes: list[str] = dataclasses.field(default_factory=list)  # what `camo grid run` says before it starts

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "path": str(self.path), "cells": [c.to_dict() for c in self.cells]}


# --------------------------------------------------------------------------------------------------------------
# options of `camo optimize` (the run options) and `camo evaluate` (the evaluation settings), as data
# --------------------------------------------------------------------------------------------------------------


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _check_key(section: str, raw_key: str, known, where: str) -> str:
    dest = str(raw_key).replace("-", "_")
    reserved = RESERVED[section]
    if dest in reserved:
        raise CamoError(f"{where}: [{section}] {raw_key} is set by the grid: {reserved[dest]}")
    if dest not in known:
        names = ", ".join(sorted(k.replace("_", "-") for k in known if k not in reserved))
        raise CamoError(f"{where}: [{section}] unknown option {raw_key!r}; `camo {section}` options: {names}")
    return dest


def _optimize_values(table: dict[str, Any], where: str) -> dict[str, Any]:
    """One ``[optimize]`` table as run option values (:meth:`optimizer.optimise.options.Option.convert`: the types,
    choices and ranges of ``camo optimize``'s flags), options equal to their absent value left out (the same work,
    the same cell key)."""
    from optimizer.optimise.options import ABSENT, KEY_STABLE, OPTIONS

    absent = {**ABSENT, **KEY_STABLE}
    values: dict[str, Any] = {}
    for raw_key, value in table.items():
        dest = _check_key("optimize", raw_key, set(OPTIONS) | set(RESERVED["optimize"]), where)
        try:
            v = OPTIONS[dest].convert(value, str(raw_key))
        except CamoError as exc:
            raise CamoError(f"{where}: [optimize] {exc}") from None
        if v == absent.get(dest, False if OPTIONS[dest].kind is bool else None):
            continue
        values[dest] = v
    return values


def _evaluate_values(table: dict[str, Any], where: str) -> dict[str, Any]:
    """One ``[evaluate]`` table as evaluation setting values (:meth:`evaluation.settings.EvalOption.convert`: the
    types and ranges of ``camo evaluate``'s flags), options equal to their default left out (the same work, the
    same cell key), checked by making the settings of them (:meth:`evaluation.settings.EvalSettings.from_options`);
    a problem is one line naming the grid's key."""
    from camo_base.errors import renamed
    from evaluation.settings import OPTIONS, EvalSettings

    values: dict[str, Any] = {}
    keys: dict[str, str] = {}
    for raw_key, value in table.items():
        dest = _check_key("evaluate", raw_key, set(OPTIONS) | set(RESERVED["evaluate"]), where)
        try:
            v = OPTIONS[dest].convert(value, str(raw_key))
        except CamoError as exc:
            raise CamoError(f"{where}: [evaluate] {exc}") from None
        keys[dest] = str(raw_key)
        if v == OPTIONS[dest].default:
            continue
        values[dest] = v
    try:
        EvalSettings.from_options(values)
    except CamoError as exc:
        raise CamoError(f"{where}: [evaluate] {renamed(exc, keys)}") from None
    return values


# --------------------------------------------------------------------------------------------------------------
# the grid file
# --------------------------------------------------------------------------------------------------------------


def _str_list(doc: dict, key: str, where: str, default: list | None = None) -> list[str]:
    if key not in doc:
        if default is None:
            raise CamoError(f"{where}: `{key} = [...]` is missing")
        return list(default)
    v = doc[key]
    if isinstance(v, str):
        v = [v]
    if not isinstance(v, list) or not v or not all(isinstance(x, str) and x.strip() for x in v):
        raise CamoError(f"{where}: {key} must be a non-empty list of strings, got {v!r}")
    items = [x.strip() for x in v]
    dup = sorted({x for x in items if items.count(x) > 1})
    if dup:
        raise CamoError(f"{where}: {key} lists {', '.join(dup)} more than once")
    return items


def _ablations(doc: dict, where: str) -> list[str]:
    from optimizer.assets.conditions import parse_ablations

    raw = doc.get("ablations", ["none"])
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list) or not raw:
        raise CamoError(f"{where}: ablations must be a non-empty list, got {raw!r}")
    out = []
    for item in raw:
        if isinstance(item, list):
            if not all(isinstance(x, str) for x in item):
                raise CamoError(f"{where}: ablations: {item!r} must list parameter names")
            item = ",".join(item)
        if not isinstance(item, str):
            raise CamoError(f"{where}: ablations: {item!r} is not a string")
        text = item.strip()
        if text in ("", "none"):
            out.append("none")
            continue
        try:
            parts = parse_ablations(text, field="ablations")
        except CamoError as exc:
            raise CamoError(f"{where}: {exc}") from None
        out.append(",".join(parts))
    dup = sorted({x for x in out if out.count(x) > 1})
    if dup:
        raise CamoError(f"{where}: ablations list {', '.join(dup)} more than once")
    return out


def _seeds(doc: dict, where: str) -> list[int]:
    raw = doc.get("seeds", [0])
    if isinstance(raw, int) and not isinstance(raw, bool):
        raw = [raw]
    if not isinstance(raw, list) or not raw or not all(isinstance(s, int) and not isinstance(s, bool) for s in raw):
        raise CamoError(f"{where}: seeds must be a non-empty list of integers, got {raw!r}")
    if any(s < 0 for s in raw):
        raise CamoError(f"{where}: seeds must be >= 0, got {raw!r}")
    if len(set(raw)) != len(raw):
        raise CamoError(f"{where}: seeds list a seed more than once: {raw!r}")
    return list(raw)


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _scene_entries(scenes: list[str], objects: list[str] | None, base: Path, where: str
                   ) -> list[tuple[str, str, str | None]]:
    """``[(scene argument, scene label, pack sha256 or None)]`` for the scenes x objects axis."""
    from optimizer.scenes import builtin_scenes
    from optimizer.scenes.primitives import PRIMITIVES

    if objects is not None:
        bad = [o for o in objects if o not in PRIMITIVES]
        if bad:
            raise CamoError(f"{where}: unknown object(s) {', '.join(bad)}; built-in objects: "
                            f"{', '.join(sorted(PRIMITIVES))}")
    out = []
    plain = 0
    for s in scenes:
        env, sep, obj = s.partition(":")
        if env in builtin_scenes.SCENES:
            if sep:
                if obj not in PRIMITIVES:
                    raise CamoError(f"{where}: scene {s!r}: unknown object {obj!r}; built-in objects: "
                                    f"{', '.join(sorted(PRIMITIVES))}")
                out.append((s, s, None))
            elif objects is None:
                out.append((s, s, None))
            else:
                plain += 1
                out += [(f"{s}:{o}", f"{s}:{o}", None) for o in objects]
            continue
        p = Path(s).expanduser()
        p = p if p.is_absolute() else (base / p)
        if s.endswith(".toml") or p.is_file():
            if not p.is_file():
                raise CamoError(f"{where}: scene pack not found: {p}")
            out.append((str(p.resolve()), s, _file_sha256(p)))
            continue
        raise CamoError(f"{where}: unknown scene {s!r}: not a built-in scene ({', '.join(builtin_scenes.SCENES)}) "
                        "and not a pack file")
    if objects is not None and plain == 0:
        raise CamoError(f"{where}: objects are crossed with plain built-in scene names only, and scenes has none")
    labels = [lab for _, lab, _ in out]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise CamoError(f"{where}: scene {', '.join(dup)} appears more than once after crossing with objects")
    return out


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_.") or "x"


def cell_key(doc: dict[str, Any]) -> str:
    blob = json.dumps({"v": KEY_VERSION, **doc}, sort_keys=True, separators=(",", ":"), default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def load_grid(path: str | Path) -> Grid:
    """Parse and validate a grid file; CamoError (one line) for anything wrong, before any work starts."""
    from optimizer.optimise.methods import METHOD_NAMES
    from optimizer.optimise.spec import check_options_apply, option_applies

    path = Path(path).expanduser()
    if not path.is_file():
        raise CamoError(f"grid file not found: {path}")
    where = str(path)
    try:
        source = path.read_text(encoding="utf-8")
        doc = tomllib.loads(source)
    except UnicodeDecodeError:
        raise CamoError(f"{where}: not a UTF-8 text file") from None
    except tomllib.TOMLDecodeError as exc:
        raise CamoError(f"{where}: not valid TOML ({_one_line(exc)})") from None
    unknown = [k for k in doc if k not in TOP_KEYS]
    if unknown:
        raise CamoError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(TOP_KEYS)}")
    name = doc.get("name", path.stem)
    if not isinstance(name, str):
        raise CamoError(f"{where}: name must be a string")
    scenes = _str_list(doc, "scenes", where)
    objects = _str_list(doc, "objects", where) if "objects" in doc else None
    methods = _str_list(doc, "methods", where, ["ours"])
    bad = [m for m in methods if m not in METHOD_NAMES]
    if bad:
        raise CamoError(f"{where}: unknown method(s) {', '.join(bad)}; `camo optimize --method` takes: "
                        f"{', '.join(METHOD_NAMES)}")
    ablations = _ablations(doc, where)
    if ablations != ["none"] and "ours" not in methods:
        raise CamoError(f"{where}: ablations apply to method \"ours\" only, and methods does not list it")
    seeds = _seeds(doc, where)

    sections: dict[str, dict[str, Any]] = {}
    for section in ("optimize", "evaluate"):
        t = doc.get(section, {})
        if not isinstance(t, dict):
            raise CamoError(f"{where}: [{section}] must be a table")
        sections[section] = t
    per_method = {k: v for k, v in sections["optimize"].items() if isinstance(v, dict)}
    for m in per_method:
        if m not in METHOD_NAMES:
            raise CamoError(f"{where}: [optimize.{m}]: a sub-table must be named after a method "
                            f"({', '.join(METHOD_NAMES)})")
    base_opt = {k.replace("-", "_"): v for k, v in sections["optimize"].items() if not isinstance(v, dict)}
    eval_values = _evaluate_values(sections["evaluate"], where)
    base_values = _optimize_values(base_opt, where)
    unused = [d.replace("_", "-") for d in base_opt
              if d in base_values and not any(option_applies(m, d) for m in methods)]
    # Not an error: grid files written before run specs may carry them (and their cells' keys include them)
    notes = [f"[optimize] {', '.join(unused)} {'applies' if len(unused) == 1 else 'apply'} to none of this grid's "
             f"methods ({', '.join(methods)}): no cell uses {'it' if len(unused) == 1 else 'them'}"] if unused else []
    opt_by_method: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {}
    for m in methods:
        own = {k.replace("-", "_"): v for k, v in per_method.get(m, {}).items()}
        sub_where = where if m not in per_method else f"{where} (method {m})"
        values = _optimize_values({**base_opt, **own}, sub_where)
        try:
            check_options_apply(m, own)
        except CamoError as exc:
            raise CamoError(f"{where}: [optimize.{m}] {exc}") from None
        # the key takes every option the grid gives the method (as keys always did); the spec those it uses
        opt_by_method[m] = values, {d: v for d, v in values.items() if option_applies(m, d)}

    entries = _scene_entries(scenes, objects, path.parent, where)
    cells: list[Cell] = []
    for scene_arg, label, sha in entries:
        for m in methods:
            opt_values, used = opt_by_method[m]
            for abl in (ablations if m == "ours" else ["none"]):
                for seed in seeds:
                    key = cell_key({"scene": label, "pack_sha256": sha, "method": m, "ablation": abl, "seed": seed,
                                    "optimize": opt_values, "evaluate": eval_values})
                    abl_part = "" if abl == "none" else "-wo-" + abl.replace(",", "+")
                    scene_part = Path(label).stem if sha else label
                    nm = _slug(f"{scene_part}__{m}{abl_part}__s{seed}")
                    options = {"scene": scene_arg, "method": m, "seed": seed, **used,
                               **({"ablate": abl} if abl != "none" else {})}
                    spec = cell_spec(options, f"{where}: cell {nm}")
                    cells.append(Cell(key=key, name=nm, scene=scene_arg, scene_label=label, method=m, ablation=abl,
                                      seed=seed, spec=spec, evaluate=tuple(sorted(eval_values.items()))))
    names = [c.name for c in cells]
    if len(set(names)) != len(names):  # two packs with one file name: make the run names unique
        cells = [dataclasses.replace(c, name=f"{c.name}__{c.key[:8]}") if names.count(c.name) > 1 else c
                 for c in cells]
    return Grid(path=path.resolve(), name=name, cells=cells, source=source, notes=notes)


def cell_spec(options: dict[str, Any], where: str) -> dict[str, Any]:
    """The run spec (``to_dict``) of a cell's run options (:meth:`optimizer.optimise.spec.RunSpec.from_options`);
    a problem is one line naming the grid's keys."""
    from camo_base.errors import renamed
    from optimizer.optimise.spec import RunSpec, grid_names

    try:
        return RunSpec.from_options(options).to_dict()
    except CamoError as exc:
        raise CamoError(f"{where}: {renamed(exc, grid_names(options.get('method')))}") from None


def check_metrics_available(grid: Grid) -> None:
    """CamoError (one line, naming the fix) when a metric the grid's ``[evaluate]`` asks for cannot run on this
    machine (e.g. ``lpips`` without its installed weights): checked before ``camo grid run`` starts any cell, so
    a grid does not optimise for hours and then fail every evaluation. Loads nothing."""
    from evaluation.evaluate import select_metrics, weights_of

    seen: set[tuple] = set()
    for c in grid.cells:
        if c.evaluate in seen:
            continue
        seen.add(c.evaluate)
        try:
            settings = c.evaluation_settings()
            select_metrics(settings.metrics, weights_of(settings))
        except CamoError as exc:
            raise CamoError(f"{grid.path}: [evaluate]: {exc}") from None

