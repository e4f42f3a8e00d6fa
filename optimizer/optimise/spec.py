"""The run specification: one dataclass tree that defines a ``camo optimize`` run.

A :class:`RunSpec` is what a run *is*. It is built from data: :meth:`RunSpec.from_options` makes one from a
``{option: value}`` mapping (the run options of :mod:`optimizer.optimise.options`; ``camo optimize`` passes its
flags, a grid cell its ``[optimize]`` table) with a preset (:mod:`optimizer.optimise.presets`) and the start rules
applied; :meth:`RunSpec.from_dict` reads a recorded one; a run directory's ``config.toml`` is ``spec.to_dict()``
plus provenance (:func:`optimizer.assets.rundir.write_config`)::

    spec_version   2 (a config.toml without it is the layout before run specs; optimizer.assets.rundir reads both)
    scene          the SCENE argument as given: a built-in ENV or ENV:OBJECT, or a scene pack file
    method         a method of optimizer.optimise.methods.METHODS (ours, transparent, mean, ...)
    seed           the run seed: camo_base.seeds derives every random stream of the run from it, by name
    preset         the preset the settings started from (optimizer.optimise.presets.PRESETS; none recorded for a
                   spec built field by field in Python)
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
    [options]      the method's own options (its dataclass, ``Method.options``); ours and transparent have none
    [pack]         the resolved scene pack (resolution, views, target vertices, init and the preset's starting
                   material applied)

**Each method declares what it reads** (``Method.reads``, spec fields or whole tables). A spec holds settings for
those only: :meth:`RunSpec.to_dict` writes only them, :meth:`RunSpec.from_dict` refuses any other, and
:meth:`RunSpec.validate` refuses a spec whose unread fields differ from their defaults -- a setting the method
would ignore is an error, never silence. ``ours`` reads everything but ``[options]``; a baseline reads
:data:`optimizer.optimise.method.COMMON_READS` (scene, seed, the target spp, the loss and its domain, the map
resolution, the planner) and its own ``[options]``. Errors name options and spec fields
(:class:`camo_base.errors.SettingError`); ``camo optimize`` shows them as its flags (:func:`option_name`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, Callable, Mapping

from camo_base.errors import CamoError, SettingError, literal
from optimizer.assets.conditions import ABLATIONS, ablated_switches, parse_ablations
from optimizer.assets.rundir import CONFIG_VERSION, config_fingerprint
from optimizer.optimise.holdout import HoldoutSettings
from optimizer.optimise.method import Method
from optimizer.optimise.methods import METHODS, resolve_method
from optimizer.optimise.options import OPTIONS, RANGES, UNCAPPED, given, option_field
from optimizer.optimise.presets import PRESETS, get_preset
from optimizer.optimise.stage1 import Stage1Config, Stage1Settings
from optimizer.optimise.stage2 import Stage2Config, Stage2Settings
from optimizer.optimise.warmstart import SUN_MODES
from optimizer.rendering.appearance import AppearanceConfig
from optimizer.scenes.scenepack import RenderSpec, ScenePack

#: The spec's version, as written to config.toml (``spec_version``).
SPEC_VERSION = CONFIG_VERSION
#: Fields a resumed run may change (its checkpoint stays valid): left out of :meth:`RunSpec.fingerprint`.
RESUMABLE = ("checkpoint_every", "snapshot_every", "stage1.iterations", "stage2.iterations")


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
    preset: str | None = None  # the preset the settings started from (from_options); None: the fields as given
    stages: tuple[int, ...] = (1, 2)
    ablate: tuple[str, ...] = ()
    planner: bool = True
    shadow_gradients: bool = False
    rough_start: bool = True  # raise a glint-prone initial roughness to planner.GLINT_ROUGHNESS (the fast preset's)
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

    @classmethod
    def from_options(cls, options: Mapping[str, Any], preset: str | None = None) -> "RunSpec":
        """The run spec of ``{option: value}`` (the options of :mod:`optimizer.optimise.options`, by name, ``-`` or
        ``_``; what ``camo optimize``'s flags and a grid's ``[optimize]`` table give), validated.

        ``preset`` (or an option ``preset``; default :data:`~optimizer.optimise.presets.DEFAULT_PRESET`) gives the
        starting values; every option given overrides its field. The start rules: the preset's starting material
        unless ``init`` names a value, an ablation pins what it fixes, ``init`` albedo turns the warm start off,
        ``init`` roughness (or ``bsdf`` ablated, or no held-out views) turns the roughness start search off,
        ``time_budget`` without an iteration count lifts the iteration caps, ``inpainting`` ablated runs Stage 1
        only. SettingError (one line, naming options or spec fields) for an unknown option, a bad value or one the
        method does not use.

        >>> spec = RunSpec.from_options({"scene": "meadow", "iterations": 3, "ablate": "pose"})
        >>> spec.preset, spec.stage1.iterations, spec.appearance.pose, spec.stage1.warm_start
        ('fast', 3, False, True)
        """
        vals: dict[str, Any] = {}
        for name, value in given(dict(options)).items():
            if name not in OPTIONS:
                raise SettingError(f"unknown option {literal(repr(name))}; the options are "
                                   f"{', '.join('{%d}' % i for i in range(len(OPTIONS)))}", *OPTIONS)
            vals[name] = OPTIONS[name].convert(value)
        if "scene" not in vals:
            raise SettingError("{0} is missing (a built-in scene name or a scene pack file)", "scene")
        if preset is not None and vals.get("preset", preset) != preset:
            raise SettingError(f"{{0}} {literal(vals['preset'])} differs from the preset {literal(preset)} asked for",
                               "preset")
        p = get_preset(preset if preset is not None else vals.get("preset"))
        method_name = vals.get("method", "ours")
        method, make_options = resolve_method(method_name)
        _check_options_apply(method, method_name, vals)
        pack = _pack_of(vals)
        ablate = parse_ablations(vals.get("ablate", ""))
        init = parse_init(vals.get("init", ""))
        for a in ablate:
            for key in ABLATIONS[a].fixes:
                if key in init:
                    raise SettingError(f"{{0}} {key} conflicts with {{1}} {a} (the ablation fixes it)", "init", "ablate")
        start = {k: v for k, v in p.material.items() if k not in init}
        if init or start:
            pack.material = dataclasses.replace(pack.material, **start, **init)
        pins = {k: v for a in ablate for k, v in ABLATIONS[a].pins}
        if pins:
            pack.material = dataclasses.replace(pack.material, **pins)
        # every other option sets its field as given: group them by table
        tables: dict[str, dict[str, Any]] = {"": {}, "spp": {}, "stage1": {}, "stage2": {}, "appearance": {},
                                             "holdout": {}, "options": {}}
        for name, value in vals.items():
            if name not in _SPECIAL:
                head, _, rest = option_field(method, name).partition(".")
                if rest:
                    tables[head][rest] = value
                else:
                    tables[""][head] = value
        app = dataclasses.replace(AppearanceConfig(), **p.appearance, **ablated_switches(ablate))
        app = dataclasses.replace(app, **tables["appearance"])
        s1 = dataclasses.replace(Stage1Settings(**p.stage1), **tables["stage1"])
        holdout = dataclasses.replace(HoldoutSettings(**p.holdout), **tables["holdout"])
        s2 = dataclasses.replace(Stage2Settings(**p.stage2), **tables["stage2"],
                                 displacement=not vals.get("stage2_fixed_displacement", False))
        if vals.get("time_budget") and "iterations" not in vals:
            s1 = dataclasses.replace(s1, iterations=UNCAPPED)
        if vals.get("time_budget") and "stage2_iterations" not in vals:
            s2 = dataclasses.replace(s2, iterations=UNCAPPED)
        if "warm_start" in vals:
            s1 = dataclasses.replace(s1, warm_start=vals["warm_start"] == "on")
        elif "albedo" in init:  # an explicit starting albedo is kept (the warm start would replace it)
            s1 = dataclasses.replace(s1, warm_start=False)
        if "init_search" in vals:
            s1 = dataclasses.replace(s1, init_search=vals["init_search"] == "on")
        elif not holdout.views:  # nothing to score the starts on
            s1 = dataclasses.replace(s1, init_search=False)
        if "roughness_search" in vals:
            s1 = dataclasses.replace(s1, roughness_search=parse_roughness_list(vals["roughness_search"]))
        elif "roughness" in init or "bsdf" in ablate or not holdout.views:
            # an explicit (or ablated) starting roughness is kept; without held-out views there is nothing to score on
            s1 = dataclasses.replace(s1, roughness_search=())
        stages = parse_stages(vals["stages"]) if "stages" in vals else (1, 2)
        if any(ABLATIONS[a].stage1_only for a in ablate):
            stages = (1,)
        options = make_options()
        for path, value in tables["options"].items():
            options = _set_option(options, path.split("."), value)
        spec = cls(scene=vals["scene"], pack=pack, method=method_name, preset=p.name, stages=stages, ablate=ablate,
                   planner=not vals.get("no_planner", False), rough_start=p.rough_start and "roughness" not in init,
                   spp=SppSettings(**tables["spp"]), stage1=s1, stage2=s2, appearance=app, holdout=holdout,
                   options=options, **tables[""])
        # what the method does not read goes back to its default (the preset's values for `ours` among them): the
        # spec records only what the method reads; every option given was checked above to be read
        return spec.normalised().validate()

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

    def start_without_init(self):
        """The starting material this spec's run would take had ``init`` named nothing: the scene's pack, the
        preset's start, the ablations' pins (a :class:`~optimizer.scenes.scenepack.MaterialSpec`); None when it is
        the spec's own (no ``init``, or ``init`` named the values it had anyway) or the scene cannot be read again.
        The init search (``stage1.init_search``) tries it beside the ``init`` start."""
        from optimizer.scenes.builtin_scenes import resolve_scene

        try:
            material = resolve_scene(self.scene).material
        except (CamoError, OSError):
            return None
        preset = PRESETS.get(self.preset) if self.preset is not None else None
        pins = {k: v for a in self.ablate if a in ABLATIONS for k, v in ABLATIONS[a].pins}
        material = dataclasses.replace(material, **(preset.material if preset else {}), **pins)
        return None if material == self.pack.material else material

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

    def validate(self) -> "RunSpec":
        """SettingError (one line, naming spec fields: a front end shows them as its own names, ``camo optimize``
        as flags) for a value out of range (:data:`optimizer.optimise.options.RANGES`) or a setting the method
        would ignore; returns ``self``."""
        from optimizer.optimise.schedule import SCHEDULES

        m = self.method_info

        def fields(paths) -> str:
            return ", ".join("{%d}" % i for i in range(len(paths)))

        unread = self.unread_settings()
        if unread:
            raise SettingError(f"method {m.name} does not use {fields(unread)}", *unread)

        def get(path: str) -> Any:
            obj: Any = self
            for part in path.split("."):
                obj = obj.get(part) if isinstance(obj, dict) else getattr(obj, part, None)
            return obj

        for path, r in RANGES.items():
            v = get(path)
            if v is None or not m.reads_path(path):
                continue
            for x in (v if isinstance(v, (tuple, list)) else (v,)):  # pack.render.resolution: (width, height)
                r.check(x, path)

        def one_of(path: str, allowed) -> None:
            v = get(path)
            if m.reads_path(path) and v not in allowed and not (v is None and path.startswith("options.")):
                raise SettingError(f"{{0}} must be one of {', '.join(map(str, allowed))}, got {literal(repr(v))}",
                                   path)

        if m.reads_path("holdout") and self.holdout.patience and not self.holdout.views:
            raise SettingError("{0} needs held-out views ({1} >= 1)", "holdout.patience", "holdout.views")
        if m.reads_path("stage1.roughness_search") and self.stage1.roughness_search:
            rs = self.stage1.roughness_search
            if not all(isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and 0.0 <= r <= 1.0
                       for r in rs):
                raise SettingError(f"{{0}} must be numbers in [0, 1], got {literal(list(rs))}",
                                   "stage1.roughness_search")
            if not self.holdout.views:
                raise SettingError("{0} needs held-out views ({1} >= 1)", "stage1.roughness_search", "holdout.views")
        if m.reads_path("stage1.init_search") and self.stage1.init_search and not self.holdout.views:
            raise SettingError("{0} needs held-out views ({1} >= 1)", "stage1.init_search", "holdout.views")
        if m.reads_path("stage1.tint_scale") and self.stage1.tint_scale and not self.stage1.tint_match:
            raise SettingError("{0} is the scale of {1}: set {1} > 0 too", "stage1.tint_scale", "stage1.tint_match")
        if m.reads_path("stage1.coarse_grid") and self.stage1.coarse_grid > self.appearance.map_resolution:
            raise SettingError(f"{{0}} must be at most {{1}} ({self.appearance.map_resolution}), got "
                               f"{literal(self.stage1.coarse_grid)}", "stage1.coarse_grid", "appearance.map_resolution")
        if m.reads_path("stage1.grain") and self.stage1.grain and not self.stage1.warm_start:
            raise SettingError("{0} is projected by the warm start: turn {1} on (a given initial albedo turns it off)",
                               "stage1.grain", "stage1.warm_start")
        for f, off in (("warm_transmittance", 0.0), ("warm_transmittance_low", 1.0)):
            if m.reads_path(f"stage1.{f}") and getattr(self.stage1, f) != off and not self.stage1.warm_start:
                raise SettingError("{0} is solved by the warm start: set {1} on", f"stage1.{f}", "stage1.warm_start")
        if m.reads_path("stage1.warm_transmittance_sun") and self.stage1.warm_transmittance_sun not in SUN_MODES:
            raise SettingError(f"{{0}} must be one of {', '.join(SUN_MODES)}, got "
                               f"{literal(self.stage1.warm_transmittance_sun)}", "stage1.warm_transmittance_sun")
        if m.reads_path("stage1.warm_transmittance_sun") and self.stage1.warm_transmittance_sun != "off":
            if not self.stage1.warm_start:
                raise SettingError("{0} is a choice of the warm start: set {1} on", "stage1.warm_transmittance_sun",
                                   "stage1.warm_start")
            if self.stage1.warm_transmittance_low >= 1.0:
                raise SettingError("{0} chooses where {1} lowers the transmittance: set {1} below 1 too",
                                   "stage1.warm_transmittance_sun", "stage1.warm_transmittance_low")
        if m.reads_path("stage1.grain_sharpen") and self.stage1.grain_sharpen and not self.stage1.grain:
            raise SettingError("{0} sharpens what {1} projects: set {1} > 0 too", "stage1.grain_sharpen", "stage1.grain")
        if m.reads_path("stage1.coarse_lr") and self.stage1.coarse_lr and not self.stage1.coarse_grid:
            raise SettingError("{0} is the rate of {1}: set {1} > 0 too", "stage1.coarse_lr", "stage1.coarse_grid")
        if m.reads_path("stage1.clear_roughness") and self.stage1.clear_roughness and not self.stage1.clear_candidate:
            raise SettingError("{0} is the start of {1}'s clear glass: set {1} too", "stage1.clear_roughness",
                               "stage1.clear_candidate")
        if m.reads_path("stage1.clear_candidate") and self.stage1.clear_candidate:
            if not 1.0 < self.stage1.clear_candidate <= 4.0:
                raise SettingError(f"{{0}} must be 0 (off) or an index of refraction in (1, 4], got "
                                   f"{literal(self.stage1.clear_candidate)}", "stage1.clear_candidate")
            if not self.holdout.views:
                raise SettingError("{0} needs held-out views ({1} >= 1)", "stage1.clear_candidate", "holdout.views")
            if not self.appearance.bsdf:
                raise SettingError("{0} needs the principled BSDF (an albedo-only object has no index of "
                                   "refraction)", "stage1.clear_candidate")
        if self.preset is not None:
            one_of("preset", tuple(PRESETS))
        one_of("stage1.loss", ("gated", "mse"))
        one_of("stage1.domain", ("object+shadow", "frame"))
        one_of("stage1.lr_schedule", SCHEDULES)
        one_of("stage2.backend", ("patch", "diffusers"))
        one_of("options.backend", ("patch", "diffusers"))
        one_of("options.albedo_mode", ("global", "local", "photo"))
        if m.reads_path("stages") and (not self.stages or set(self.stages) - {1, 2} or 1 not in self.stages):
            raise SettingError(f"{{0}} must include 1 and may include 2, got {list(self.stages)}", "stages")
        parse_ablations(self.ablate)
        if m.reads_path("stage2") and 2 in self.stages and self.stage2.backend == "diffusers" and \
                not (self.stage2.sdxl_path and self.stage2.controlnet_path):
            raise SettingError("{0} diffusers needs {1} and {2} (local folders; nothing is downloaded)",
                               "stage2.backend", "stage2.sdxl_path", "stage2.controlnet_path")
        opts = self.options
        if getattr(opts, "backend", None) == "diffusers" and not all(
                (opts.backend_options or {}).get(k) for k in ("sdxl_path", "controlnet_path")):
            raise SettingError("{0} diffusers needs {1} and {2} (local folders; nothing is downloaded)",
                               "options.backend", "options.backend_options.sdxl_path",
                               "options.backend_options.controlnet_path")
        return self


# --------------------------------------------------------------------------------------------------------------
# options -> spec: the start rules' parts
# --------------------------------------------------------------------------------------------------------------

#: Options whose value is not their field's value as given (read and converted by :meth:`RunSpec.from_options`).
_SPECIAL = ("scene", "method", "preset", "resolution", "views", "target_vertices", "init", "ablate", "stages",
            "warm_start", "init_search", "no_planner", "stage2_fixed_displacement", "roughness_search")


def option_applies(method_name: str, name: str) -> bool:
    """Whether ``method_name`` reads what run option ``name`` sets (other names apply to every method)."""
    if name not in OPTIONS:
        return True
    method, _ = resolve_method(method_name)
    return method.reads_path(option_field(method, name))


def check_options_apply(method_name: str, names) -> None:
    """SettingError (one line) naming the first run option in ``names`` that ``method_name`` does not read."""
    method, _ = resolve_method(method_name)
    _check_options_apply(method, method_name, [n for n in names if n in OPTIONS])


def option_name(name: str, method: str | None = None) -> str | None:
    """The run option (or execution argument) a library error's setting ``name`` is given by: the name itself for
    an option or an execution argument, the option that sets it for a spec field (``method``'s own options
    considered: GANmouflage's ``options.iterations`` is ``iterations``), else None."""
    from optimizer.optimise.options import EXECUTION, option_names

    if name in OPTIONS or name in EXECUTION:
        return name
    try:
        m = resolve_method(method)[0] if method else METHODS["ours"]
    except CamoError:
        m = METHODS["ours"]
    return option_names(m).get(name) or option_names(METHODS["ours"]).get(name)


def grid_names(method: str | None = None) -> Callable[[str], str]:
    """How a grid file calls a setting an error names: by its ``[optimize]`` key (:func:`option_name`)."""
    return lambda n: option_name(n, method) or n


def _check_options_apply(method: Method, method_name: str, vals) -> None:
    """SettingError naming the first option in ``vals`` that ``method`` does not read."""
    for name in vals:
        field = option_field(method, name)
        if name != "scene" and not method.reads_path(field):
            takes = sorted(n for n in OPTIONS if method.reads_path(option_field(method, n)) and n != "scene")
            raise SettingError(f"{{0}} does not apply to {{1}} {method_name} (it sets {field}, which {method.name} "
                               f"does not use); {method_name} takes "
                               f"{', '.join('{%d}' % (i + 2) for i in range(len(takes)))}", name, "method", *takes)


def _pack_of(vals: Mapping[str, Any]) -> ScenePack:
    """The scene pack of ``vals["scene"]`` with the ``resolution``, ``views`` and ``target_vertices`` options
    applied (a run's spp are its own: the pack's [render] spp is not touched)."""
    from optimizer.scenes.builtin_scenes import resolve_scene

    pack = resolve_scene(vals["scene"])
    if "resolution" in vals:
        pack.render = dataclasses.replace(pack.render, resolution=(vals["resolution"], vals["resolution"]))
    if "views" in vals:
        if pack.cameras.mode == "list":
            raise SettingError("{0} only applies to orbit cameras", "views")
        pack.cameras = dataclasses.replace(pack.cameras, views=vals["views"])
    if "target_vertices" in vals:
        pack.object = dataclasses.replace(pack.object, target_vertices=vals["target_vertices"])
    return pack


def parse_init(text: str, field: str = "init") -> dict:
    """``init``: ``"roughness=0.5,albedo=0.4/0.3/0.2"`` -> initial material values (the maps of
    :data:`optimizer.scenes.bsdf_maps.MAPS`: a colour map takes a grey or R/G/B); SettingError naming ``field``."""
    from optimizer.scenes.bsdf_maps import MAPS

    out: dict = {}
    for item in (x.strip() for x in text.split(",")):
        if not item:
            continue
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or key not in MAPS:
            raise SettingError(f"{{0}} takes KEY=VALUE with KEY one of {', '.join(MAPS)}; got {literal(repr(item))}",
                               field)
        if key in out:
            raise SettingError(f"{{0}} sets {key} twice", field)
        colour = MAPS[key].channels == 3
        try:
            nums = [float(v) for v in val.split("/")]
        except ValueError:
            raise SettingError(f"{{0}} {key} must be a number in [0, 1]{' or R/G/B' if colour else ''}, got "
                               f"{literal(repr(val))}", field) from None
        if len(nums) not in ((1, 3) if colour else (1,)) or not all(0.0 <= v <= 1.0 for v in nums):
            raise SettingError(f"{{0}} {key} must be {'a grey or R/G/B values' if colour else 'a number'} in [0, 1], "
                               f"got {literal(repr(val))}", field)
        out[key] = tuple(nums * 3 if len(nums) == 1 else nums) if colour else nums[0]
    return out


def parse_roughness_list(text: str, field: str = "roughness_search") -> tuple[float, ...]:
    """``roughness_search``: ``R1,R2,...`` (numbers in [0, 1]) or ``off`` / empty -> a tuple; SettingError otherwise."""
    if text.strip().lower() in ("", "off", "none"):
        return ()
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise SettingError(f"{{0}} must be a comma list of numbers in [0, 1] or 'off', got {literal(repr(text))}",
                           field) from None
    return values


def parse_stages(text: str, field: str = "stages") -> tuple[int, ...]:
    """``stages``: ``"1,2"`` or ``"1"`` -> the sorted stages; SettingError otherwise."""
    try:
        stages = tuple(sorted({int(x) for x in text.split(",") if x.strip()}))
    except ValueError:
        raise SettingError(f"{{0}} must be a comma list of 1 and 2, got {literal(repr(text))}", field) from None
    if not stages or set(stages) - {1, 2} or 1 not in stages:
        raise SettingError(f"{{0}} must include 1 and may include 2, got {literal(repr(text))}", field)
    return stages


def spec_from_file(path: str, seed: int | None = None, field: str = "path") -> "RunSpec":
    """The run spec recorded in ``path`` (a run directory's ``config.toml`` or the directory), with ``seed`` replaced
    when given (a replicate); CamoError (one line) for a missing file, a config.toml from before run specs, or a
    bad spec."""
    from pathlib import Path

    from camo_base.documents import read_toml
    from optimizer.assets.rundir import read_config, spec_of_config

    p = Path(path)
    run_dir = p if p.is_dir() else p.parent
    if not p.is_dir() and not p.is_file():
        raise SettingError(f"{{0}} {literal(path)}: no such file or run directory", field)
    cfg = read_config(run_dir) if p.is_dir() else read_toml(p, "run spec")
    data = spec_of_config(cfg, run_dir)
    if seed is not None:
        data["seed"] = seed
    return RunSpec.from_dict(data, where=str(p)).validate()


def _set_option(options, path: list[str], value):
    """``options`` with the field at ``path`` (``["backend_options", "sdxl_path"]``: a key of a dict field) set."""
    if len(path) == 1:
        return dataclasses.replace(options, **{path[0]: value})
    d = dict(getattr(options, path[0]) or {})
    d[path[1]] = value
    return dataclasses.replace(options, **{path[0]: d})


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
