"""The settings of an evaluation, as data: the schema ``camo evaluate``'s setting flags and a grid's ``[evaluate]``
keys are made from, and :class:`EvalSettings`, what :func:`evaluation.evaluate.evaluate` runs with.

Each :class:`EvalOption` is one setting a caller may give by name (``views``, ``no_noise_match``; the flag is
``--`` plus the name with ``-`` for ``_``): its type, the :class:`EvalSettings` field it sets, its default and its
help; the range of every number is :data:`evaluation.ranges.RANGES`. :meth:`EvalSettings.from_options` turns a
plain ``{name: value}`` mapping (the parsed flags, a grid's ``[evaluate]`` table) into settings, converting each
value the way argparse converts the flag's text (:func:`camo_base.ranges.convert`), so the same settings given
either way are equal. Its errors name the settings (:class:`~camo_base.errors.SettingError`); ``camo evaluate``
shows them as its flags, a grid as its keys.

What to evaluate (run directories, ``--asset``, ``--triplets``, ``--inputs``) is not a setting: :mod:`evaluation.
inputs`.

    >>> s = EvalSettings.from_options({"views": 4, "metrics": ["psnr", "ssim"], "no_planner": True})
    >>> s.views, s.metrics, s.planner, s.spp
    (4, ['psnr', 'ssim'], False, 64)
    >>> EvalSettings.from_options({"jitter": 0})
    Traceback (most recent call last):
    ...
    camo_base.errors.SettingError: jitter must be a number in (0, 100], got 0

This module imports nothing heavy (the planner's denoiser names: no renderer): ``camo --help`` reads it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

from camo_base.errors import SettingError, literal
from camo_base.ranges import convert
from evaluation.ranges import RANGES

#: The paper's evaluation jitter: up to +-0.25 units per axis at radius 4.
DEFAULT_JITTER = 0.25


@dataclasses.dataclass
class EvalSettings:
    """How an evaluation renders and scores (:func:`evaluation.evaluate.evaluate`); build it from option values with
    :meth:`from_options`."""

    views: int | None = None  # default: the number of training views
    jitter: float = DEFAULT_JITTER
    spp: int = 64
    resolution: int | None = None  # default: the run's
    metrics: Sequence[str] | None = None  # default: the weight-free metrics + the learned ones that can run
    seed: int = 0
    weights: dict[str, str] = dataclasses.field(default_factory=dict)  # {metric: path} (setting `weights`)
    threads: int | None = None
    progress: bool = True
    write_report: bool = True
    planner: bool = True  # False: full path tracing (depth 12) of every full frame (the bench's reference)
    noise_match: bool = True  # more samples where the object's render is noisier than the background's
    denoise: str = ""  # opt-in: the denoiser (optimizer.rendering.planner.DENOISERS) the plan applies where the noise
    # at spp is above its bias (after noise matching), or "": off by default, as it smooths the ground seen through a
    # see-through object (docs/evaluation.md)
    setting: str = ""  # "auto": the render's setting (denoiser factor, rule, features' spp, spp level) chosen per scene by
    # a pilot against full tracing's error at spp (evaluation.views.evaluation_setting_pilot); "": as the other options
    sampler: str = "independent"  # how each pixel's samples are drawn in both renders (optimizer.rendering.tracer.
    # SAMPLERS; the plan's integrator carries it; "sobol" opt-in: stratified, lower error per sample, docs/cli.md)

    def validate(self) -> "EvalSettings":
        """SettingError (one line, naming the setting) for a value outside :data:`evaluation.ranges.RANGES` (the
        jitter must be > 0: evaluation never uses the training cameras; the denoiser one of its choices). Returns the
        settings."""
        for name in ("views", "jitter", "spp", "resolution", "seed", "threads"):
            v = getattr(self, name)
            if v is not None:
                RANGES[name].check(v, name)
        if self.denoise:
            OPTIONS["denoise"].convert(self.denoise)
        OPTIONS["sampler"].convert(self.sampler)
        if self.setting:
            OPTIONS["setting"].convert(self.setting)
            if not self.planner or not self.noise_match:
                raise SettingError(f"{{0}} {self.setting}: needs the planner and noise matching (drop {{1}})",
                                   "setting", "no_planner" if not self.planner else "no_noise_match")
        return self

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> "EvalSettings":
        """The settings of ``{option name: value}`` (:data:`OPTIONS`; ``-`` or ``_`` in names; None, and false for a
        switch, mean absent: the option's default). Values are converted as the flags' text is
        (:meth:`EvalOption.convert`), metric names and weights checked against the metrics registry; SettingError
        (one line, naming the option) for an unknown option or a bad value."""
        values = {}
        for key, value in options.items():
            name = str(key).replace("-", "_")
            if name not in OPTIONS:
                raise SettingError(f"{{0}} is not an evaluation setting (settings: {', '.join(OPTIONS)})", name)
            if value is not None:
                values[name] = OPTIONS[name].convert(value)
        kw: dict[str, Any] = {}
        for opt in OPTIONS.values():
            if opt.kind in (int, float) and opt.name in values:
                kw[opt.field] = values[opt.name]
            elif opt.kind is bool and values.get(opt.name):
                kw[opt.field] = not _FIELD_DEFAULTS[opt.field]  # (a switch flips its field's default)
            elif opt.choices is not None and values.get(opt.name):
                kw[opt.field] = values[opt.name]
        return cls(**kw, metrics=parse_metrics(values.get("metrics")), weights=parse_weights(values)).validate()


@dataclasses.dataclass(frozen=True)
class EvalOption:
    """One evaluation setting a caller gives by name (module doc). ``kind``: int, float, str, or bool (a switch:
    given means true, and it flips its ``field``'s default: off for ``no_*``). ``field``: the
    :class:`EvalSettings` field it sets (weights options: ``weights``, for ``metric``). ``default``: what absent
    means, as the option would be written. ``choices``: the names a str option takes; ``const``: its value when the
    flag is given without one (``--denoise``; in a grid, ``denoise = true``; false means absent)."""

    name: str
    kind: type
    field: str
    help: str
    default: Any = None
    metavar: str | None = None
    metric: str | None = None  # a weights option's metric (`lpips_weights`: the same as `weights` lpips=PATH)
    choices: tuple[str, ...] | None = None
    const: str | None = None

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def range(self):
        return RANGES.get(self.name) if self.kind in (int, float) else None

    def convert(self, value: Any, name: str | None = None) -> Any:
        """``value`` as this option's type (:func:`camo_base.ranges.convert`); SettingError naming ``name``
        (default: the option's name)."""
        if self.const is not None and isinstance(value, bool):
            return self.const if value else None
        return convert(value, self.kind, name or self.name, choices=self.choices, rng=self.range)


def _options() -> tuple[EvalOption, ...]:
    from optimizer.rendering.planner import DENOISER, DENOISERS, EVALUATION_SAMPLER
    from optimizer.rendering.tracer import SAMPLERS

    o = EvalOption
    weights = (
        ("lpips", "an AlexNet trunk (torchvision layout, .pth or .safetensors), or a folder with the trunk and the "
                  "v0.1 heads (alex.pth, or the files `camo data fetch data_manifests/lpips_weights.toml` lands)"),
        ("sifid", "Inception v3 state dict for SIFID"),
        ("dreamsim", "DreamSim weights folder (its cache_dir)"),
    )
    short = {"lpips": "lpips_weights", "sifid": "inception_weights", "dreamsim": "dreamsim_weights"}
    return (
        o("views", int, "views", "evaluation views per run (default: the number of training views; more repeats the "
          "jitter)"),
        o("jitter", float, "jitter", f"camera offset bound per axis at radius 4, scaled with the radius (default "
          f"{DEFAULT_JITTER}; must be > 0)", default=DEFAULT_JITTER),
        o("spp", int, "spp", "samples per pixel of the evaluation renders (default 64)", default=64),
        o("resolution", int, "resolution", "image width = height in pixels (default: the run's)"),
        o("metrics", str, "metrics", "comma list of metrics (default: the weight-free ones and the learned ones whose "
          "weights are found; list: camo evaluate --help)"),
        o("seed", int, "seed", "camera jitter and sampler seed (same for every run)", default=0),
        o("weights", str, "weights", "weights of learned metrics other than the installed ones, per metric (what a "
          "path may be: docs/evaluation.md), e.g. lpips=DIR_OR_TRUNK,sifid=INCEPTION.pth,dreamsim=DIR",
          metavar="NAME=PATH[,NAME=PATH]"),
        *(o(short[m], str, "weights", what, metavar="PATH", metric=m) for m, what in weights),
        o("threads", int, "threads", "CPU threads for the LLVM backend"),
        o("no_planner", bool, "planner", "full path tracing of every full frame (max_depth 12) instead of the measured "
          "plan (a pilot per scene picks the depth; only the region each object can change is rendered)",
          default=False),
        o("no_noise_match", bool, "noise_match", "the same spp everywhere (default: pixels where the render with the "
          "object is noisier than the background get more samples, up to 8x, so noise does not give the object "
          "away)", default=False),
        o("denoise", str, "denoise", "denoise both renders alike by Open Image Denoise (after noise matching) where "
          "the plan's pilot measures the noise at --spp above the denoiser's bias; VARIANT: "
          f"{DENOISER} (first-hit albedo and normal, the flag alone) or oidn-through (see-through features: keeps "
          "more of the ground seen through a see-through object); default: off, as it smooths that ground "
          "(docs/evaluation.md)", metavar="VARIANT", choices=DENOISERS, const=DENOISER),
        o("setting", str, "setting", "auto: a pilot per scene (two views, seconds) chooses how the render with the "
          "object is made -- its spp level, the object's extra samples and how they combine with noise matching's, "
          "the denoiser features' spp (denoiser: --denoise, or oidn-through) -- as the cheapest render as accurate "
          "as full path tracing at --spp whose object is no noisier than the background; none qualifying: as without "
          "it (evaluation/views.py evaluation_setting_pilot)", metavar="auto", choices=("auto",)),
        o("sampler", str, "sampler", "how each pixel's samples are drawn in the background and with-object renders: "
          "independent (default) or sobol (stratified: the position in the pixel and the first vertex's emitter and "
          "BSDF samples; unbiased, lower error at equal spp, but with noise matching the object's surroundings can "
          "stay noisier than the background: docs/results/planner.md)", default=EVALUATION_SAMPLER,
          metavar="|".join(SAMPLERS), choices=SAMPLERS),
        o("quiet", bool, "progress", "no progress messages", default=False),
    )


#: Every evaluation setting by name.
OPTIONS: dict[str, EvalOption] = {o.name: o for o in _options()}
#: The :class:`EvalSettings` fields' defaults (a switch sets its field to the other value).
_FIELD_DEFAULTS: dict[str, Any] = {f.name: f.default for f in dataclasses.fields(EvalSettings)}


def parse_weights(values: Mapping[str, Any]) -> dict[str, str]:
    """``{metric: path}`` of the ``weights`` option (``NAME=PATH[,NAME=PATH]``) and the per-metric weights options
    (``lpips_weights``, ...); SettingError (one line) for an item without ``=`` or a metric given twice. The paths
    are checked by the metrics (:func:`evaluation.evaluate.weights_of`)."""
    out: dict[str, str] = {}

    def put(metric: str, path: str, option: str, item: str) -> None:
        if not metric or not path:
            raise SettingError.of(option, f" {item}: expected NAME=PATH, e.g. lpips=/path/to/weights")
        if metric in out:
            raise SettingError.of(option, f" {item}: weights for {metric} given twice")
        out[metric] = path

    for item in (values.get("weights") or "").split(","):
        if item.strip():
            metric, _, path = item.strip().partition("=")
            put(metric.strip(), path.strip(), "weights", item.strip())
    for opt in OPTIONS.values():
        if opt.metric is not None and values.get(opt.name):
            put(opt.metric, str(values[opt.name]), opt.name, str(values[opt.name]))
    return out


def parse_metrics(text: str | None) -> list[str] | None:
    """The ``metrics`` option (``psnr,ssim``) as names (None when not given); SettingError for an empty list or
    unknown names (the registry is imported only then)."""
    if text is None:
        return None
    names = [t.strip() for t in text.split(",") if t.strip()]
    if not names:
        raise SettingError.of("metrics", " is empty; give a comma list, e.g. psnr,ssim,lpips_proxy")
    from evaluation.metrics import METRICS

    bad = [n for n in names if n not in METRICS]
    if bad:
        raise SettingError(f"unknown metric(s) {literal(', '.join(bad))} in {{0}}; known: {', '.join(METRICS)}",
                           "metrics")
    return list(dict.fromkeys(names))
