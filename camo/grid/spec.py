"""The grid file (TOML) and the cells it expands to.

Schema (every key but ``scenes`` is optional; unknown keys are errors)::

    name      = "table2"                       # free text, shown by `camo grid status`
    scenes    = ["gravel", "split:chair", "packs/yard.toml"]   # built-in ENV, ENV:OBJECT, or a pack file
    objects   = ["utility_box", "vase"]        # built-in primitives, crossed with the plain ENV scenes only
    methods   = ["ours", "transparent", "mean", "random"]      # `camo optimize --method` names (default ours)
    ablations = ["none", "pose", "displacement", "bsdf", "transmittance", "inpainting", "pose,displacement"]
                                               # crossed with method "ours" only (default ["none"])
    seeds     = [0, 1, 2]                      # `camo optimize --seed` (default [0])

    [optimize]                                 # any `camo optimize` option (long name, - or _)
    iterations = 50
    resolution = 128
    views = 16
    stages = "1,2"                             # lists are joined with commas: stages = [1, 2]
    no-planner = false                         # flags are booleans

    [optimize.ganmouflage]                     # per-method overrides (a table named after a method)
    iterations = 2000

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

Each cell has a **key**: the first 16 hex digits of the SHA-256 of its resolved config (scene as written plus
the pack file's SHA-256, method, ablation, seed, and the resolved optimise and evaluate options; not the
thread count). A cell with the same key is the same work: a finished one is never redone.
"""

from __future__ import annotations

import argparse
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
    method: str
    ablation: str  # "none" or a sorted comma list
    seed: int
    optimize: tuple[tuple[str, Any], ...]  # resolved options: (dest, value), sorted
    evaluate: tuple[tuple[str, Any], ...]
    optimize_argv: tuple[str, ...]  # option arguments only (no SCENE/--out/--threads/--resume)
    evaluate_argv: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["optimize"] = dict(self.optimize)
        d["evaluate"] = dict(self.evaluate)
        d["optimize_argv"] = list(self.optimize_argv)
        d["evaluate_argv"] = list(self.evaluate_argv)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Cell":
        return cls(key=d["key"], name=d["name"], scene=d["scene"], scene_label=d["scene_label"], method=d["method"],
                   ablation=d["ablation"], seed=int(d["seed"]),
                   optimize=tuple(sorted(d["optimize"].items())), evaluate=tuple(sorted(d["evaluate"].items())),
                   optimize_argv=tuple(d["optimize_argv"]), evaluate_argv=tuple(d["evaluate_argv"]))

    # ------------------------------------------------------------------------------------------------------
    # the camo command lines of this cell
    # ------------------------------------------------------------------------------------------------------

    def run_dir(self, cell_dir: Path) -> Path:
        return Path(cell_dir) / "run" / self.name

    def eval_dir(self, cell_dir: Path) -> Path:
        return Path(cell_dir) / "eval" / self.name  # named after the cell: the report's settings list it

    def optimize_command(self, cell_dir: Path, threads: int | None, mode: str = "fresh") -> list[str]:
        """``camo optimize`` argv (without the program name); ``mode``: fresh, resume or restart."""
        argv = ["optimize", self.scene, "--out", str(self.run_dir(cell_dir)), "--method", self.method,
                "--seed", str(self.seed)]
        if self.ablation != "none":
            argv += ["--ablate", self.ablation]
        argv += [*self.optimize_argv, "--quiet"]
        if threads:
            argv += ["--threads", str(threads)]
        if mode == "resume":
            argv.append("--resume")
        elif mode == "restart":
            argv.append("--overwrite")
        return argv

    def evaluate_command(self, cell_dir: Path, threads: int | None) -> list[str]:
        argv = ["evaluate", str(self.run_dir(cell_dir)), "--out", str(self.eval_dir(cell_dir)),
                *self.evaluate_argv, "--quiet"]
        if threads:
            argv += ["--threads", str(threads)]
        return argv


@dataclasses.dataclass
class Grid:
    path: Path
    name: str
    cells: list[Cell]
    source: str  # the grid file's text

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "path": str(self.path), "cells": [c.to_dict() for c in self.cells]}


# --------------------------------------------------------------------------------------------------------------
# options of `camo optimize` / `camo evaluate`, read from their real parsers
# --------------------------------------------------------------------------------------------------------------


def command_parser(command: str) -> argparse.ArgumentParser:
    """The argparse parser of ``camo <command>`` as registered by its plugin (so new options just work)."""
    root = argparse.ArgumentParser(prog="camo")
    sub = root.add_subparsers(dest="command")
    if command == "optimize":
        from camo import optimize_cli

        optimize_cli.register(sub)
    else:
        from evaluation import cli as eval_cli

        eval_cli.register(sub)
    return sub.choices[command]


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """``{dest: action}`` of the optional arguments that take a ``--long`` name."""
    out = {}
    for a in parser._actions:  # noqa: SLF001 - argparse has no public accessor
        longs = [s for s in a.option_strings if s.startswith("--")]
        if longs and not isinstance(a, argparse._HelpAction):  # noqa: SLF001
            out[a.dest] = a
    return out


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _option_args(section: str, table: dict[str, Any], parser: argparse.ArgumentParser, where: str
                 ) -> tuple[dict[str, Any], list[str]]:
    """Validate one ``[optimize]`` / ``[evaluate]`` table: resolved ``{dest: value}`` and argv fragments."""
    actions = _options(parser)
    reserved = RESERVED[section]
    values: dict[str, Any] = {}
    for raw_key, value in table.items():
        dest = str(raw_key).replace("-", "_")
        if dest in reserved:
            raise CamoError(f"{where}: [{section}] {raw_key} is set by the grid: {reserved[dest]}")
        action = actions.get(dest)
        if action is None:
            known = ", ".join(sorted(k.replace("_", "-") for k in actions if k not in reserved))
            raise CamoError(f"{where}: [{section}] unknown option {raw_key!r}; `camo {section}` options: {known}")
        if action.nargs == 0:  # store_true / store_false flags
            if not isinstance(value, bool):
                raise CamoError(f"{where}: [{section}] {raw_key} is a flag: write true or false, not {value!r}")
            if value != action.default:
                values[dest] = value
            continue
        if isinstance(value, bool) or isinstance(value, dict) or value is None:
            raise CamoError(f"{where}: [{section}] {raw_key} must be a number, a string or a list, not {value!r}")
        if isinstance(value, list):
            if not value or any(isinstance(v, (list, dict, bool)) for v in value):
                raise CamoError(f"{where}: [{section}] {raw_key}: a list must hold plain numbers or strings, "
                                f"got {value!r}")
            text = ",".join(str(v) for v in value)
        elif isinstance(value, float) and value != value:
            raise CamoError(f"{where}: [{section}] {raw_key} is NaN")
        else:
            text = str(value)
        converted: Any = text
        if action.type is not None:
            try:
                converted = action.type(text)
            except (TypeError, ValueError):
                tname = getattr(action.type, "__name__", "value")
                raise CamoError(f"{where}: [{section}] {raw_key} must be {'an' if tname[0] in 'aeiou' else 'a'} "
                                f"{tname}, got {value!r}") from None
            if isinstance(converted, float) and (converted != converted or converted in (float("inf"), float("-inf"))):
                raise CamoError(f"{where}: [{section}] {raw_key} must be finite, got {value!r}")
        if action.choices is not None and converted not in action.choices:
            raise CamoError(f"{where}: [{section}] {raw_key} must be one of {', '.join(map(str, action.choices))}, "
                            f"got {value!r}")
        if converted == action.default:  # the same work as leaving it out: the same cell key
            continue
        values[dest] = converted
    argv: list[str] = []
    for dest in sorted(values):
        action = actions[dest]
        flag = max((s for s in action.option_strings if s.startswith("--")), key=len)
        if action.nargs == 0:
            argv.append(flag)
        else:
            argv.append(f"{flag}={values[dest]}")  # `=` keeps values such as "-1" from looking like options
    return values, argv


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
    from camo.cli import parse_ablate

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
            parts = parse_ablate(text)
        except CamoError as exc:
            raise CamoError(f"{where}: ablations: {exc}".replace("--ablate ", "")) from None
        out.append(",".join(sorted(parts)))
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
    from camo.optimize_cli import METHODS

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
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise CamoError(f"{where}: unknown method(s) {', '.join(bad)}; `camo optimize --method` takes: "
                        f"{', '.join(METHODS)}")
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
        if m not in METHODS:
            raise CamoError(f"{where}: [optimize.{m}]: a sub-table must be named after a method "
                            f"({', '.join(METHODS)})")
    base_opt = {k: v for k, v in sections["optimize"].items() if not isinstance(v, dict)}
    opt_parser, eval_parser = command_parser("optimize"), command_parser("evaluate")
    eval_values, eval_argv = _option_args("evaluate", sections["evaluate"], eval_parser, where)
    opt_by_method = {}
    for m in methods:
        merged = {**{k.replace("-", "_"): v for k, v in base_opt.items()},
                  **{k.replace("-", "_"): v for k, v in per_method.get(m, {}).items()}}
        sub_where = where if m not in per_method else f"{where} (method {m})"
        opt_by_method[m] = _option_args("optimize", merged, opt_parser, sub_where)

    entries = _scene_entries(scenes, objects, path.parent, where)
    cells: list[Cell] = []
    for scene_arg, label, sha in entries:
        for m in methods:
            opt_values, opt_argv = opt_by_method[m]
            for abl in (ablations if m == "ours" else ["none"]):
                for seed in seeds:
                    key = cell_key({"scene": label, "pack_sha256": sha, "method": m, "ablation": abl, "seed": seed,
                                    "optimize": opt_values, "evaluate": eval_values})
                    abl_part = "" if abl == "none" else "-wo-" + abl.replace(",", "+")
                    scene_part = Path(label).stem if sha else label
                    nm = _slug(f"{scene_part}__{m}{abl_part}__s{seed}")
                    cells.append(Cell(key=key, name=nm, scene=scene_arg, scene_label=label, method=m, ablation=abl,
                                      seed=seed, optimize=tuple(sorted(opt_values.items())),
                                      evaluate=tuple(sorted(eval_values.items())), optimize_argv=tuple(opt_argv),
                                      evaluate_argv=tuple(eval_argv)))
    names = [c.name for c in cells]
    if len(set(names)) != len(names):  # two packs with one file name: make the run names unique
        cells = [dataclasses.replace(c, name=f"{c.name}__{c.key[:8]}") if names.count(c.name) > 1 else c
                 for c in cells]
    grid = Grid(path=path.resolve(), name=name, cells=cells, source=source)
    validate_cells(grid)
    return grid


def validate_cells(grid: Grid) -> None:
    """Run every cell's command lines through the real `camo optimize` / `camo evaluate` checks (cheap: no
    rendering, no Mitsuba) so that bad settings fail before the first cell starts."""
    import contextlib
    import io

    from evaluation.evaluate import EvalSettings, parse_metrics

    from camo.cli import build_parser
    from camo.optimize_cli import config_from_args

    parser = build_parser()
    seen_eval: set[tuple] = set()
    for c in grid.cells:
        argv = c.optimize_command(Path("/nonexistent-camo-grid-cell"), None)
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                args = parser.parse_args(argv)
        except SystemExit:
            msg = err.getvalue().strip().splitlines()
            raise CamoError(f"{grid.path}: cell {c.name}: {msg[-1] if msg else 'bad optimize options'}") from None
        try:
            config_from_args(args)
        except CamoError as exc:
            raise CamoError(f"{grid.path}: cell {c.name}: {exc}") from None
        if c.evaluate_argv not in seen_eval:
            seen_eval.add(c.evaluate_argv)
            try:
                with contextlib.redirect_stderr(err):
                    ea = parser.parse_args(c.evaluate_command(Path("/nonexistent-camo-grid-cell"), None))
            except SystemExit:
                msg = err.getvalue().strip().splitlines()
                raise CamoError(f"{grid.path}: [evaluate]: {msg[-1] if msg else 'bad evaluate options'}") from None
            try:
                EvalSettings(views=ea.views, jitter=ea.jitter, spp=ea.spp, resolution=ea.resolution,
                             metrics=parse_metrics(ea.metrics), seed=ea.seed).validate()
            except CamoError as exc:
                raise CamoError(f"{grid.path}: [evaluate]: {exc}") from None
