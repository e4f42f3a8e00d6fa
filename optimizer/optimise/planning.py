"""A run's effect plan: the pilot on the run's own scene, starting object and stages, decided once and recorded.

``ours`` and every baseline plan the same way (:func:`run_plan`): the pilot renders the starting object (the
appearance's initial values from the pack's material, at its initial pose) from the run's training cameras (stream
``pilot`` of :mod:`camo_base.seeds`, the targets' numbers), and :class:`optimizer.rendering.planner.Planner` decides
for the optimised parameters at the largest spp the plan's depth serves (the targets'), untimed, so that a run's
plan is reproducible (a depth cut is priced in the pilot's path vertices; ``timed=True``: in seconds timed at the
run's own size, up to four of the training views at their resolution and the training spp,
:meth:`Planner.time_cut`). Baselines plan the full parameter set of ``ours`` with its starting values, so a baseline
and ``ours`` with the same settings (no ablation) render bit-identical targets; an ablation (``--ablate
transmittance``: an opaque start) is planned as what it is. ``spec.planner = False`` (``--no-planner``) is full path
tracing (:func:`optimizer.rendering.planner.full_plan`). The plan travels in the checkpoint (``plan/json``): a
resumed run takes it from there and does not run the pilot again.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from camo_base import seeds
from optimizer.rendering.appearance import AppearanceConfig, Geometry, initial_values, object_mesh
from optimizer.rendering.planner import Plan, Planner, full_plan, moves_geometry

CHECKPOINT_KEY = "plan/json"


def stage_spp(spec) -> dict[str, int]:
    """The spp of the run's stages that the plan's depth serves."""
    out = {"training": int(spec.spp.train), "targets": int(spec.spp.target)}
    if spec.method == "ours" and spec.holdout.views:
        out["holdout"] = int(spec.holdout.spp)
    return out


def run_plan(spec, pack, env, prepared, cams, app: AppearanceConfig, log=lambda s: None,
             state: dict[str, np.ndarray] | None = None) -> Plan:
    """The plan of a run (module doc) of appearance ``app`` (its optimised parameters and starting values); from
    ``state`` (a checkpoint) when it holds one."""
    params = app.planner_params()
    if not spec.planner:
        return full_plan("optimize", geometry=moves_geometry(params))
    if state is not None and CHECKPOINT_KEY in state:
        try:
            return Plan.from_dict(json.loads(str(state[CHECKPOINT_KEY])))
        except (TypeError, ValueError, KeyError):
            from camo_base.errors import CamoError

            raise CamoError("checkpoint is corrupt: bad plan/json") from None
    return measure_plan(pack, env, prepared, cams, app, spec.seed, stage_spp(spec), spec.shadow_gradients, log)


def measure_plan(pack, env, prepared, cams, app: AppearanceConfig, seed: int, spp: dict[str, int],
                 shadow_gradients: bool = False, log=lambda s: None, timed: bool = False) -> Plan:
    """Run the pilot on the starting object of appearance ``app`` (its initial values from the pack's material, the
    initial pose) seen from ``cams`` and plan ``app``'s optimised parameters for the stages' ``spp`` (module doc);
    ``timed``: price a depth cut in seconds measured here (not reproducible across machines or loads)."""
    params = app.planner_params()
    geometry = Geometry.build(prepared, pack.object, app)
    values = initial_values(app, pack.material)

    def mesh():
        return object_mesh(geometry, values, app)

    planner = Planner()
    pilot = planner.pilot(env, mesh, cams, seed=seeds.seed("pilot", seed),
                          geometry=moves_geometry(params), size=pack.object.size)
    cut = planner.admissible_cut(pilot, params, spp)
    train_spp = int(spp.get("training", min(spp.values())))
    timing = None if cut is None or not timed else planner.time_cut(pack, env, params, mesh, cams, pilot, cut, train_spp,
                                                       seed=seeds.seed("pilot", seed),
                                                       shadow_gradients=shadow_gradients)
    pl = planner.plan(pack, env, params, "optimize", pilot, spp, shadow_gradients, cut_timing=timing)
    log(f"plan: pilot {pilot.seconds:.1f} s" + ("" if timing is None else
                                                f", the depth cut to {cut} timed: saves {timing.saving:.0%}") +
        f"; max_depth {pl.max_depth}, Russian roulette from {pl.rr_depth}, "
        f"region {pilot.to_dict()['region_share']:.0%} of the pilot's frames")
    return pl


def narrowed(pl: Plan, pack, env, params: set[str], shadow_gradients: bool) -> Plan:
    """``pl`` (a measured plan) for fewer optimised ``params`` (an ablation, Stage 2 without pose): the same measured
    depth, Russian roulette, region and figures, the integrator ``params`` need."""
    from optimizer.rendering.planner import _structure

    base = _structure(pack, env, params, "optimize", shadow_gradients, pl.max_depth, pl.rr_depth,
                      [r for r in pl.reasons if r[0] in ("max_depth", "rr_depth")])
    base.reasons += [r for r in pl.reasons if r[0] == "region"]
    base.region, base.effects, base.spp, base.pilot, base.curve = pl.region, pl.effects, pl.spp, pl.pilot, pl.curve
    base.drop_emitters, base.region_threshold = list(pl.drop_emitters), pl.region_threshold
    base.region_search = pl.region_search
    return base


def checkpoint_entry(pl: Plan) -> dict[str, np.ndarray]:
    return {CHECKPOINT_KEY: np.array(json.dumps(pl.to_dict()))} if pl.measured else {}


def config_record(pl: Plan) -> dict[str, Any]:
    """The plan as ``config.toml``'s ``[plan]`` table records it (its curve is in ``summary.json``)."""
    d = pl.to_dict()
    d.pop("curve", None)
    d["reasons"] = [f"{k}: {v}" for k, v in pl.reasons]
    return d
