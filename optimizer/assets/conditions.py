"""Conditions of a comparison: a method and the parameters ablated from it -- names, Table II labels and order.

The one list of **ablations** (:data:`ABLATIONS`: what ``--ablate`` takes, what each switches off, its Table II
label) and of the **methods' display labels** (:data:`METHOD_LABELS`, in the paper's Table II order). A run
directory records its method's name and its ablations; the evaluation report (:mod:`evaluation.report`), the grid
table and the study read the labels here, so they live below the optimiser (evaluating a result never imports
it). The methods themselves -- what each runs and which settings it reads -- are
:data:`optimizer.optimise.methods.METHODS`; a method without an entry here is shown under its ``--method`` name
(after the paper's baselines).

    >>> condition_label("ours", "none"), condition_label("ours", "pose"), condition_label("mean", "none")
    ('Ours', 'w/o Pose', 'Mean [6]')
    >>> condition_label("ours", "displacement,pose")
    'w/o Pose + Displacement'
"""

from __future__ import annotations

import dataclasses

from camo_base.errors import SettingError, literal


@dataclasses.dataclass(frozen=True)
class Ablation:
    """One ``--ablate`` item: a part of the method switched off (paper Table II, "w/o ...").

    ``switches``: :class:`optimizer.rendering.appearance.AppearanceConfig` booleans it turns off; ``fixes``: the
    initial material values it decides (an ``--init`` of one of them is a conflict); ``pins``: the pack's initial
    material values it sets (``(key, value)``); ``stage1_only``: the run stops after Stage 1 (no synthesis)."""

    name: str
    label: str  # Table II row of ours without it
    short: str  # its name in a combination: "w/o Pose + Displacement"
    help: str
    switches: tuple[str, ...] = ()
    fixes: tuple[str, ...] = ()
    pins: tuple[tuple[str, float], ...] = ()
    stage1_only: bool = False


#: Every ablation, in the paper's Table II order.
ABLATIONS: dict[str, Ablation] = {a.name: a for a in (
    Ablation("pose", "w/o Pose", "Pose", "the object keeps the pack's pose (no translation or turn)", ("pose",)),
    Ablation("displacement", "w/o Displacement", "Displacement", "no surface displacement", ("displacement",)),
    Ablation("bsdf", "w/o BSDF (Only Albedo)", "BSDF",
             "albedo only: a Lambertian surface (no metallic, roughness or transmittance)", ("bsdf",),
             fixes=("transmittance", "metallic", "roughness"), pins=(("transmittance", 0.0),)),
    Ablation("transmittance", "w/o Transmittance", "Transmittance", "transmittance fixed at 0", ("transmittance",),
             fixes=("transmittance",), pins=(("transmittance", 0.0),)),
    Ablation("inpainting", "w/o Inpainting", "Inpainting", "Stage 1 only (no Stage 2 synthesis)", stage1_only=True),
)}

#: The method every ablation applies to.
OURS = "ours"

#: Table II labels of the methods, in the paper's order (baselines first; ``ours`` is the last row). A method not
#: listed is shown under its name, after these baselines.
METHOD_LABELS: dict[str, str] = {
    "transparent": "Transparent",
    "random": "Random [6]",
    "mean": "Mean [6]",
    "greedy": "Greedy [6]",
    "ganmouflage": "GANmouflage [7]",
    "ganmouflage-paper": "GANmouflage [7] (paper settings)",
    "diffusion2d": "2D Diffusion",
    OURS: "Ours",
}


def parse_ablations(text: str | tuple | list | set, field: str = "ablate") -> tuple[str, ...]:
    """``"pose,displacement"`` (or a list of names) -> the sorted names; SettingError naming ``field`` for an unknown
    one. ``""`` and ``"none"`` are no ablation.

    >>> parse_ablations("pose, bsdf")
    ('bsdf', 'pose')
    """
    items = [t.strip() for t in text.split(",")] if isinstance(text, str) else [str(t).strip() for t in text]
    names = {t for t in items if t and t != "none"}
    bad = sorted(names - set(ABLATIONS))
    if bad:
        raise SettingError(f"unknown {{0}} item(s) {literal(', '.join(bad))}; allowed: {', '.join(ABLATIONS)}", field)
    return tuple(sorted(names))


def ablated_switches(ablations) -> dict[str, bool]:
    """``{switch: on}`` for every appearance switch an ablation can turn off (off where one of ``ablations`` does):
    ``dataclasses.replace(app_config, **ablated_switches(...))``."""
    off = {s for a in ablations for s in ABLATIONS[a].switches}
    return {s: s not in off for a in ABLATIONS.values() for s in a.switches}


def ablations_help() -> str:
    """``--ablate`` help: each ablation and what it switches off."""
    return "; ".join(f"{a.name}: {a.help}" for a in ABLATIONS.values())


def ablation_list(ablation: str | tuple | list | None) -> list[str]:
    """The ablations of a metrics row (a comma list, ``"none"`` or empty) in Table II order (unknown ones last)."""
    items = [a for a in (str(ablation or "").split(",") if not isinstance(ablation, (tuple, list)) else ablation)
             if a and a != "none"]
    order = list(ABLATIONS)
    return sorted(items, key=lambda a: (order.index(a) if a in order else len(order), a))


def method_label(method: str) -> str:
    """The Table II label of a method (its name when it has none; matched without case, but only ``ours`` itself
    is Ours)."""
    m = str(method)
    if m == OURS:
        return METHOD_LABELS[OURS]
    return METHOD_LABELS.get(m.lower(), m) if m.lower() != OURS else m


def condition_label(method: str, ablation: str | tuple | list | None) -> str:
    """The Table II row label of a method and its ablations (comma list or ``"none"``)."""
    abl = ablation_list(ablation)
    m = str(method)
    if m == OURS:
        if not abl:
            return METHOD_LABELS[OURS]
        if len(abl) == 1 and abl[0] in ABLATIONS:
            return ABLATIONS[abl[0]].label
        return "w/o " + " + ".join(ABLATIONS[a].short if a in ABLATIONS else a for a in abl)
    base = method_label(m)
    if not abl:
        return base
    return f"{base} (w/o {' + '.join(ABLATIONS[a].short if a in ABLATIONS else a for a in abl)})"


def condition_order(method: str, ablation: str | tuple | list | None) -> tuple:
    """Sort key of Table II rows: baselines (paper order), other methods, single ablations (paper order), combined
    ablations, Ours."""
    abl = ablation_list(ablation)
    m = str(method).lower()
    if m == OURS:
        if not abl:
            return (5, 0, "")
        if len(abl) == 1 and abl[0] in ABLATIONS:
            return (3, list(ABLATIONS).index(abl[0]), "")
        return (4, len(abl), ",".join(abl))
    baselines = [k for k in METHOD_LABELS if k != OURS]
    if m in baselines:
        return (0, baselines.index(m), ",".join(abl))
    return (1, 0, m + "," + ",".join(abl))
