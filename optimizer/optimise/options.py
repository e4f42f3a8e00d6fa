"""The options of a run: the schema ``camo optimize``'s flags and a grid's ``[optimize]`` keys are made from.

Each :class:`Option` is one setting a caller may give by name (``iterations``, ``map_resolution``; the flag is
``--`` plus the name with ``-`` for ``_``): its type, its choices, the run spec field it sets and its help. The
range of every number is :data:`RANGES` (by spec field), the one place a limit is written:
:meth:`optimizer.optimise.spec.RunSpec.validate` checks fields with it, and ``camo optimize`` gives each numeric
flag its :class:`~camo_base.ranges.Range` as argparse ``type``. :func:`convert` turns a plain value (a TOML value,
a parsed flag) into the option's type, the way argparse would turn its text, so a grid file and a command line
with the same settings give the same values (and the same grid cell keys).
:meth:`~optimizer.optimise.spec.RunSpec.from_options` turns a ``{name: value}`` mapping into a run spec.

Options that only say where and how a run executes (:data:`EXECUTION`) are not part of the spec.

This module imports nothing heavy: ``camo --help`` reads it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from camo_base.ranges import Range, convert
from optimizer.optimise.presets import DEFAULT_PRESET, PRESETS, preset_values

#: Iteration cap of a stage under --time-budget when no iteration count is given (the budget ends it first).
UNCAPPED = 100_000

#: The range of every numeric run spec field (and of the execution option ``threads``).
RANGES: dict[str, Range] = {
    "seed": Range(int, 0, 2**63 - 1),
    "spp.train": Range(int, 1, 2**20), "spp.target": Range(int, 1, 2**20), "spp.stage2_preview": Range(int, 1, 2**20),
    "stage1.iterations": Range(int, 1, UNCAPPED), "stage2.iterations": Range(int, 1, UNCAPPED),
    "stage1.silhouette_every": Range(int, 1, 10_000),
    "stage1.pose_search": Range(int, 0, 3600),
    "stage1.average": Range(float, 0.0, 0.999),
    "stage1.loss_clamp": Range(float, 0.0, 1e6), "stage1.grad_clip": Range(float, 0.0, 1e6),
    "stage1.perceptual": Range(float, 0.0, 1e3), "stage1.detail_match": Range(float, 0.0, 1e3),
    "stage1.tint_match": Range(float, 0.0, 1e3), "stage1.tint_scale": Range(float, 0.0, 1e3),
    "stage1.coarse_grid": Range(int, 0, 64), "stage1.coarse_lr": Range(float, 0.0, 1.0),
    "stage1.grain": Range(float, 0.0, 2.0), "stage1.grain_sharpen": Range(float, 0.0, 8.0),
    "stage1.warm_transmittance": Range(float, 0.0, 1.0), "stage1.warm_transmittance_low": Range(float, 0.0, 1.0),
    "stage1.clear_candidate": Range(float, 0.0, 4.0),  # 0 (off) or an IOR in (1, 4]: RunSpec.validate
    "stage1.clear_roughness": Range(float, 0.0, 1.0),
    "stage1.shadow_weight": Range(float, 0.0, 1e3),
    "stage2.strength": Range(float, 0.0, 1.0, lo_open=True),
    "checkpoint_every": Range(int, 1, UNCAPPED), "snapshot_every": Range(int, 0, UNCAPPED),
    "time_budget": Range(float, 0.0, None, lo_open=True),
    "appearance.map_resolution": Range(int, 8, 16384), "appearance.displacement_resolution": Range(int, 8, 16384),
    "appearance.displacement_bound": Range(float, 0.0, 0.5),
    "appearance.eta": Range(float, 1.0, 4.0, lo_open=True),
    "appearance.lr_maps": Range(float, 0.0, 10.0, lo_open=True),
    "appearance.lr_displacement": Range(float, 0.0, 10.0, lo_open=True),
    "appearance.grad_blur": Range(float, 0.0, 64.0),
    "appearance.displacement_warmup": Range(int, 0, UNCAPPED),
    "appearance.map_smoothness": Range(float, 0.0, 1e6, lo_open=True),
    "holdout.views": Range(int, 0, 1024), "holdout.every": Range(int, 1, UNCAPPED), "holdout.spp": Range(int, 1, 2**20),
    "holdout.patience": Range(int, 0, UNCAPPED),
    "pack.object.target_vertices": Range(int, 100, 10_000_000),
    "pack.render.resolution": Range(int, 8, 8192),
    "pack.cameras.views": Range(int, 1, 1024),
    "options.iterations": Range(int, 1, 10_000_000),
    "options.strength": Range(float, 0.0, 1.0, lo_open=True),
    "threads": Range(int, 1, 4096),
}


@dataclasses.dataclass(frozen=True)
class Option:
    """One run option (module doc). ``kind``: int, float, str, or bool (a switch: given means true). ``field``: the
    spec field it sets (``negate``: a switch that sets its field to false); ``choices``: the values a str option
    takes."""

    name: str
    field: str
    kind: type
    help: str
    metavar: str | None = None
    choices: tuple[str, ...] | None = None
    negate: bool = False

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def range(self) -> Range | None:
        return RANGES.get(self.field) if self.kind in (int, float) else None

    def convert(self, value: Any, name: str | None = None) -> Any:
        """``value`` as this option's type, as argparse converts the text of the flag (a str option takes a list
        as its comma-joined items; :func:`camo_base.ranges.convert`); SettingError naming ``name`` (default: the
        option's name) otherwise."""
        return convert(value, self.kind, name or self.name, choices=self.choices, rng=self.range)


def _p(field: str) -> str:
    """``(fast: X; paper: Y)`` from the presets, or '' when no preset sets ``field``."""
    v = preset_values(field)
    return f" ({v})" if v else ""


def _options() -> tuple[Option, ...]:
    from optimizer.assets.conditions import ablations_help
    from optimizer.optimise.schedule import SCHEDULES
    from optimizer.scenes.bsdf_maps import MAPS

    o = Option
    return (
        o("scene", "scene", str, "built-in scene name (ENV or ENV:OBJECT) or a scene pack .toml"),
        o("method", "method", str, "the method (default ours; list: camo optimize --help)"),
        o("preset", "preset", str, "the defaults the settings start from; explicit options override them",
          choices=tuple(PRESETS)),
        o("seed", "seed", int, "the run seed (default 0): every random stream derives from it (camo_base.seeds)"),
        o("time_budget", "time_budget", float,
          "stop when warm start + Stage 1 + Stage 2 iterations have taken this long (Stage 1 gets 80 %%; without "
          "--iterations / --stage2-iterations the iteration caps are lifted)", metavar="SECONDS"),
        o("warm_start", "stage1.warm_start", str, "least-squares albedo start" + _p("stage1.warm_start")
          + "; off when --init sets albedo", choices=("on", "off")),
        o("lr_schedule", "stage1.lr_schedule", str, "learning-rate schedule" + _p("stage1.lr_schedule"),
          choices=tuple(SCHEDULES)),
        o("lr_maps", "appearance.lr_maps", float, "Adam rate of the BSDF maps" + _p("appearance.lr_maps")),
        o("lr_displacement", "appearance.lr_displacement", float,
          "Adam rate of the normalised displacement" + _p("appearance.lr_displacement")),
        o("grad_blur", "appearance.grad_blur", float,
          "blur the BSDF maps' gradients by a Gaussian of this sigma before each Adam step (0: off)"
          + _p("appearance.grad_blur") + "; averages the per-texel Monte Carlo noise that otherwise speckles the maps",
          metavar="TEXELS"),
        o("map_update", "appearance.map_update", str,
          "how the BSDF maps step: 'adam' (per-texel Adam, the paper) or 'large_steps' (the gradient preconditioned "
          "by (I + lambda L)^-2 on the texel grid and one Adam normalisation per map, after Nicolet et al. 2021: "
          "no texel moves alone, so no salt-and-pepper)" + _p("appearance.map_update"),
          choices=("adam", "large_steps")),
        o("map_smoothness", "appearance.map_smoothness", float,
          "lambda of --map-update large_steps, in texels^2 (a spike spreads over ~sqrt(lambda) texels)"
          + _p("appearance.map_smoothness"), metavar="LAMBDA"),
        o("average", "stage1.average", float,
          "the result is the moving average of the iterates with this decay (about the last 1 / (1 - DECAY) "
          "iterates; 0: the iterate itself)", metavar="DECAY"),
        o("loss_clamp", "stage1.loss_clamp", float,
          "compare the renders in the loss through w tanh(x / w), w = this many times the background's 99th "
          "percentile in the loss domain: a sun glint's pixel adds at most w^2 and no gradient (0: linear)"
          + _p("stage1.loss_clamp"), metavar="FACTOR"),
        o("grad_clip", "stage1.grad_clip", float,
          "clip each parameter's gradient to this many times its running norm, so one glint's step cannot move a "
          "whole map (0: off)" + _p("stage1.grad_clip"), metavar="FACTOR"),
        o("perceptual", "stage1.perceptual", float,
          "add this weight times the mean LPIPS of each Stage 1 render against its background target to the loss "
          "(sees texture the per-pixel loss misses: a too smooth or speckled body; needs the LPIPS weights)"
          + _p("stage1.perceptual") + "; 0: off", metavar="WEIGHT"),
        o("perceptual_net", "stage1.perceptual_net", str, "the LPIPS trunk of --perceptual"
          + _p("stage1.perceptual_net"), choices=("alex", "vgg")),
        o("detail_match", "stage1.detail_match", float,
          "add this weight times the mismatch of the body's pixel-scale texture energy (mean squared Laplacian of the "
          "luma on the object's pixels) with the background target's in the same pixels: the squared error alone "
          "leaves the body smoother than the ground (optimizer/optimise/detail.py)" + _p("stage1.detail_match")
          + "; 0: off", metavar="WEIGHT"),
        o("tint_match", "stage1.tint_match", float,
          "add this weight times the squared error of the body's mean colour in each view (its coverage-weighted "
          "mean against the background target's in the same pixels; 1 doubles that part of the squared error): the "
          "glassy tint (optimizer/optimise/tint.py)" + _p("stage1.tint_match") + "; 0: off", metavar="WEIGHT"),
        o("tint_scale", "stage1.tint_scale", float,
          "--tint-match compares the colour error low-passed by a Gaussian of this many pixels, each pixel its own "
          "neighbourhood's cast (0: one mean colour per view)" + _p("stage1.tint_scale"), metavar="PX"),
        o("init_search", "stage1.init_search", str,
          "when --init sets maps, also warm-start the start the run takes without it (at each starting roughness of "
          "the preset's search) and start from whichever scores best on the held-out views"
          + _p("stage1.init_search") + "; off: the --init start as given", choices=("on", "off")),
        o("clear_candidate", "stage1.clear_candidate", float,
          "after the other start searches, also try clear glass on the held-out views: this shared index of "
          "refraction (e.g. 1.05) with a smooth start (roughness 0.2), kept with its IOR (Stage 2, final renders, the "
          "exported asset) when it scores better (optimizer/optimise/startsearch.py)" + _p("stage1.clear_candidate")
          + "; 0: off", metavar="ETA"),
        o("clear_roughness", "stage1.clear_roughness", float,
          "the starting roughness of --clear-candidate's clear glass (rougher glass spreads the sunlight it focuses "
          "into its shadow and blurs the ground seen through it)" + _p("stage1.clear_roughness") + "; 0: 0.2",
          metavar="R"),
        o("shadow_weight", "stage1.shadow_weight", float,
          "weigh the loss domain's pixels outside the object (its cast shadow and reflections on the ground) this "
          "many times the object's pixels in Stage 1's loss, so the transmittance and pose are pulled harder "
          "towards a lighter shadow (optimizer/optimise/stage1.py shadow_weighted)" + _p("stage1.shadow_weight")
          + "; 1: the plain domain, 0: the object alone", metavar="W"),
        o("coarse_grid", "stage1.coarse_grid", int,
          "give the albedo and transmittance maps a coarse level of this many cells a side (1: one offset per channel "
          "for the whole body), added before rendering and stepped by Adam at its own rate, so the body's colour "
          "moves as a whole (optimizer/optimise/coarse.py)" + _p("stage1.coarse_grid") + "; 0: off", metavar="K"),
        o("coarse_lr", "stage1.coarse_lr", float,
          "the learning rate of --coarse-grid's level" + _p("stage1.coarse_lr") + "; 0: the maps' rate",
          metavar="LR"),
        o("grain", "stage1.grain", float,
          "add this gain times a fixed grain layer to the albedo in Stage 1: the ground's own texture, projected from "
          "each texel's best training view, minus the warm start's multi-view mean that leaves the body smoother than "
          "the ground (optimizer/optimise/grain.py; needs the warm start)" + _p("stage1.grain") + "; 0: off",
          metavar="GAIN"),
        o("warm_transmittance", "stage1.warm_transmittance", float,
          "the warm start also solves the transmittance map, per texel between the start's transmittance and T, where "
          "the albedo alone would have to exceed 1 to match the ground (more light through the body; "
          "optimizer/optimise/warmstart.py; needs the warm start)" + _p("stage1.warm_transmittance")
          + "; 0: the albedo alone", metavar="T"),
        o("warm_transmittance_low", "stage1.warm_transmittance_low", float,
          "the same solve may also lower the transmittance per texel down to T (a more diffuse, sunlit body where the "
          "light through it is darker than the ground; needs the warm start)" + _p("stage1.warm_transmittance_low")
          + "; 1: not below the start", metavar="T"),
        o("warm_transmittance_sun", "stage1.warm_transmittance_sun", str,
          "where --warm-transmittance-low may lower the transmittance, by the scene's sun: 'facing' only on the texels "
          "facing away from it (the sun-facing ones keep at least the start's), 'shadow' only on the texels whose cast "
          "shadow no training view sees; 'off' everywhere (needs a sunsky, sun or directional emitter)",
          choices=("off", "facing", "shadow"), metavar="MODE"),
        o("grain_sharpen", "stage1.grain_sharpen", float,
          "--grain's best view reads the background targets sharpened by an unsharp mask of this amount (B + A (B - "
          "Gauss 0.7 px B)), undoing the blur of resampling the target at each texel and of the render's pixel"
          + _p("stage1.grain_sharpen") + "; 0: the targets as they are", metavar="A"),
        o("roughness_search", "stage1.roughness_search", str,
          "before Stage 1, warm-start each of these uniform starting roughness values and start from the one that "
          "scores best on the held-out views" + _p("stage1.roughness_search") + "; off with 'off' or --init "
          "roughness=X", metavar="R1,R2,..."),
        o("snapshot_every", "snapshot_every", int,
          "save the parameters every N iterations to snapshots/ (bench/bench_convergence.py scores them)",
          metavar="N"),
        o("pose_search", "stage1.pose_search", int,
          "before Stage 1, try N turns of the object about the vertical axis and start from the one whose shadow and "
          "reflections change the ground least" + _p("stage1.pose_search") + "; 0: off", metavar="N"),
        o("holdout_views", "holdout.views", int,
          "held-out jittered views (own seed stream, never the evaluation's) that pick the result among the "
          "iterates checked every --holdout-every iterations and at each stage's end" + _p("holdout.views")
          + "; 0: the last iterate is the result", metavar="N"),
        o("holdout_every", "holdout.every", int, "iterations between held-out checks" + _p("holdout.every"),
          metavar="N"),
        o("holdout_spp", "holdout.spp", int, "samples per pixel of the held-out renders" + _p("holdout.spp"),
          metavar="N"),
        o("patience", "holdout.patience", int,
          "stop Stage 1 after N held-out checks in a row without a better iterate (default 0: never)", metavar="N"),
        o("iterations", "stage1.iterations", int, "Stage 1 iterations" + _p("stage1.iterations")),
        o("resolution", "pack.render.resolution", int, "render width = height in pixels (default: the pack's)"),
        o("spp", "spp.train", int,
          "samples per pixel of each training render (default 4; the run spec's spp.train; `camo scenes render "
          "--spp` is a render's own spp)"),
        o("target_spp", "spp.target", int,
          "samples per pixel of the background targets, the loss domain, the warm start and the final render "
          "(default 64; spp.target)"),
        o("views", "pack.cameras.views", int, "number of orbit views (default: the pack's, 16)"),
        o("ablate", "ablate", str, "comma list of parts switched off: " + ablations_help()),
        o("init", "pack.material", str,
          f"initial material values, overriding the scene pack's [material]: {', '.join(MAPS)} in [0, 1] (a colour "
          f"map: grey or R/G/B; paper: {', '.join(f'{m.initial:g}' for m in MAPS.values())})",
          metavar="KEY=VALUE,..."),
        o("loss", "stage1.loss", str,
          "luminance-gated (Eq. 9) or squared error (unbiased at a few spp)" + _p("stage1.loss"),
          choices=("gated", "mse")),
        o("map_resolution", "appearance.map_resolution", int, "BSDF map resolution (default 800, the paper's)"),
        o("displacement_resolution", "appearance.displacement_resolution", int,
          "displacement map resolution (default 256)"),
        o("eta", "appearance.eta", float,
          "index of refraction shared by the whole surface (default 1.5, the paper's; it sets the Fresnel reflection "
          "of the transmissive parts and how far they displace what is seen through them)", metavar="IOR"),
        o("displacement_bound", "appearance.displacement_bound", float,
          "displacement amplitude bound, fraction of object size (default 0.02)"),
        o("target_vertices", "pack.object.target_vertices", int, "remeshing target (paper: ~30,000)"),
        o("domain", "stage1.domain", str, "loss pixel domain (default object+shadow)",
          choices=("object+shadow", "frame")),
        o("stages", "stages", str, "stages to run: 1 (background matching), 2 (synthesis); default 1,2"),
        o("stage2_iterations", "stage2.iterations", int, "Stage 2 iterations" + _p("stage2.iterations")),
        o("stage2_backend", "stage2.backend", str, "Stage 2 inpainter (default: patch, offline)",
          choices=("patch", "diffusers")),
        o("stage2_strength", "stage2.strength", float, "Stage 2 noise strength t_start in (0, 1] (default 0.5)"),
        o("stage2_fixed_displacement", "stage2.displacement", bool,
          "Stage 2 refines the BSDF maps only and keeps Stage 1's displacement (default: refines both, as the "
          "paper; from roughness 0 under the sun, fixed gave fewer glints in novel views, docs/results)",
          negate=True),
        o("sdxl_path", "stage2.sdxl_path", str, "local SDXL inpainting pipeline folder (diffusers backend)"),
        o("controlnet_path", "stage2.controlnet_path", str, "local depth ControlNet folder (diffusers backend)"),
        o("silhouette_every", "stage1.silhouette_every", int,
          "projective training: the silhouette gradient on a random 1/N of the views per step, weighted N"
          + _p("stage1.silhouette_every") + "; 1 = every view"),
        o("checkpoint_every", "checkpoint_every", int, "checkpoint every N iterations (default 10)", metavar="N"),
        o("no_planner", "planner", bool, "always full path tracing (max_depth 12, projective on)", negate=True),
        o("shadow_gradients", "shadow_gradients", bool, "let shadow boundaries drive the pose (~35x cost)"),
    )


#: Every run option by name (the spec's; execution options are :data:`EXECUTION`).
OPTIONS: dict[str, Option] = {o.name: o for o in _options()}

#: Options that say where and how a run executes, not what it is: never part of the spec (``camo optimize`` flags).
EXECUTION = ("spec", "out", "resume", "overwrite", "accept_versions", "quiet", "threads")

#: What an absent option means, for the options whose absence is a fixed value (not the pack's or the preset's):
#: the run spec's defaults, written as the option would be. ``camo grid`` drops an option set to this value from a
#: cell's key (the same work); tests/test_optimize_cli.py checks it against the spec.
ABSENT: dict[str, Any] = {"seed": 0, "preset": DEFAULT_PRESET, "ablate": "", "init": "", "stages": "1,2",
                          "checkpoint_every": 10, "snapshot_every": 0, "method": "ours"}

#: Option values ``camo grid`` also leaves out of cell keys although they are no longer what an absent option
#: means: ``loss = "gated"`` was the default until the fast preset took the squared error (2026-11-24), and grid
#: folders made before keep their keys. Known limit: a grid naming ``loss = "gated"`` and one naming no loss get the
#: same cell keys; give such grids their own output folder (each cell's config.toml records the loss it ran).
KEY_STABLE: dict[str, Any] = {"loss": "gated"}


def option_field(method, name: str) -> str:
    """The run spec field option ``name`` sets for ``method`` (an :class:`~optimizer.optimise.method.Method`: a
    method may take an option for its own ``[options]``)."""
    return dict(method.option_names).get(name) or OPTIONS[name].field


def option_names(method) -> dict[str, str]:
    """``{spec field: option name}`` for ``method``: how to call a field in a message about options."""
    out = {option_field(method, n): n for n in OPTIONS}
    return out


def given(mapping: dict[str, Any]) -> dict[str, Any]:
    """The options a mapping gives: keys with ``-`` as ``_``, None and false switches left out (absent)."""
    out = {}
    for k, v in mapping.items():
        name = str(k).replace("-", "_")
        if v is None or (v is False and name in OPTIONS and OPTIONS[name].kind is bool):
            continue
        out[name] = v
    return out
