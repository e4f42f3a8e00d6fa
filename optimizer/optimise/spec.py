"""The run specification: one dataclass tree that defines a ``camo optimize`` run, and the methods it can name.

A :class:`RunSpec` is what a run *is*. ``camo optimize`` only fills one from its flags
(:func:`camo.optimize_cli.spec_from_args`), a grid cell stores one (``camo.grid``), and a run directory's
``config.toml`` is ``spec.to_dict()`` plus provenance (:func:`optimizer.assets.rundir.write_config`)::

    spec_version   2 (a config.toml without it is the layout before run specs; optimizer.assets.rundir reads both)
    scene          the SCENE argument as given: a built-in ENV or ENV:OBJECT, or a scene pack file
    method         ours | transparent | mean | random | greedy | diffusion2d | ganmouflage (:data:`METHODS`)
    seed           the run seed: camo_base.seeds derives every random stream of the run from it, by name
    preset         fast | paper (optimizer.optimise.schedule.PRESETS): the defaults the settings started from
    stages, ablate, planner, shadow_gradients, rough_start, time_budget, checkpoint_every, snapshot_every
    [spp]          SppSettings, every samples-per-pixel count of a run once:
                     train           each training render (Stage 1 and Stage 2 gradient steps)        --spp
                     target          background targets, loss domain, warm start, the baselines' white
                                     render, and the final render (previews, renders.npz, summary)     --target-spp
                     stage2_preview  the render a Stage 2 pseudo ground truth is inpainted from
                   (the evaluation's spp is `camo evaluate --spp`; the pack's own [render] spp belongs to
                   `camo scenes render` and is not part of a run)
    [stage1]       Stage1Settings (optimizer.optimise.stage1)
    [stage2]       Stage2Settings (optimizer.optimise.stage2)
    [appearance]   AppearanceConfig (optimizer.rendering.appearance)
    [holdout]      HoldoutSettings (optimizer.optimise.holdout): held-out views that pick the result among the
                   iterates (views 0: off, the paper's last iterate)
    [options]      the method's own options (its dataclass, :attr:`Method.options`); ours and transparent have none
    [pack]         the resolved scene pack (--resolution, --views, --target-vertices, --init and the preset's
                   starting material applied)

**Each method declares what it reads** (:attr:`Method.reads`, spec fields or whole tables). A spec holds
settings for those only: :meth:`RunSpec.to_dict` writes only them, :meth:`RunSpec.from_dict` refuses any other,
and :meth:`RunSpec.validate` refuses a spec whose unread fields differ from their defaults -- a setting the
method would ignore is an error, never silence. ``ours`` reads everything but ``[options]``; a baseline reads
:data:`COMMON_READS` (scene, seed, the target spp, the loss and its domain, the map resolution, the planner) and
its own ``[options]``.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import math
from typing import Any, Callable, Mapping

from camo_base.errors import CamoError
from optimizer.assets.rundir import CONFIG_VERSION, config_fingerprint
from optimizer.optimise.holdout import HoldoutSettings
from optimizer.optimise.stage1 import Stage1Config, Stage1Settings
from optimizer.optimise.stage2 import Stage2Config, Stage2Settings
from optimizer.rendering.appearance import AppearanceConfig
from optimizer.scenes.scenepack import RenderSpec, ScenePack

#: The spec's version, as written to config.toml (``spec_version``).
SPEC_VERSION = CONFIG_VERSION
#: What ``--ablate`` may name.
ABLATIONS = ("pose", "displacement", "bsdf", "transmittance", "inpainting")
#: Fields a resumed run may change (its checkpoint stays valid): left out of :meth:`RunSpec.fingerprint`.
RESUMABLE = ("checkpoint_every", "snapshot_every", "stage1.iterations", "stage2.iterations")

#: What every method reads: the scene, the seed, the background targets and loss domain (the target spp, Stage 1's
#: loss settings), the albedo atlas' resolution and the index of refraction, the effect planner's inputs.
COMMON_READS = ("scene", "pack", "method", "seed", "preset", "spp.target", "stage1.loss", "stage1.alpha", "stage1.eps",
                "stage1.domain", "stage1.domain_dilate", "stage1.shadow_threshold", "appearance.map_resolution",
                "appearance.eta", "planner", "shadow_gradients")


@dataclasses.dataclass(frozen=True)
class Method:
    """One ``--method`` and what it reads of a run spec.

    ``reads``: spec fields (``"stage1.iterations"``) or whole tables (``"stage2"``, ``"options"``); ``"*"`` is
    every field but ``options``. ``options``: ``"module:callable"`` making the method's options dataclass (imported
    when needed; None: the method has no options). ``option_names``: ``camo optimize`` option names (the flags,
    ``-`` as ``_``; also the keys of a grid's ``[optimize]`` table) that set the method's own options instead of
    the field they set for ``ours`` -- ``--iterations`` is GANmouflage's training iterations, not Stage 1's."""

    name: str
    summary: str
    reads: tuple[str, ...] = COMMON_READS
    options: str | None = None
    option_names: tuple[tuple[str, str], ...] = ()

    def reads_path(self, path: str) -> bool:
        """Whether the method reads spec field ``path`` (dotted: ``"stage2.iterations"``, ``"options.backend"``)."""
        if path == "spec_version":
            return True
        if path == "options" or path.startswith("options."):
            return self.options is not None
        for r in self.reads:
            if r == "*" or path == r or path.startswith(r + "."):
                return True
        return False

    def make_options(self) -> Any:
        """The method's default options (None when it has none)."""
        return _call(self.options) if self.options else None


def _call(ref: str) -> Any:
    module, _, attr = ref.partition(":")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj()


#: Every method a run spec may name, by ``--method`` name.
METHODS: dict[str, Method] = {m.name: m for m in (
    Method("ours", "Stage 1 (background matching) and Stage 2 (synthesis): the paper's method", reads=("*",)),
    Method("transparent", "transmittance 1 everywhere: a glass-like object (baselines.transparent)"),
    Method("mean", "Owens et al. 2014: mean background colour over the views (baselines.owens2014)",
           options="optimizer.optimise.baselines.owens2014:OwensOptions"),
    Method("random", "Owens et al. 2014: one random projection order (baselines.owens2014)",
           options="optimizer.optimise.baselines.owens2014:OwensOptions"),
    Method("greedy", "Owens et al. 2014: greedy view choice (baselines.owens2014)",
           options="optimizer.optimise.baselines.owens2014:OwensOptions"),
    Method("diffusion2d", "per-view inpainting projected onto the surface (baselines.diffusion2d)",
           options="optimizer.optimise.baselines.diffusion2d:Diffusion2DOptions",
           option_names=(("stage2_backend", "options.backend"), ("sdxl_path", "options.backend_options.sdxl_path"),
                         ("controlnet_path", "options.backend_options.controlnet_path"))),
    Method("ganmouflage", "Guo et al. 2023: texture field, perceptual + adversarial losses (baselines.ganmouflage)",
           options="optimizer.optimise.baselines.ganmouflage:GanmouflageConfig",
           option_names=(("iterations", "options.iterations"),)),
)}
#: ``--method`` names that are a method with other default options: ``(method, options factory)``.
METHOD_ALIASES: dict[str, tuple[str, str]] = {
    "ganmouflage-paper": ("ganmouflage", "optimizer.optimise.baselines.ganmouflage:GanmouflageConfig.paper"),
}
#: Every name ``--method`` takes.
METHOD_NAMES = (*METHODS, *METHOD_ALIASES)


def resolve_method(name: str) -> tuple[Method, Callable[[], Any]]:
    """``(method, default options factory)`` of a ``--method`` name; CamoError for an unknown one."""
    if name in METHOD_ALIASES:
        base, ref = METHOD_ALIASES[name]
        return METHODS[base], lambda: _call(ref)
    m = METHODS.get(name)
    if m is None:
        raise CamoError(f"unknown --method {name!r}; choose one of: {', '.join(METHOD_NAMES)}")
    return m, m.make_options


@dataclasses.dataclass
class SppSettings:
    """Samples per pixel of a run, each once (module doc: which render takes which)."""

    train: int = 4  # each training render of a gradient step (Stage 1 and Stage 2)
    target: int = 64  # background targets, loss domain, warm start, baselines' white render, the final render
    stage2_preview: int = 16  # the render each Stage 2 pseudo ground truth is inpainted from


@dataclasses.dataclass
class RunSpec:
    """One run (module doc). Build it with :meth:`from_dict` or field by field; check it with :meth:`validate`."""

    scene: str
    pack: ScenePack
    method: str = "ours"
    seed: int = 0
    preset: str = "fast"
    stages: tuple[int, ...] = (1, 2)
    ablate: tuple[str, ...] = ()
    planner: bool = True
    shadow_gradients: bool = False
    rough_start: bool = True  # raise a glint-prone initial roughness to planner.GLINT_ROUGHNESS (fast preset)
    time_budget: float | None = None  # seconds for warm start + Stage 1 + Stage 2 iterations (setup excluded)
    checkpoint_every: int = 10
    snapshot_every: int = 0  # > 0: snapshots/sS_XXXX.npz every N iterations of each stage (bench_convergence)
    spp: SppSettings = dataclasses.field(default_factory=SppSettings)
    stage1: Stage1Settings = dataclasses.field(default_factory=Stage1Settings)
    stage2: Stage2Settings = dataclasses.field(default_factory=Stage2Settings)
    appearance: AppearanceConfig = dataclasses.field(default_factory=AppearanceConfig)
    holdout: HoldoutSettings = dataclasses.field(default_factory=HoldoutSettings)
    options: Any = None  # the method's options dataclass (None: its defaults, or the method has none)

    def __post_init__(self) -> None:
        m, make = resolve_method(self.method)
        self.method = m.name
        default = make()
        if self.options is None:
            self.options = default
        elif default is None:
            raise CamoError(f"method {m.name} takes no options, got {type(self.options).__name__}")
        elif type(self.options) is not type(default):
            raise CamoError(f"method {m.name} takes {type(default).__name__} options, got {type(self.options).__name__}")
        # The pack's own [render] spp is `camo scenes render`'s; a run has its spp in `spp` and records no other.
        if self.pack.render.spp != RenderSpec.spp:
            self.pack = dataclasses.replace(self.pack, render=dataclasses.replace(self.pack.render, spp=RenderSpec.spp))
        self.stages = tuple(int(s) for s in self.stages)
        self.ablate = tuple(sorted(str(a) for a in self.ablate))

    # ----------------------------------------------------------------------------------------------------------
    @property
    def method_info(self) -> Method:
        return METHODS[self.method]

    def stage1_config(self, time_budget: float | None = None) -> Stage1Config:
        """Stage 1's runtime config: its settings, the seed, the training and target spp."""
        return Stage1Config(**dataclasses.asdict(self.stage1), spp=self.spp.train, target_spp=self.spp.target,
                            seed=self.seed, time_budget=time_budget)

    def stage2_config(self) -> Stage2Config:
        """Stage 2's runtime config: its settings and the preview spp."""
        return Stage2Config(**dataclasses.asdict(self.stage2), preview_spp=self.spp.stage2_preview)

    # ----------------------------------------------------------------------------------------------------------
    def full_dict(self) -> dict[str, Any]:
        """Every field (read or not) as TOML-writable values (no None, lists for tuples)."""
        d: dict[str, Any] = {"spec_version": SPEC_VERSION}
        for f in dataclasses.fields(self):
            if f.name != "pack":
                d[f.name] = plain(getattr(self, f.name))
        d["pack"] = _pack_dict(self.pack)  # last: the longest table
        return {k: v for k, v in d.items() if v is not None}

    def to_dict(self) -> dict[str, Any]:
        """The spec as config.toml records it: the fields the method reads (module doc), TOML-writable."""
        m = self.method_info
        return _prune(self.full_dict(), m.reads_path)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "run spec") -> "RunSpec":
        """A spec from :meth:`to_dict`'s layout (a config.toml, a grid cell); CamoError (one line) for a field the
        method does not read, an unknown field, a wrong type or a missing ``spec_version``/``scene``/``pack``."""
        d = dict(data)
        version = d.pop("spec_version", None)
        if version != SPEC_VERSION:
            if version is None:
                raise CamoError(f"{where}: no spec_version (a config.toml from before run specs cannot be re-run; "
                                f"its run directory still evaluates)")
            raise CamoError(f"{where}: spec_version {version!r} is not {SPEC_VERSION} (written by another camo version)")
        m, make = resolve_method(str(d.get("method", "ours")))
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - set(fields))
        if unknown:
            raise CamoError(f"{where}: unknown field(s) {', '.join(unknown)}")
        for key in ("scene", "pack"):
            if key not in d:
                raise CamoError(f"{where}: no {key}")
        unread = [p for p in _leaves(d) if not m.reads_path(p)]
        if unread:
            raise CamoError(f"{where}: method {m.name} does not use {', '.join(unread)}")
        kw: dict[str, Any] = {}
        for name, value in d.items():
            if name == "pack":
                kw[name] = _pack_from(value, where)
            elif name == "options":
                base = make()
                kw[name] = _dataclass_from(type(base), value, f"{where}: [options]", base=base)
            elif name in _TABLES:
                kw[name] = _dataclass_from(_TABLES[name], value, f"{where}: [{name}]")
            else:
                kw[name] = _convert(fields[name].type, value, f"{where}: {name}")
        return cls(**kw)

    # ----------------------------------------------------------------------------------------------------------
    def _defaults(self) -> "RunSpec":
        """This spec with every field but scene, pack, method, seed, preset and options at its default."""
        keep = ("scene", "pack", "method", "seed", "preset", "options")
        return type(self)(**{f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name in keep})

    def unread_settings(self) -> list[str]:
        """Fields the method does not read whose values differ from their defaults (:meth:`validate` refuses them)."""
        mine, ref = _flat(self.full_dict()), _flat(self._defaults().full_dict())
        m = self.method_info
        return sorted(p for p in set(mine) | set(ref) if not m.reads_path(p) and mine.get(p) != ref.get(p))

    def normalised(self) -> "RunSpec":
        """This spec with every field the method does not read back at its default (what :meth:`to_dict` keeps)."""
        ref, out = self._defaults(), self
        for path in self.unread_settings():
            out = _replace_path(out, path.split("."), _get_path(ref, path.split(".")))
        return out

    def fingerprint(self) -> str:
        """16 hex digits identifying the work: the spec without :data:`RESUMABLE` fields (a checkpoint made with
        another fingerprint cannot be resumed)."""
        return config_fingerprint(self.to_dict(), ignore=RESUMABLE)

    def validate(self, names: Mapping[str, str] | None = None) -> "RunSpec":
        """CamoError (one line) for a value out of range or a setting the method would ignore; returns ``self``.

        ``names``: how to call a field in the message (``camo optimize`` passes its flags: ``--spp`` for
        ``spp.train``); else the dotted field name."""
        from optimizer.optimise.schedule import PRESETS, SCHEDULES

        m = self.method_info

        def name(path: str) -> str:
            return (names or {}).get(path, path)

        unread = self.unread_settings()
        if unread:
            raise CamoError(f"method {m.name} does not use {', '.join(name(p) for p in unread)}")

        def get(path: str) -> Any:
            obj: Any = self
            for part in path.split("."):
                obj = obj.get(part) if isinstance(obj, dict) else getattr(obj, part, None)
            return obj

        def at_least(path: str, lo: int) -> None:
            v = get(path)
            if m.reads_path(path) and v is not None and v < lo:
                raise CamoError(f"{name(path)} must be >= {lo}, got {v}")

        def one_of(path: str, allowed) -> None:
            v = get(path)
            if m.reads_path(path) and v not in allowed and not (v is None and path.startswith("options.")):
                raise CamoError(f"{name(path)} must be one of {', '.join(map(str, allowed))}, got {v!r}")

        def within(path: str, lo: float, hi: float, lo_open: bool = False) -> None:
            v = get(path)
            if not m.reads_path(path) or v is None:
                return
            ok = math.isfinite(v) and (lo < v if lo_open else lo <= v) and v <= hi
            if not ok:
                raise CamoError(f"{name(path)} must be in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {v}")

        at_least("seed", 0)
        for p in ("spp.train", "spp.target", "spp.stage2_preview", "stage1.iterations", "stage2.iterations",
                  "stage1.silhouette_every", "checkpoint_every", "appearance.map_resolution",
                  "appearance.displacement_resolution", "options.iterations"):
            at_least(p, 1)
        at_least("snapshot_every", 0)
        at_least("stage1.pose_search", 0)
        for p in ("holdout.views", "holdout.patience"):
            at_least(p, 0)
        for p in ("holdout.every", "holdout.spp"):
            at_least(p, 1)
        if m.reads_path("holdout") and self.holdout.patience and not self.holdout.views:
            raise CamoError(f"{name('holdout.patience')} needs held-out views ({name('holdout.views')} >= 1)")
        at_least("pack.object.target_vertices", 100)
        within("appearance.displacement_bound", 0.0, 0.5)
        within("appearance.lr_maps", 0.0, 10.0, lo_open=True)
        within("appearance.lr_displacement", 0.0, 10.0, lo_open=True)
        within("appearance.grad_blur", 0.0, 64.0)
        within("stage1.average", 0.0, 0.999)
        if m.reads_path("stage1.roughness_search") and self.stage1.roughness_search:
            rs = self.stage1.roughness_search
            if not all(isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and 0.0 <= r <= 1.0
                       for r in rs):
                raise CamoError(f"{name('stage1.roughness_search')} must be numbers in [0, 1], got {list(rs)}")
            if not self.holdout.views:
                raise CamoError(f"{name('stage1.roughness_search')} needs held-out views ({name('holdout.views')} >= 1)")
        within("stage2.strength", 0.0, 1.0, lo_open=True)
        within("options.strength", 0.0, 1.0, lo_open=True)
        if m.reads_path("time_budget") and self.time_budget is not None and \
                not (math.isfinite(self.time_budget) and self.time_budget > 0):
            raise CamoError(f"{name('time_budget')} must be a positive number of seconds, got {self.time_budget}")
        one_of("preset", tuple(PRESETS))
        one_of("stage1.loss", ("gated", "mse"))
        one_of("stage1.domain", ("object+shadow", "frame"))
        one_of("stage1.lr_schedule", SCHEDULES)
        one_of("stage2.backend", ("patch", "diffusers"))
        one_of("options.backend", ("patch", "diffusers"))
        one_of("options.albedo_mode", ("global", "local", "photo"))
        if m.reads_path("stages") and (not self.stages or set(self.stages) - {1, 2} or 1 not in self.stages):
            raise CamoError(f"{name('stages')} must include 1 and may include 2, got {list(self.stages)}")
        bad = sorted(set(self.ablate) - set(ABLATIONS))
        if bad:
            raise CamoError(f"unknown {name('ablate')} item(s) {', '.join(bad)}; allowed: {', '.join(ABLATIONS)}")
        if m.reads_path("stage2") and 2 in self.stages and self.stage2.backend == "diffusers" and \
                not (self.stage2.sdxl_path and self.stage2.controlnet_path):
            raise CamoError(f"{name('stage2.backend')} diffusers needs {name('stage2.sdxl_path')} and "
                            f"{name('stage2.controlnet_path')} (local folders; nothing is downloaded)")
        opts = self.options
        if getattr(opts, "backend", None) == "diffusers" and not all(
                (opts.backend_options or {}).get(k) for k in ("sdxl_path", "controlnet_path")):
            raise CamoError(f"{name('options.backend')} diffusers needs {name('options.backend_options.sdxl_path')} "
                            f"and {name('options.backend_options.controlnet_path')} (local folders; nothing is "
                            "downloaded)")
        return self


# --------------------------------------------------------------------------------------------------------------
# dict <-> dataclass
# --------------------------------------------------------------------------------------------------------------

_TABLES: dict[str, type] = {"spp": SppSettings, "stage1": Stage1Settings, "stage2": Stage2Settings,
                            "appearance": AppearanceConfig, "holdout": HoldoutSettings}


def plain(obj: Any) -> Any:
    """A TOML-writable copy of ``obj``: dataclasses as dicts, no None values, tuples as lists."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        obj = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    return obj


def _pack_dict(pack: ScenePack) -> dict[str, Any]:
    d = plain(pack.to_dict())
    d.get("render", {}).pop("spp", None)  # not part of a run (RunSpec.__post_init__)
    return d


def _pack_from(value: Any, where: str) -> ScenePack:
    from optimizer.scenes.scenepack import parse_pack

    if not isinstance(value, dict):
        raise CamoError(f"{where}: [pack] must be a table")
    if "spp" in (value.get("render") or {}):
        raise CamoError(f"{where}: [pack.render] spp is not part of a run: the run's spp are in [spp]")
    data = json.loads(json.dumps(value))
    source = data.pop("source", None)
    try:
        return parse_pack(data, source=source)
    except CamoError as exc:
        raise CamoError(f"{where}: [pack]: {exc}") from None


def _flat(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        p = f"{prefix}{k}"
        if isinstance(v, dict) and v and p != "pack":
            out.update(_flat(v, p + "."))
        else:
            out[p] = v
    return out


def _leaves(d: Mapping[str, Any]) -> list[str]:
    return list(_flat(d))


def _prune(d: dict[str, Any], keep: Callable[[str], bool], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        p = f"{prefix}{k}"
        if keep(p):
            out[k] = v
        elif isinstance(v, dict):
            sub = _prune(v, keep, p + ".")
            if sub:
                out[k] = sub
    return out


def _get_path(obj: Any, path: list[str]) -> Any:
    for part in path:
        obj = obj.get(part) if isinstance(obj, dict) else getattr(obj, part)
    return obj


def _replace_path(obj: Any, path: list[str], value: Any) -> Any:
    """A copy of dataclass (or dict) ``obj`` with the field at ``path`` set to ``value``."""
    head, rest = path[0], path[1:]
    new = _replace_path(_get_path(obj, [head]), rest, value) if rest else value
    if isinstance(obj, dict):
        return {**obj, head: new}
    return dataclasses.replace(obj, **{head: new})


def _convert(annotation: Any, value: Any, where: str) -> Any:
    """``value`` (from TOML/JSON) as the field's annotated type (a string under ``from __future__ import
    annotations``); CamoError for a mismatch."""
    t = str(annotation).replace("typing.", "").strip()
    optional = t.endswith("| None") or t.startswith("None |") or t.startswith("Optional[")
    base = t.replace("| None", "").replace("None |", "").strip()
    if value is None:
        if optional:
            return None
        raise CamoError(f"{where} must not be empty")
    if base == "bool":
        if not isinstance(value, bool):
            raise CamoError(f"{where} must be true or false, got {value!r}")
        return value
    if base == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise CamoError(f"{where} must be an integer, got {value!r}")
        return value
    if base == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CamoError(f"{where} must be a number, got {value!r}")
        return float(value)
    if base == "str":
        if not isinstance(value, str):
            raise CamoError(f"{where} must be a string, got {value!r}")
        return value
    if base.startswith("tuple"):
        if not isinstance(value, (list, tuple)):
            raise CamoError(f"{where} must be a list, got {value!r}")
        return tuple(value)
    if base.startswith("dict"):
        if not isinstance(value, dict):
            raise CamoError(f"{where} must be a table, got {value!r}")
        return dict(value)
    return value


def _dataclass_from(cls: type, value: Any, where: str, base: Any = None) -> Any:
    """An instance of dataclass ``cls`` from a table: fields absent take ``base``'s values (or the defaults)."""
    if not isinstance(value, dict):
        raise CamoError(f"{where} must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(value) - set(fields))
    if unknown:
        raise CamoError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(fields)}")
    kw = {k: _convert(fields[k].type, v, f"{where} {k}") for k, v in value.items()}
    return dataclasses.replace(base, **kw) if base is not None else cls(**kw)
