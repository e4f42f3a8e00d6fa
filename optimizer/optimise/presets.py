"""Run presets of ``camo optimize --preset``: the one registry.

A preset is the set of defaults a run spec starts from (:meth:`optimizer.optimise.spec.RunSpec.from_options`):
values of Stage 1 / Stage 2 / appearance / held-out settings, the starting material, and whether a glint-prone
starting roughness is raised (``rough_start``). Every option given explicitly overrides its preset's value. The
``--preset`` help and each option's "(fast: ..., paper: ...)" note are generated from here
(:func:`preset_values`). A run spec built field by field in Python has no preset (``preset = None``): its
settings are the dataclass defaults (the paper's values) and whatever the caller sets.

    >>> PRESETS["paper"].stage1["iterations"], PRESETS["fast"].stage1["iterations"]
    (50, 60)
    >>> preset_values("stage1.pose_search")
    'fast: 16; paper: 0'
"""

from __future__ import annotations

import dataclasses
from typing import Any

from camo_base.errors import CamoError


@dataclasses.dataclass(frozen=True)
class Preset:
    """One preset: field overrides per spec table, the starting material, and the rough start."""

    name: str
    summary: str
    stage1: dict[str, Any]
    stage2: dict[str, Any]
    appearance: dict[str, Any]
    holdout: dict[str, Any]
    material: dict[str, Any]  # initial material values replacing the pack's unless --init names them
    rough_start: bool  # raise a glint-prone initial roughness (optimizer.optimise.run.glint_safe_start)

    def value(self, field: str) -> Any:
        """The preset's value of a dotted spec field (``"stage1.iterations"``), or None when it sets none."""
        table, _, key = field.partition(".")
        if not key:
            return getattr(self, table, None) if table == "rough_start" else None
        return (getattr(self, table, None) or {}).get(key) if table in _TABLES else None


_TABLES = ("stage1", "stage2", "appearance", "holdout", "material")

#: ``paper`` is the paper's schedule exactly (Sec. IV-A): grey start, constant rates 1e-2 / 1e-1, 50 + 20
#: iterations, the silhouette term on every view every step. ``fast`` (the default) is measured in
#: ``bench/bench_convergence.py`` and docs/results/convergence.md.
PRESETS: dict[str, Preset] = {p.name: p for p in (
    Preset(
        "fast",
        "least-squares albedo warm start, transmittance start 0.75, squared-error loss, proximal L1 step on the "
        "displacement and its rate ramped over 10 steps, map gradients blurred by 2 texels, a soft-clamped loss and "
        "gradients clipped at 4x their running norm (glints), 60 + 4 iterations, a 16-turn pose search, a two-value roughness start search and (with --init) "
        "the start without --init tried first, a coarse level under the albedo and transmittance maps (one offset per "
        "channel), the best iterate on 4 held-out views is the result",
        # loss "mse": Eq. 9's absolute values are median-seeking, and with the decorrelated adjoint of a 4-spp render
        # that is a biased target: under Eq. 9 the training loss rises again after ~20 iterations and novel views get
        # worse (meadow 31.2 dB at 20 iterations, 30.2 at 87); the squared error's fixed point is the mean, so more
        # iterations keep paying (docs/results/convergence.md, "Why Eq. 9 stops improving at a few spp").
        # 60 iterations at the paper's map rate 1e-2 beat Eq. 9's 20 on all six built-in scenes and both metrics (room
        # 31.54 dB / 0.147 LPIPS-proxy against 30.39 / 0.199, split 27.10 / 0.343 against 26.20 / 0.375); 2e-2 was
        # better on room and split but worse on gravel, panorama and meadow. Constant rates.
        # pose_search 16: the object starts at the best of 16 turns about the vertical axis, scored by how much its
        # shadow and reflections change the ground (optimizer/optimise/posesearch.py; gravel +1.28 dB, panorama
        # +1.07, room +0.70, occluded +0.16 at equal settings, one run each)
        # roughness_search: Stage 1 starts from the best of these uniform roughness values, each warm-started and
        # scored on the held-out views (optimizer/optimise/startsearch.py): the roughness map stays within ~0.1 of its
        # start, and the best start is scene-dependent (0.7 against 0.5: meadow +0.46 dB, gravel +0.51, occluded
        # +0.61; split -0.74, room -0.63), which the score after the warm start predicts
        # loss_clamp 8, grad_clip 4, init_search (issue 32, docs/results/hard_cases.md): meadow from a mirror start at
        # 4 views / 64 px, 20 + 2 iterations: Stage 1's loss spiked to 87 (x7000 its median) and the held-out PSNR
        # ended at 20.84 dB; with the clamp and the clip the loss stayed flat (21.05 dB), with the init search too
        # the run started from the start without --init (24.48 dB). Thin parts: spike x13.7 -> x2.65. The six
        # built-in scenes: within the scores' noise (0.1 dB). The values 8 and 4 were chosen, not tuned.
        # coarse_grid 1 (issue 29, docs/results/giveaways.md): one Adam-stepped offset per channel under the albedo
        # and transmittance maps (optimizer/optimise/coarse.py), so the body's colour moves as a whole. Against no
        # level, on the six built-in scenes (4 views at 64 px, 24 + 4 iterations, evaluation at 512 spp): no worse
        # on crop PSNR or LPIPS-proxy on any scene, +0.65 dB and -0.021 real LPIPS on average, tint -7 %; 0.1 ms a
        # step. --coarse-grid 0 turns it off.
        stage1={"iterations": 60, "loss": "mse", "warm_start": True, "lr_schedule": "constant",
                "silhouette_every": 4, "pose_search": 16, "roughness_search": (0.5, 0.7),
                "loss_clamp": 8.0, "grad_clip": 4.0, "init_search": True, "coarse_grid": 1},
        stage2={"iterations": 4},
        # grad_blur 2: the maps' gradients blurred by 2 texels (AppearanceConfig.grad_blur); one run per scene at demo
        # sizes: meadow +0.35 dB / -0.012 LPIPS-proxy, split +0.69 / -0.022, room +0.88 / -0.040, gravel and
        # occluded level, the real sky-cone -0.12 / +0.004 (docs/results/convergence.md)
        # displacement_warmup 10: the displacement's rate ramps up over Stage 1's and Stage 2's first 10 steps; without
        # it Adam's sign-like first step moves every texel at once and the logged total loss jumps ~11x at iteration
        # 2 (the L1 term; optimizer/optimise/adam.py)
        appearance={"lr_maps": 1e-2, "lr_displacement": 5e-2, "displacement_shrink": 0.5, "grad_blur": 2.0,
                    "displacement_warmup": 10},
        # the result is the best of the iterates checked every 10 iterations (and at each stage's end) on 4 held-out
        # jittered views (optimizer/optimise/holdout.py): Stage 2 at demo sizes can cost novel-view quality
        # (gravel -0.15 dB, meadow -0.27), and the check keeps Stage 1's result where it does
        holdout={"views": 4, "every": 10, "spp": 16},
        # the shadow is what is left once the body matches; transmittance is the only parameter that lightens it
        material={"transmittance": 0.75},
        rough_start=True,
    ),
    Preset(
        "paper",
        "the paper's schedule exactly (Eq. 9 loss, grey start, constant rates 1e-2 / 1e-1, 50 + 20 iterations, "
        "silhouette term on every view)",
        stage1={"iterations": 50, "loss": "gated", "warm_start": False, "lr_schedule": "constant",
                "silhouette_every": 1, "pose_search": 0, "roughness_search": (), "loss_clamp": 0.0, "grad_clip": 0.0,
                "init_search": False, "coarse_grid": 0},
        stage2={"iterations": 20},
        appearance={"lr_maps": 1e-2, "lr_displacement": 1e-1, "displacement_shrink": 0.0, "grad_blur": 0.0,
                    "displacement_warmup": 0},
        holdout={},  # the last iterate is the result
        material={},
        rough_start=False,
    ),
)}
#: The preset ``camo optimize`` (and a grid) applies when none is named.
DEFAULT_PRESET = "fast"


def get_preset(name: str | None, field: str = "preset") -> Preset:
    """The preset called ``name`` (:data:`DEFAULT_PRESET` for None); CamoError naming ``field`` otherwise."""
    name = DEFAULT_PRESET if name is None else name
    if name not in PRESETS:
        raise CamoError(f"unknown {field} {name!r}; choose one of: {', '.join(PRESETS)}")
    return PRESETS[name]


def _show(v: Any) -> str:
    if isinstance(v, bool):
        return "on" if v else "off"
    if isinstance(v, (tuple, list)):
        return ",".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v) if v else "off"
    return f"{v:g}" if isinstance(v, float) else str(v)


def preset_values(field: str) -> str:
    """``"fast: 16; paper: 0"``: each preset's value of a spec field (presets that set none are left out)."""
    parts = [f"{p.name}: {_show(p.value(field))}" for p in PRESETS.values() if p.value(field) is not None]
    return "; ".join(parts)


def presets_help() -> str:
    """The ``--preset`` help: each preset and what it sets."""
    return "; ".join(f"{p.name}{' (default)' if p.name == DEFAULT_PRESET else ''}: {p.summary}"
                     for p in PRESETS.values())
