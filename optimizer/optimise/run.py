"""``camo optimize``: run a :class:`optimizer.optimise.spec.RunSpec` into its run directory.

:func:`run` takes a spec and runs its method: ``ours`` here (:func:`optimize`: Stage 1, then Stage 2 unless
ablated), a baseline through :func:`run_baseline` (what it computes: its
:class:`~optimizer.optimise.method.Method` in :data:`optimizer.optimise.methods.METHODS`). The run directory (see
CONTRIBUTING.md) is written through :mod:`optimizer.assets.rundir` (``config.toml`` = the spec + provenance,
``log.jsonl``, ``summary.json``) and :mod:`optimizer.assets.result` (maps, ``result.glb``, ``result.obj``,
``scene.xml``, ``pose.json``, previews, renders); ``checkpoint.npz`` (every ``checkpoint_every`` iterations;
``--resume`` continues from it and ends with the same numbers as an uninterrupted run) is written here. Every file
is written atomically.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from camo_base import atomic, imaging
from camo_base.errors import CamoError, SettingError
from camo_base.provenance import versions
from optimizer.assets.rundir import CHECKPOINT, LOG, RunTransaction, provenance, write_config, write_log
from optimizer.optimise.finish import finish
from optimizer.optimise.holdout import Holdout
from optimizer.optimise.spec import RunSpec
from optimizer.optimise.stage1 import Stage1
from optimizer.rendering.appearance import AppearanceConfig
from optimizer.scenes.scenepack import ScenePack


def run(spec: RunSpec, out: str | Path, resume: bool = False, overwrite: bool = False, progress: bool = True,
        threads: int | None = None, accept_versions: bool = False) -> Path:
    """Run ``spec`` into the run directory ``out`` (validated first; SettingError/CamoError, one line, for bad input).

    The run writes into a staging folder beside ``out`` and moves it into place only once it finished
    (:class:`optimizer.assets.rundir.RunTransaction`): a failure, Ctrl-C or a kill leaves an earlier run in ``out``
    byte for byte (``overwrite``: it is replaced at the end). ``resume``: continue from the checkpoint of the
    unfinished staging folder or of ``out`` (``ours`` only); refused for a run recorded by another spec layout or
    major camo / Mitsuba version unless ``accept_versions``; each attempt is appended to ``config.toml``'s history.
    ``threads``: CPU threads of the LLVM backend (and torch, for GANmouflage); not part of the spec (it does not
    change the result), recorded in the history."""
    
    spec.validate()
    if resume and spec.method_info.compute is not None:
        raise SettingError(f"{{0}}: method {spec.method!r} is a one-shot baseline and keeps no checkpoint; run it "
                           "again", "resume")
    with RunTransaction(out, resume, overwrite, accept_versions, versions()) as txn:
        if spec.method_info.compute is None:
            optimize_in(spec, txn, progress=progress, threads=threads)
        else:
            baseline_in(spec, txn, progress=progress, threads=threads)
    return Path(out)


def optimize(spec: RunSpec, out: str | Path, resume: bool = False, overwrite: bool = False,
             progress: bool = True, threads: int | None = None, accept_versions: bool = False) -> Path:
    """:func:`run` for method ``ours``."""
    if spec.method != "ours":
        raise ValueError(f"optimize runs method ours, not {spec.method!r} (use run)")
    return run(spec, out, resume, overwrite, progress, threads, accept_versions)


def run_baseline(spec: RunSpec, out: str | Path, overwrite: bool = False, progress: bool = True,
                 threads: int | None = None) -> Path:
    """:func:`run` for a baseline (its :class:`~optimizer.optimise.method.Method` in
    :data:`optimizer.optimise.methods.METHODS` says what it computes)."""
    if spec.method_info.compute is None:
        raise ValueError(f"run_baseline runs baselines; method {spec.method} runs through optimizer.optimise.run.run")
    return run(spec, out, overwrite=overwrite, progress=progress, threads=threads)


def baseline_in(spec: RunSpec, txn: RunTransaction, progress: bool = True, threads: int | None = None) -> None:
    """A baseline's run into the staging folder of ``txn`` (options get the thread count of a torch method)."""
    from optimizer import backend
    from optimizer.optimise.baselines.common import run_directory

    method, options = spec.method_info, spec.options
    if options is not None and threads is not None and hasattr(options, "threads"):
        options = dataclasses.replace(options, threads=threads)
    backend.init(threads=threads)
    run_directory(spec, txn.path, lambda setup: method.compute(setup, options, progress), progress, threads,
                  provenance(versions(), None, "start"))


def _read_log(path: Path, stage1_upto: int | None, stage2_upto: int | None) -> list[dict[str, Any]]:
    """The log records a checkpoint covers: Stage 1 up to ``stage1_upto`` (all when None), Stage 2 up to
    ``stage2_upto`` (none when None)."""
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:  # a line torn by a kill: the checkpoint never covers it
            continue
        it, stage = rec.get("iteration", 0), rec.get("stage", 1)
        if (stage == 1 and (stage1_upto is None or it <= stage1_upto)) or \
           (stage == 2 and stage2_upto is not None and it <= stage2_upto):
            out.append(rec)
    return out


def load_checkpoint(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # zipfile/ValueError/OSError on corrupt files
        raise CamoError(f"checkpoint {path} is corrupt or unreadable ({type(exc).__name__}); delete it or start a new run") from None


def optimize_in(spec: RunSpec, txn: RunTransaction, progress: bool = True, threads: int | None = None) -> None:
    """Stage 1 and, unless ablated, Stage 2 of ``spec`` (method ``ours``) into the staging folder of ``txn``: the
    set-up, Stage 1's named preparation steps (:class:`~optimizer.optimise.stage1.Stage1`), the stages' loops
    with their checkpoints, then the result (:func:`finish_run`)."""
    from optimizer import backend
    from optimizer.scenes.environments import get_environment

    out = txn.path
    backend.init(threads=threads)
    env = get_environment(spec.pack.environment)
    pack, rough_note = glint_safe_start(spec.pack, env, spec)
    fingerprint = spec.fingerprint()
    state = _resume_state(spec, out, fingerprint) if txn.resume else None
    resume_stage = int(state["stage"]) if state is not None and "stage" in state else 1
    inpainter = _inpainter(spec)  # first: a bad weights folder must fail before Stage 1 runs
    say = (lambda s: print(s, file=sys.stderr)) if progress else (lambda s: None)
    t_setup = time.perf_counter()
    setup = _setup(spec, pack, env, rough_note, say, state)
    s1, hold, warm_seconds = _prepare_stage1(spec, setup, state, say)
    setup_seconds = time.perf_counter() - t_setup - warm_seconds
    history = _restore(s1, hold, state, resume_stage, out) if state is not None else []
    write_config(out, spec.to_dict(), {
        **provenance(versions(), txn.previous, "resume" if txn.resume else "start",
                     **({"from_stage": resume_stage, "from_iteration": int(state["iteration"])} if state else {})),
        "plan": _plan_record(setup, s1), "fingerprint": {"value": fingerprint}})
    write_log(out, history)
    ctx = _Loop(spec, out, fingerprint, s1, hold, history, progress, {"offset": warm_seconds})
    with open(out / LOG, "a", encoding="utf-8") as log:
        ctx.log = log
        final_stage = ctx.stage1(resume_stage, state)
        if 2 in spec.stages:
            final_stage = ctx.stage2(setup, inpainter, resume_stage, state, warm_seconds, say)
    values = hold.best if hold is not None and hold.best is not None else final_stage.current_values()
    if spec.snapshot_every > 0:  # the result itself, at the run's end (with a holdout: the chosen iterate)
        chosen = hold.best_check if hold is not None and hold.best_check else \
            {"stage": final_stage.STAGE, "iteration": final_stage.iteration}
        write_snapshot(out / "snapshots" / "result.npz", values,
                       warm_seconds + stage_seconds(history, 1) + stage_seconds(history, 2),
                       chosen["iteration"], chosen["stage"])
    finish_run(out, final_stage, setup.pack, setup.env, history, setup_seconds, spec, s1.warm_start_info,
               values=values, holdout=hold.summary() if hold is not None else None, pose=s1.pose_search_info,
               start=s1.start_search_info, init=s1.init_search_info, clear=s1.clear_search_info, plan=setup.plan)


@dataclasses.dataclass
class _Setup:
    """What both stages share: the pack (its start roughness made glint-safe), environment (without the emitters
    the plan dropped), prepared object, cameras, Stage 1's plan (measured by the pilot) and the appearance config."""

    pack: ScenePack
    env: Any
    prepared: Any
    cams: list
    plan: Any
    app: AppearanceConfig
    rough_note: str | None
    plan_for: Any


def _setup(spec: RunSpec, pack: ScenePack, env, rough_note: str | None, say, state=None) -> _Setup:
    """The prepared object, cameras and the run's effect plan: the pilot on this scene and start
    (:func:`optimizer.optimise.planning.run_plan`; a resumed run's plan comes from its checkpoint)."""
    from optimizer.scenes.cameras import cameras
    from optimizer.rendering.placement import prepare_object
    from optimizer.optimise.planning import narrowed, run_plan
    from optimizer.rendering.planner import full_plan, moves_geometry

    prepared = prepare_object(pack)
    cams = cameras(pack)
    pl = run_plan(spec, pack, env, prepared, cams, spec.appearance, say, state)
    env = pl.environment(env)

    def plan_for(a: AppearanceConfig):
        params = a.planner_params()
        return narrowed(pl, pack, env, params, spec.shadow_gradients) if spec.planner else \
            full_plan("optimize", geometry=moves_geometry(params))

    advice = dict(pl.reasons).get("initial roughness")
    if rough_note:
        say(f"note: {rough_note}")
    elif advice:
        say(f"note: initial roughness {advice}")
    return _Setup(pack, env, prepared, cams, pl, spec.appearance, rough_note, plan_for)


def _resume_state(spec: RunSpec, out: Path, fingerprint: str) -> dict[str, np.ndarray]:
    """The checkpoint a resumed run continues, checked against ``spec`` (SettingError naming ``resume``)."""
    state = load_checkpoint(out / CHECKPOINT)
    if str(state.get("fingerprint", "")) != fingerprint:
        raise SettingError("{0}: the run was made with a different configuration; start a new run instead", "resume")
    stage = int(state["stage"]) if "stage" in state else 1
    if stage == 2 and not spec.time_budget and not spec.holdout.patience and \
            int(state.get("stage1_iterations", -1)) != spec.stage1.iterations:
        raise SettingError(f"{{0}}: the run finished Stage 1 with {int(state.get('stage1_iterations', -1))} "
                           f"iterations; it cannot continue with {{1}} {spec.stage1.iterations} (start a new run)",
                           "resume", "stage1.iterations")
    return state


def _inpainter(spec: RunSpec):
    """Stage 2's inpainter (None without Stage 2)."""
    if 2 not in spec.stages:
        return None
    from optimizer.optimise.inpaint import get_inpainter

    s2c = spec.stage2_config()
    opts = {"sdxl_path": s2c.sdxl_path, "controlnet_path": s2c.controlnet_path, "prompt": s2c.prompt} \
        if s2c.backend == "diffusers" else {}
    return get_inpainter(s2c.backend, **opts)


def _prepare_stage1(spec: RunSpec, setup: _Setup, state, say) -> tuple[Stage1, Holdout | None, float]:
    """Stage 1 and its held-out views, prepared step by step: the turn search, the targets, the warm start, the
    optimiser and scene, then the start search (a resumed run reuses the recorded choices). Returns the stage, the
    held-out views (or None) and the seconds of the searches and the warm start (counted as optimisation; paid from
    Stage 1's time budget)."""
    budget1 = stage1_budget(spec)
    s1cfg = spec.stage1_config(time_budget=budget1)
    s1 = Stage1(setup.pack, setup.env, setup.prepared, setup.cams, setup.plan, s1cfg, setup.app, say)
    s1.search_pose(checkpointed_turn(state))
    s1.render_targets()
    s1.warm_start(checkpointed_start(state))
    s1.build()
    hold = Holdout.for_stage(spec.holdout, s1) if spec.holdout.views else None
    if state is None and hold is not None and s1cfg.roughness_search and "roughness" in setup.app.trainable():
        s1.search_start(s1cfg.roughness_search, lambda values: hold.score(values)[0])
    if state is None and hold is not None and s1cfg.init_search:
        alternatives = init_alternatives(spec, setup.app)
        if alternatives:
            s1.search_init(alternatives, lambda values: hold.score(values)[0])
    elif state is not None and "init_search/info" in state:
        # a resumed run: the maps come from the checkpoint; the record is the search's (summary.json)
        s1.init_search_info = checkpointed_init(state)
    if state is None and hold is not None and s1cfg.clear_candidate:
        s1.search_clear(s1cfg.clear_candidate, hold.score)
    elif state is not None and "clear_search/info" in state:
        # a resumed run: the maps come from the checkpoint, the IOR from the search's record
        s1.clear_search_info = checkpointed_clear(state)
        if s1.clear_search_info.chosen_eta != s1.app.eta:
            s1.use_eta(s1.clear_search_info.chosen_eta)
    setup.app = s1.app  # Stage 2, the final renders and the exported asset keep Stage 1's IOR
    warm_seconds = sum(info.seconds for info in (s1.warm_start_info, s1.pose_search_info, s1.start_search_info,
                                                 s1.init_search_info, s1.clear_search_info) if info is not None)
    if budget1:
        s1.time_budget = max(budget1 - warm_seconds, 1e-3)
    return s1, hold, warm_seconds


def init_alternatives(spec: RunSpec, app: AppearanceConfig) -> dict[str, dict[str, np.ndarray]]:
    """The init search's alternatives (:mod:`optimizer.optimise.startsearch`): the BSDF maps of the start
    ``spec`` takes without ``init`` (:meth:`RunSpec.start_without_init`), one per starting roughness of its preset's
    roughness search (or the start's own roughness), labelled; empty when ``init`` changed nothing."""
    from optimizer.optimise.presets import PRESETS
    from optimizer.rendering.appearance import initial_values
    from optimizer.scenes.bsdf_maps import MAPS

    material = spec.start_without_init()
    if material is None:
        return {}
    preset = PRESETS.get(spec.preset) if spec.preset is not None else None
    rough = tuple((preset.stage1.get("roughness_search") if preset else None) or (material.roughness,))
    out = {}
    for r in rough if app.map_on("roughness") else (material.roughness,):
        maps = initial_values(app, dataclasses.replace(material, roughness=float(r)))
        out[f"without init, roughness {float(r):g}"] = {k: maps[k] for k in MAPS}
    return out


def _restore(s1: Stage1, hold: Holdout | None, state: dict[str, np.ndarray], resume_stage: int,
             out: Path) -> list[dict[str, Any]]:
    """A resumed run's Stage 1 (or Stage 2 checkpoint checks), held-out record and log up to its checkpoint."""
    if resume_stage == 1:
        s1.load_checkpoint_state(state)  # validates keys, shapes and values (CamoError)
    else:
        _check_stage2_checkpoint(state, s1)
    if hold is not None:
        hold.load_state(state)
        s1.stop_requested = resume_stage == 1 and hold.patience_spent()
    history = _read_log(out / LOG, s1.iteration if resume_stage == 1 else None,
                        int(state["iteration"]) if resume_stage == 2 else None)
    s1.elapsed = stage_seconds(history, 1)
    return history


def _plan_record(setup: _Setup, s1: Stage1) -> dict[str, Any]:
    from optimizer.optimise.planning import config_record

    rec = {**config_record(setup.plan),
           # as built for the training renders: explicit per-term sample counts, mi.render(spp=render_spp)
           "training_integrator": s1.scene_integrator, "render_spp": s1.render_spp}
    if setup.rough_note:
        rec["start_roughness"] = setup.pack.material.roughness  # rough_start raised the pack's (spec.pack)
    return rec


@dataclasses.dataclass
class _Loop:
    """The stages' loops of one run: logging, checkpoints (with the held-out record and the searches' choices)
    and snapshots."""

    spec: RunSpec
    out: Path
    fingerprint: str
    s1: Stage1
    hold: Holdout | None
    history: list
    progress: bool
    clock: dict[str, float]
    log: Any = None
    values1: dict[str, np.ndarray] | None = None
    s1_iterations: int = 0

    def held(self, extra=None) -> dict[str, np.ndarray]:
        """Checkpoint entries beside a stage's own: the held-out views' best iterate, the searches' choices, the
        measured plan (a resumed run does not run the pilot again)."""
        from optimizer.optimise.planning import checkpoint_entry

        s1 = self.s1
        turn = {"pose_search/info": np.array(json.dumps(s1.pose_search_info.to_dict()))} if s1.pose_search_info \
            else {}
        turn.update(checkpoint_entry(s1.plan))
        if s1.start_search_info:
            turn["start_search/info"] = np.array(json.dumps(s1.start_search_info.to_dict()))
        if s1.init_search_info:
            turn["init_search/info"] = np.array(json.dumps(s1.init_search_info.to_dict()))
        if s1.clear_search_info:
            turn["clear_search/info"] = np.array(json.dumps(s1.clear_search_info.to_dict()))
        return {**(extra or {}), **(self.hold.state() if self.hold is not None else {}), **turn}

    def loop(self, stage: Stage1, label: str, extra=None) -> None:
        _loop(stage, label, self.progress, self.log, self.history,
              lambda st: save_checkpoint(self.out / CHECKPOINT, st, self.fingerprint, self.held(extra)),
              self.spec.checkpoint_every, snapshots(self.out, self.spec.snapshot_every, self.clock), self.hold,
              self.clock)

    def stage1(self, resume_stage: int, state) -> Stage1:
        """Stage 1's iterations (none when a resumed run is past it); returns the stage."""
        if resume_stage == 1:
            self.loop(self.s1, "stage 1")
            self.values1, self.s1_iterations = self.s1.current_values(), self.s1.iteration
        else:
            self.values1 = {k[len("stage1/"):]: v for k, v in state.items() if k.startswith("stage1/")}
            self.s1_iterations = int(state["stage1_iterations"])
        return self.s1

    def stage2(self, setup: _Setup, inpainter, resume_stage: int, state, warm_seconds: float, say) -> Stage1:
        """Stage 2 from Stage 1's result: it keeps Stage 1's pose; its displacement is refined too unless
        ``stage2.displacement`` is off (then no geometry moves and the planner drops the projective integrator).
        Writes the pseudo ground truths and their strips to ``stage2/``; returns the stage."""
        from optimizer.optimise.stage2 import Stage2, pseudo_gt_strip

        spec, s1, s2c = self.spec, self.s1, self.spec.stage2_config()
        app2 = dataclasses.replace(setup.app, pose=False, freeze_displacement=not s2c.displacement)
        s2 = Stage2(setup.pack, setup.env, setup.prepared, setup.cams, setup.plan_for(app2), spec.stage1_config(),
                    app2, say, initial=self.values1, stage2=s2c, inpainter=inpainter).prepare(targets=s1.targets)
        s2.initial_render = s1.initial_render
        s2.total_iterations = s2c.iterations
        s1_seconds = warm_seconds + stage_seconds(self.history, 1)
        if spec.time_budget:
            s2.time_budget = max(spec.time_budget - s1_seconds, 1e-3)
        self.clock["offset"] = s1_seconds
        if resume_stage == 2:
            s2.load_checkpoint_state(state)
            s2.elapsed = stage_seconds(self.history, 2)
        extra = {f"stage1/{k}": v for k, v in self.values1.items()}
        extra["stage1_iterations"] = np.array(self.s1_iterations)
        self.loop(s2, "stage 2", extra)
        for v in sorted(s2.pseudo_np):
            imaging.save_png(self.out / "stage2" / f"view_{v:02d}_pseudo_gt.png", s2.pseudo_np[v])
            imaging.save_png(self.out / "stage2" / f"view_{v:02d}_strip.png", pseudo_gt_strip(s2, v))
        return s2


def checkpointed_turn(state: dict[str, np.ndarray] | None):
    """The turn search's record in a checkpoint (a resumed run starts from the same turn), or None."""
    from optimizer.optimise.posesearch import PoseSearchInfo

    if state is None or "pose_search/info" not in state:
        return None
    try:
        return PoseSearchInfo(**json.loads(str(state["pose_search/info"])))
    except (TypeError, ValueError):
        raise CamoError("checkpoint is corrupt: bad pose_search/info") from None


def checkpointed_start(state: dict[str, np.ndarray] | None):
    """The start search's record in a checkpoint (a resumed run starts from the same roughness), or None."""
    from optimizer.optimise.startsearch import StartSearchInfo

    if state is None or "start_search/info" not in state:
        return None
    try:
        info = StartSearchInfo(**json.loads(str(state["start_search/info"])))
        float(info.chosen)
        return info
    except (TypeError, ValueError):
        raise CamoError("checkpoint is corrupt: bad start_search/info") from None


def checkpointed_init(state: dict[str, np.ndarray]):
    """The init search's record in a checkpoint (CamoError when it is unreadable)."""
    from optimizer.optimise.startsearch import InitSearchInfo

    try:
        return InitSearchInfo(**json.loads(str(state["init_search/info"])))  # its seconds count, as the turn's do
    except (TypeError, ValueError):
        raise CamoError("checkpoint is corrupt: bad init_search/info") from None


def checkpointed_clear(state: dict[str, np.ndarray]):
    """The clear-glass search's record in a checkpoint (CamoError when it is unreadable)."""
    from optimizer.optimise.startsearch import ClearSearchInfo

    try:
        info = ClearSearchInfo(**json.loads(str(state["clear_search/info"])))
        if not (math.isfinite(float(info.chosen_eta)) and float(info.chosen_eta) > 1.0):
            raise ValueError(info.chosen_eta)
        return info
    except (TypeError, ValueError):
        raise CamoError("checkpoint is corrupt: bad clear_search/info") from None


def glint_safe_start(pack: ScenePack, env, spec: RunSpec) -> tuple[ScenePack, str | None]:
    """With ``spec.rough_start``, a pack whose initial roughness would keep sun glints (the planner's "initial
    roughness" advice: a compact light and roughness below ``planner.GLINT_ROUGHNESS``) starts at that roughness
    instead; returns the pack (a copy when changed) and a note saying so, or ``(pack, None)``."""
    from optimizer.rendering.planner import GLINT_ROUGHNESS, glint_advice

    params = spec.appearance.planner_params()
    if not spec.rough_start or not glint_advice(pack, env, params):
        return pack, None
    old = pack.material.roughness
    pack = dataclasses.replace(pack, material=dataclasses.replace(pack.material, roughness=GLINT_ROUGHNESS))
    return pack, (f"initial roughness {old:g} -> {GLINT_ROUGHNESS:g}: the scene has a compact light, and a smoother "
                  "start keeps specular glints (docs/optimizer.md, 'Why the built-in scenes start rough'); --init roughness=X with "
                  "--init-search off, or --preset paper, keeps the pack's value")


def stage1_budget(spec: RunSpec) -> float | None:
    """Stage 1's share of ``--time-budget`` (warm start included): 80 % when Stage 2 runs, all of it otherwise;
    Stage 2 gets whatever Stage 1 left."""
    if not spec.time_budget:
        return None
    return 0.8 * spec.time_budget if 2 in spec.stages else float(spec.time_budget)


def stage_seconds(history: list[dict[str, Any]], stage: int) -> float:
    """Wall-clock seconds of a stage's logged iterations (Stage 2: inpainting and its render included; held-out
    checks included)."""
    return float(sum(h.get("seconds_total", h.get("seconds", 0.0)) + h.get("seconds_holdout", 0.0)
                     for h in history if h.get("stage") == stage))


def snapshots(out: Path, every: int, clock: dict[str, float]):
    """A callback saving ``snapshots/sS_XXXX.npz`` (the parameters and the optimisation seconds so far) every
    ``every`` iterations, or None (the run adds ``snapshots/result.npz``, its result, at the end). ``clock["offset"]``: seconds spent before this stage (warm start, Stage 1)."""
    if every <= 0:
        return None

    def save(stage: Stage1) -> None:
        if stage.iteration % every and not stage.done():
            return
        write_snapshot(out / "snapshots" / f"s{stage.STAGE}_{stage.iteration:04d}.npz", stage.current_values(),
                       clock["offset"] + stage.elapsed, stage.iteration, stage.STAGE)

    return save


def write_snapshot(path: Path, values: dict[str, np.ndarray], seconds: float, iteration: int, stage: int) -> None:
    """One snapshot file: the parameters, the optimisation seconds so far, and the iterate's stage and iteration
    (``snapshots/result.npz``: the run's result, with the stage and iteration it was taken from)."""
    vals = dict(values)
    vals["seconds"] = np.array(seconds)
    vals["iteration"] = np.array(iteration)
    vals["stage"] = np.array(stage)
    with atomic.atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **vals)


def _check_stage2_checkpoint(state: dict[str, np.ndarray], s1: Stage1) -> None:
    """Validate a Stage 2 checkpoint's Stage 1 result before anything in the run directory changes."""
    it = state.get("iteration")
    if it is None or it.shape != () or not np.issubdtype(it.dtype, np.integer) or int(it) < 0:
        raise CamoError("checkpoint is corrupt: no valid iteration count")
    for name, ref in s1.values.items():
        arr = state.get(f"stage1/{name}")
        if arr is None or arr.shape != ref.shape or not np.isfinite(arr).all():
            raise CamoError(f"checkpoint is corrupt or from another configuration: bad stage1/{name}")
    t = state.get("adam_t")
    if t is None or t.shape != () or not np.issubdtype(t.dtype, np.integer):
        raise CamoError("checkpoint is corrupt: no integer optimiser step count")
    for name in dataclasses.replace(s1.app, pose=False).trainable():
        for key in ("value", "m", "v"):
            arr = state.get(f"{key}/{name}")
            if arr is None or arr.size != s1.values[name].size or not np.isfinite(arr).all():
                raise CamoError(f"checkpoint is corrupt or from another configuration: bad {key}/{name}")


def _loop(stage: Stage1, label: str, progress: bool, log, history: list, checkpoint, every: int,
          snapshot=None, holdout=None, clock: dict[str, float] | None = None) -> None:
    """Run ``stage`` to its end: log, checkpoint and snapshot its steps; with ``holdout`` (a
    :class:`~optimizer.optimise.holdout.Holdout`) check the held-out views when due (Stage 1's start, every
    ``holdout.every`` iterations, each stage's end), count the check's seconds in the stage's clock and its log
    record (``seconds_holdout``, ``holdout_mse``), and end Stage 1 early once its patience is spent."""
    from tqdm import tqdm

    offset = (clock or {}).get("offset", 0.0)
    # seconds of the check at Stage 1's start: counted with the first step (so that a time budget below a step's
    # cost still takes one step, as without checks)
    pending = 0.0
    if holdout is not None and stage.iteration == 0 and stage.STAGE == 1:
        pending = holdout.check(stage.current_values(), stage.STAGE, 0, offset + stage.elapsed)["check_seconds"]
    iterations = stage.total_iterations
    if snapshot is not None and stage.iteration == 0:
        snapshot(stage)
    bar = tqdm(total=iterations, initial=stage.iteration, disable=not progress, desc=label, unit="it")
    while not stage.done():
        rec = stage.step()
        stage.elapsed += pending
        if holdout is not None and holdout.due(stage.iteration, stage.done()):
            chk = holdout.check(stage.current_values(), stage.STAGE, stage.iteration, offset + stage.elapsed)
            stage.elapsed += chk["check_seconds"]
            rec["holdout_mse"] = chk["mse"]
            rec["seconds_holdout"] = chk["check_seconds"] + pending
            pending = 0.0
            if stage.STAGE == 1 and holdout.patience_spent():
                stage.stop_requested = True
        elif pending:
            rec["seconds_holdout"], pending = pending, 0.0
        history.append(rec)
        log.write(json.dumps(rec) + "\n")
        log.flush()
        # the photometric term too: L_disp (Eq. 5) starts at 0 and grows as the displacement is used, so the
        # total can rise while the image match improves
        bar.set_postfix(loss=f"{rec['loss']:.4f}", photo=f"{rec['loss_photo']:.4f}", nonfinite=rec["nonfinite_grads"])
        bar.update(1)
        if snapshot is not None:
            snapshot(stage)
        if stage.iteration % every == 0 or stage.done():
            checkpoint(stage)
    bar.close()


def save_checkpoint(path: Path, stage: Stage1, fingerprint: str, extra: dict[str, np.ndarray] | None = None) -> None:
    st = stage.checkpoint_state()
    st["fingerprint"] = np.array(fingerprint)
    st["stage"] = np.array(stage.STAGE)
    st.update(extra or {})
    with atomic.atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **st)


def finish_run(out: Path, s1: Stage1, pack: ScenePack, env, history: list[dict[str, Any]], setup_seconds: float,
               spec: RunSpec, warm=None, values: dict[str, np.ndarray] | None = None,
               holdout: dict[str, Any] | None = None, pose=None, start=None, init=None, clear=None,
               plan=None) -> None:
    """Final render, previews, exported asset and summary of an ``ours`` run (its last stage ``s1``); ``values``:
    the result's parameters (default: the last stage's current ones); ``holdout``, ``pose`` and ``start``: the
    held-out views', the turn search's and the start search's records for ``summary.json``."""
    from optimizer.assets.result import Result

    res = Result(pack, env, s1.cams, s1.geometry, s1.current_values() if values is None else values, s1.app,
                 s1.shading_integrator(), s1.cfg.target_spp, s1.targets)
    warm_s = float(warm.seconds) if warm is not None else 0.0
    pose_s = float(pose.seconds) if pose is not None else 0.0
    start_s = float(start.seconds) if start is not None else 0.0
    init_s = float(init.seconds) if init is not None else 0.0
    clear_s = float(clear.seconds) if clear is not None else 0.0
    s1_s, s2_s = stage_seconds(history, 1), stage_seconds(history, 2)
    pre = pose_s + start_s + init_s + clear_s + warm_s
    # wall-clock seconds of the optimisation: Stage 1 = pose search + start search + warm start + its iterations,
    # Stage 2 = its iterations with their pseudo-ground-truth renders and inpainting (``seconds_iterations``: gradient
    # steps only)
    seconds = {"setup": setup_seconds, "warm_start": warm_s, "pose_search": pose_s, "start_search": start_s,
               "init_search": init_s, "clear_search": clear_s,
               "stage1": pre + s1_s, "stage2": s2_s, "optimisation": pre + s1_s + s2_s}
    finish(out, res, history, s1.cfg, s1.initial_render, method=spec.method, seconds=seconds,
           extra={"fingerprint": spec.fingerprint(), "preset": spec.preset, "time_budget": spec.time_budget,
                  "warm_start": warm.to_dict() if warm is not None else None, "holdout": holdout,
                  "pose_search": pose.to_dict() if pose is not None else None,
                  "start_search": start.to_dict() if start is not None else None,
                  "init_search": init.to_dict() if init is not None else None,
                  "clear_search": clear.to_dict() if clear is not None else None,
                  "plan": plan.to_dict() if plan is not None else None})
