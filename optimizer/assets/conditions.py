"""Experimental conditions: the one place that names a result's method and ablations for people and tables.

A *condition* is what a run's spec says it is: its ``method`` and the items of its ``ablate`` list (``camo optimize
--method M --ablate a,b``; ``config.toml``'s ``method`` and ``ablate``). Every table and file that shows or stores a
condition takes both its id and its label from :func:`condition`:

* the evaluation report's Table II rows (:mod:`evaluation.report`),
* the stimuli manifest (``condition`` and ``label`` of every stimulus, :mod:`study_site.stimuli`),
* the study database (``condition`` and ``label`` columns of the plan and of every trial, :mod:`study_site.db`),
* Table I and the power analysis (:mod:`study_site.analysis`, :mod:`study_site.power`).

``id``: machine-readable and stable, ``ours``, ``ours-without-inpainting``, ``ours-without-pose+bsdf`` (ablations
in the paper's order, joined by ``+``); ``label``: the paper's wording, ``Ours``, ``w/o Inpainting``,
``w/o Pose + BSDF``. An ablation *removes* a component: ``--ablate inpainting`` is the method **without**
Stage 2's inpainting, never "ours plus inpainting".

Data, not code: :data:`METHODS` and :data:`ABLATIONS` below are the tables; a method the toolkit does not know (an
external asset labelled ``--method theirs``) keeps its own name as label. ``tests/test_conditions.py`` checks that
every ``--method`` and ``--ablate`` name of :mod:`optimizer.optimise.spec` has an entry here.

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

from camo_base.errors import CamoError

#: Every method (``--method`` names, in the paper's Table II order, ``ours`` last): its label.
METHODS: dict[str, str] = {
    "transparent": "Transparent",
    "random": "Random [6]",
    "mean": "Mean [6]",
    "greedy": "Greedy [6]",
    "ganmouflage": "GANmouflage [7]",
    "ganmouflage-paper": "GANmouflage [7] (paper settings)",
    "diffusion2d": "2D Diffusion",
    "ours": "Ours",
}
#: Every ``--ablate`` item, in the paper's order: ``(component name, label of ours without only it)``.
ABLATIONS: dict[str, tuple[str, str]] = {
    "pose": ("Pose", "w/o Pose"),
    "displacement": ("Displacement", "w/o Displacement"),
    "bsdf": ("BSDF", "w/o BSDF (Only Albedo)"),
    "transmittance": ("Transmittance", "w/o Transmittance"),
    "inpainting": ("Inpainting", "w/o Inpainting"),
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
        names = [ABLATIONS[a][0] if a in ABLATIONS else a for a in self.ablations]
        if self.method == OURS:
            if not self.ablations:
                return METHODS[OURS]
            if len(self.ablations) == 1 and self.ablations[0] in ABLATIONS:
                return ABLATIONS[self.ablations[0]][1]
            return "w/o " + " + ".join(names)
        base = METHODS.get(self.method.lower(), self.method)
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
        if m in METHODS:
            return (0, list(METHODS).index(m), ",".join(self.ablations))
        return (1, 0, m + "," + ",".join(self.ablations))


def parse_ablation(ablation: str | Iterable[str] | None) -> tuple[str, ...]:
    """Ablation items of ``"none"``, ``""``, ``"pose,bsdf"`` or a list, de-duplicated, in :data:`ABLATIONS` order
    (unknown items after them, alphabetically)."""
    if ablation is None:
        items: list[str] = []
    elif isinstance(ablation, str):
        items = [a.strip() for a in ablation.split(",")]
    else:
        items = [str(a).strip() for a in ablation]
    items = sorted({a for a in items if a.lower() not in _NONE})
    order = list(ABLATIONS)
    return tuple(sorted(items, key=lambda a: (order.index(a) if a in order else len(order), a)))


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
