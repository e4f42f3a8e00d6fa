"""``camo optimize``: one optimisation run and its run directory.

The run directory (see CONTRIBUTING.md) holds ``config.toml`` (the resolved
config with seed and library versions), ``log.jsonl``, ``checkpoint.npz``
(every ``checkpoint_every`` iterations; ``--resume`` continues from it and
ends with the same numbers as an uninterrupted run), the maps, the exported
asset (``result.glb``, ``result.obj``, ``scene.xml``), ``pose.json``,
per-view preview strips and a loss curve. Every file is written atomically.
"""

from __future__ import annotations

import dataclasses
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import atomic, imaging
from .appearance import AppearanceConfig
from .errors import CamoError
from .scenepack import ScenePack
from .stage1 import Stage1, Stage1Config

CHECKPOINT = "checkpoint.npz"


@dataclasses.dataclass
class RunConfig:
    scene: str
    method: str = "ours"
    stages: tuple[int, ...] = (1,)
    ablate: tuple[str, ...] = ()
    checkpoint_every: int = 10
    planner: bool = True
    shadow_gradients: bool = False
    threads: int | None = None
    stage1: Stage1Config = dataclasses.field(default_factory=Stage1Config)
    appearance: AppearanceConfig = dataclasses.field(default_factory=AppearanceConfig)


def versions() -> dict[str, str]:
    import drjit
    import mitsuba

    from . import __version__, backend

    out = {"camo": __version__, "python": platform.python_version(), "mitsuba": mitsuba.__version__,
           "drjit": drjit.__version__, "numpy": np.__version__}
    try:
        import torch

        out["torch"] = torch.__version__
    except ImportError:
        pass
    info = backend.info()
    if info:
        out["variant"] = info.variant
        out["threads"] = str(info.threads)
    return out


def _plain(obj: Any) -> Any:
    """A TOML-writable copy (no None, tuples as lists)."""
    if dataclasses.is_dataclass(obj):
        obj = dataclasses.asdict(obj)
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def write_config(path: Path, cfg: RunConfig, pack: ScenePack, extra: dict[str, Any]) -> None:
    import tomli_w

    doc = {"run": _plain(cfg), "pack": _plain(pack.to_dict()), **_plain(extra)}
    atomic.write_text(path, tomli_w.dumps(doc))


def config_fingerprint(cfg: RunConfig, pack: ScenePack) -> str:
    import hashlib

    d = _plain(cfg)
    d.pop("checkpoint_every", None)
    d.pop("threads", None)
    d["stage1"].pop("iterations", None)
    blob = json.dumps({"cfg": d, "pack": _plain(pack.to_dict())}, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def appearance_for(ablate: set[str], base: AppearanceConfig | None = None) -> AppearanceConfig:
    app = base or AppearanceConfig()
    return dataclasses.replace(app, pose="pose" not in ablate, displacement="displacement" not in ablate,
                               bsdf="bsdf" not in ablate, transmittance="transmittance" not in ablate)


def _read_log(path: Path, upto: int) -> list[dict[str, Any]]:
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        if line.strip():
            rec = json.loads(line)
            if rec.get("iteration", 0) <= upto and rec.get("stage", 1) == 1:
                out.append(rec)
    return out


def load_checkpoint(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # zipfile/ValueError/OSError on corrupt files
        raise CamoError(f"checkpoint {path} is corrupt or unreadable ({type(exc).__name__}); delete it or start a new run") from None


def prepare_run_dir(out: Path, resume: bool, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise CamoError(f"--out {out} exists and is not a folder")
    if resume:
        if not (out / CHECKPOINT).is_file():
            raise CamoError(f"--resume: no {CHECKPOINT} in {out}")
        return
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise CamoError(f"run directory {out} is not empty; use --resume to continue it, --overwrite to replace it, or another --out")
    out.mkdir(parents=True, exist_ok=True)


def optimize(pack: ScenePack, cfg: RunConfig, out: str | Path, resume: bool = False, overwrite: bool = False,
             progress: bool = True) -> Path:
    """Run Stage 1 (and later stages) for ``pack`` into the run directory ``out``."""
    from . import backend
    from .cameras import cameras
    from .environments import get_environment
    from .placement import prepare_object
    from .planner import full_plan, plan

    out = Path(out)
    prepare_run_dir(out, resume, overwrite)
    backend.init(threads=cfg.threads)
    fingerprint = config_fingerprint(cfg, pack)
    state = None
    if resume:
        state = load_checkpoint(out / CHECKPOINT)
        if str(state.get("fingerprint", "")) != fingerprint:
            raise CamoError(f"--resume: {out} was made with a different configuration; start a new run instead")

    t_setup = time.perf_counter()
    prepared = prepare_object(pack)
    env = get_environment(pack.environment)
    app = cfg.appearance
    params = app.planner_params()
    pl = plan(pack, env, params, "optimize", cfg.shadow_gradients) if cfg.planner else \
        full_plan("optimize", geometry=bool({"pose", "displacement"} & params))
    cams = cameras(pack)
    say = (lambda s: print(s, file=sys.stderr)) if progress else (lambda s: None)
    s1 = Stage1(pack, env, prepared, cams, pl, cfg.stage1, app, say)
    setup_seconds = time.perf_counter() - t_setup
    history: list[dict[str, Any]] = []
    if state is not None:
        s1.load_checkpoint_state(state)
        history = _read_log(out / "log.jsonl", s1.iteration)
        s1.history = list(history)
    write_config(out / "config.toml", cfg, pack, {
        "versions": versions(),
        "plan": {"integrator": pl.integrator, "reasons": [f"{k}: {v}" for k, v in pl.reasons]},
        "fingerprint": {"value": fingerprint},
    })
    atomic.write_text(out / "log.jsonl", "".join(json.dumps(h) + "\n" for h in history))

    from tqdm import tqdm

    bar = tqdm(total=cfg.stage1.iterations, initial=s1.iteration, disable=not progress, desc="stage 1", unit="it")
    with open(out / "log.jsonl", "a", encoding="utf-8") as log:
        while s1.iteration < cfg.stage1.iterations:
            rec = s1.step()
            history.append(rec)
            log.write(json.dumps(rec) + "\n")
            log.flush()
            bar.set_postfix(loss=f"{rec['loss']:.4f}", nonfinite=rec["nonfinite_grads"])
            bar.update(1)
            if s1.iteration % cfg.checkpoint_every == 0 or s1.iteration == cfg.stage1.iterations:
                save_checkpoint(out / CHECKPOINT, s1, fingerprint)
    bar.close()
    finish_run(out, s1, pack, env, history, setup_seconds)
    return out


def save_checkpoint(path: Path, s1: Stage1, fingerprint: str) -> None:
    st = s1.checkpoint_state()
    st["fingerprint"] = np.array(fingerprint)
    with atomic.atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **st)


def finish_run(out: Path, s1: Stage1, pack: ScenePack, env, history: list[dict[str, Any]], setup_seconds: float) -> None:
    """Final render, previews, exported asset and summary of a Stage 1 run."""
    from .loss import make_loss
    from .result import Result, write_result

    res = Result(pack, env, s1.cams, s1.geometry, s1.current_values(), s1.app, s1.shading_integrator(),
                 s1.cfg.target_spp, s1.targets)
    final = write_result(out, res, history, seed=s1.cfg.seed)
    bg = s1.targets.background
    lossfn = make_loss(s1.cfg.loss, s1.cfg.alpha, s1.cfg.eps)
    dom = [None if s1.cfg.domain == "frame" else s1.targets.domain[v] for v in range(len(final))]
    per_view = [lossfn.numpy(final[v], bg[v], dom[v]) for v in range(len(final))]
    initial = [lossfn.numpy(s1.initial_render[v], bg[v], dom[v]) for v in range(len(final))]
    atomic.write_json(out / "summary.json", {
        "scene": pack.name,
        "iterations": s1.iteration,
        "loss": s1.cfg.loss,
        "initial_loss_high_spp": float(np.mean(initial)),
        "final_loss_high_spp": float(np.mean(per_view)),
        "final_loss_per_view": per_view,
        "seconds_setup": setup_seconds,
        "seconds_iterations": float(sum(h["seconds"] for h in history)),
        "nonfinite_grads_total": int(sum(h["nonfinite_grads"] for h in history)),
    })
