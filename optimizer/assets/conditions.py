"""Experimental conditions: the one place that names a result's method and ablations for people and tables, and the
one list of ablations.

A *condition* is what a run's spec says it is: its ``method`` and the items of its ``ablate`` list (``camo optimize
--method M --ablate a,b``; ``config.toml``'s ``method`` and ``ablate``). Every table and file that shows or stores a
condition takes both its id and its label from :func:`condition`:

* the evaluation report's Table II rows (:mod:`evaluation.report`) and the grid's merged table (:mod:`camo.grid`),
* the stimuli manifest (``condition`` and ``label`` of every stimulus, :mod:`study_site.stimuli`),
* the study database (``condition`` and ``label`` columns of the plan and of every trial, :mod:`study_site.db`),
* Table I and the power analysis (:mod:`study_site.analysis`, :mod:`study_site.power`).

``id``: machine-readable and stable, ``ours``, ``ours-without-inpainting``, ``ours-without-pose+bsdf`` (ablations
in the paper's order, joined by ``+``); ``label``: the paper's wording, ``Ours``, ``w/o Inpainting``,
``w/o Pose + BSDF``. An ablation *removes* a component: ``--ablate inpainting`` is the method **without**
Stage 2's inpainting, never "ours plus inpainting".

Data, not code: :data:`ABLATIONS` is the one list of what ``--ablate`` takes (each :class:`Ablation`: its label,
what it switches off, the material values it pins; the run spec, ``camo plan`` and the grid read it here), and
:data:`METHOD_LABELS` the Table II labels of the methods, in the paper's order. The methods themselves -- what each
runs and which settings it reads -- are :data:`optimizer.optimise.methods.METHODS`; a method without a label here
(a new baseline, an external asset labelled ``--method theirs``) keeps its own name as label, after the paper's
baselines. ``tests/test_conditions.py`` checks that every ``--method`` and ``--ablate`` name has its id and label.

>>> c = condition("ours", "inpainting")
>>> c.id, c.label
('ours-without-inpainting', 'w/o Inpainting')
>>> condition("ours", "bsdf,pose").label
'w/o Pose + BSDF'
>>> parse_id("ours-without-pose+bsdf") == condition("ours", "pose,bsdf")
True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Mapping

from camo_base.errors import CamoError, SettingError, literal


@dataclass(frozen=True)
class Ablation:
    """One ``--ablate`` item: a component of ours switched off (paper Table II, "w/o ...").

    ``switches``: :class:`optimizer.rendering.appearance.AppearanceConfig` booleans it turns off; ``fixes``: the
    initial material values it decides (an ``--init`` of one of them is a conflict); ``pins``: the pack's initial
    material values it sets (``(key, value)``); ``stage1_only``: the run stops after Stage 1 (no synthesis)."""

    name: str
    short: str  # its name in a combination: "w/o Pose + BSDF"
    label: str  # Table II row of ours without only it
    help: str
    switches: tuple[str, ...] = ()
    fixes: tuple[str, ...] = ()
    pins: tuple[tuple[str, float], ...] = ()
    stage1_only: bool = False


#: Every ``--ablate`` item, in the paper's Table II order.
ABLATIONS: dict[str, Ablation] = {a.name: a for a in (
    Ablation("pose", "Pose", "w/o Pose", "the object keeps the pack's pose (no translation or turn)", ("pose",)),
    Ablation("displacement", "Displacement", "w/o Displacement", "no surface displacement", ("displacement",)),
    Ablation("bsdf", "BSDF", "w/o BSDF (Only Albedo)",
             "albedo only: a Lambertian surface (no metallic, roughness or transmittance)", ("bsdf",),
             fixes=("transmittance", "metallic", "roughness"), pins=(("transmittance", 0.0),)),
    Ablation("transmittance", "Transmittance", "w/o Transmittance", "transmittance fixed at 0", ("transmittance",),
             fixes=("transmittance",), pins=(("transmittance", 0.0),)),
    Ablation("inpainting", "Inpainting", "w/o Inpainting", "Stage 1 only (no Stage 2 synthesis)", stage1_only=True),
)}

#: The methods' Table II labels, in the paper's order (``ours`` last). A method not listed shows its own name.
METHOD_LABELS: dict[str, str] = {
    "transparent": "Transparent",
    "random": "Random [6]",
    "mean": "Mean [6]",
    "greedy": "Greedy [6]",
    "ganmouflage": "GANmouflage [7]",
    "ganmouflage-paper": "GANmouflage [7] (paper settings)",
    "diffusion2d": "2D Diffusion",
    "ours": "Ours",
}
#: The method whose ablations are the paper's "w/o X" rows.
OURS = "ours"
#: Separators of a condition id (neither occurs in a method or ablation name the toolkit writes).
WITHOUT, JOIN = "-without-", "+"
#: Ablation strings that mean "no ablation".
_NONE = ("", "none", "full", "null")


@dataclass(frozen=True)
class Condition:
    """A method and the components it was run without (``ablations``: in :data:`ABLATIONS` order)."""

    method: str
    ablations: tuple[str, ...] = ()

    @property
    def id(self) -> str:
        """``ours``, ``ours-without-inpainting``, ``ours-without-pose+bsdf`` (stored in files and databases)."""
        return self.method if not self.ablations else f"{self.method}{WITHOUT}{JOIN.join(self.ablations)}"

    @property
    def ablation(self) -> str:
        """The ablations as a run directory lists them: ``none`` or a comma list."""
        return ",".join(self.ablations) if self.ablations else "none"

    @property
    def label(self) -> str:
        """The label people read (Table II rows, Table I rows, the admin page)."""
        names = [ABLATIONS[a].short if a in ABLATIONS else a for a in self.ablations]
        if self.method == OURS:
            if not self.ablations:
                return METHOD_LABELS[OURS]
            if len(self.ablations) == 1 and self.ablations[0] in ABLATIONS:
                return ABLATIONS[self.ablations[0]].label
            return "w/o " + " + ".join(names)
        base = method_label(self.method)
        return base if not self.ablations else f"{base} (w/o {' + '.join(names)})"

    @property
    def order(self) -> tuple:
        """Sort key of the paper's tables: baselines (paper order), other methods, ours' single ablations (paper
        order), combined ablations, Ours last."""
        m = self.method.lower()
        if m == OURS:
            if not self.ablations:
                return (5, 0, "")
            if len(self.ablations) == 1 and self.ablations[0] in ABLATIONS:
                return (3, list(ABLATIONS).index(self.ablations[0]), "")
            return (4, len(self.ablations), ",".join(self.ablations))
        if m in METHOD_LABELS:
            return (0, list(METHOD_LABELS).index(m), ",".join(self.ablations))
        return (1, 0, m + "," + ",".join(self.ablations))


def method_label(method: str) -> str:
    """The Table II label of a method (:data:`METHOD_LABELS`, matched without case; else its own name)."""
    m = str(method)
    return METHOD_LABELS.get(m.lower(), m)


def parse_ablation(ablation: str | Iterable[str] | None) -> tuple[str, ...]:
    """Ablation items of ``"none"``, ``""``, ``"pose,bsdf"`` or a list, de-duplicated, in :data:`ABLATIONS` order
    (unknown items after them, alphabetically). Reading what a result says; :func:`parse_ablations` checks what a
    user asks for."""
    if ablation is None:
        items: list[str] = []
    elif isinstance(ablation, str):
        items = [a.strip() for a in ablation.split(",")]
    else:
        items = [str(a).strip() for a in ablation]
    items = sorted({a for a in items if a.lower() not in _NONE})
    order = list(ABLATIONS)
    return tuple(sorted(items, key=lambda a: (order.index(a) if a in order else len(order), a)))


def parse_ablations(text: str | Iterable[str] | None, field: str = "ablate") -> tuple[str, ...]:
    """What a user asks ``--ablate`` for (``"pose,bsdf"``, a list, ``""`` or ``"none"``): the items, sorted by name
    (as a run spec records them); SettingError naming ``field`` for an unknown one.

    >>> parse_ablations("pose, bsdf")
    ('bsdf', 'pose')
    """
    items = parse_ablation(text)
    bad = [a for a in items if a not in ABLATIONS]
    if bad:
        raise SettingError(f"unknown {{0}} item(s) {literal(', '.join(bad))}; allowed: {', '.join(ABLATIONS)}", field)
    return tuple(sorted(items))


def ablated_switches(ablations: Iterable[str]) -> dict[str, bool]:
    """``{switch: on}`` for every appearance switch an ablation can turn off (off where one of ``ablations`` does):
    ``dataclasses.replace(app_config, **ablated_switches(...))``."""
    off = {s for a in ablations for s in ABLATIONS[a].switches}
    return {s: s not in off for a in ABLATIONS.values() for s in a.switches}


def ablations_help() -> str:
    """``--ablate`` help: each ablation and what it switches off."""
    return "; ".join(f"{a.name}: {a.help}" for a in ABLATIONS.values())


def condition(method: str, ablation: str | Iterable[str] | None = None) -> Condition:
    """The condition of a method and its ablations (``"none"``, a comma list or a sequence)."""
    m = str(method or "").strip()
    if not m:
        raise CamoError("a condition needs a method name")
    if WITHOUT in m:
        raise CamoError(f"method name {m!r} may not contain {WITHOUT!r} (it separates a condition id's ablations)")
    return Condition(m, parse_ablation(ablation))


def condition_of_config(config: Mapping[str, Any]) -> Condition:
    """The condition of a run from its parsed ``config.toml``: ``method`` and ``ablate`` at the top (run spec,
    spec_version 2) or in the ``[run]`` table (the layout before run specs); method ``ours`` when absent."""
    run = config if "method" in config or "ablate" in config else dict(config.get("run") or {})
    return condition(str(run.get("method", OURS)), run.get("ablate", ()))


def parse_id(text: str) -> Condition:
    """The condition an id names (inverse of :attr:`Condition.id`)."""
    method, sep, rest = str(text).partition(WITHOUT)
    if not method:
        raise CamoError(f"not a condition id: {text!r}")
    return Condition(method, parse_ablation(rest.split(JOIN)) if sep else ())


def label_of_id(text: str) -> str:
    """The label of a condition id (``ours-without-inpainting`` -> ``w/o Inpainting``)."""
    return parse_id(text).label
