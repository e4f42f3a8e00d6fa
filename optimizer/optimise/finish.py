"""The last step of every method (``ours`` and each baseline): the result and ``summary.json``, written one way.

The result is re-rendered at the target spp with the ``final_render`` seed stream and exported
(:func:`optimizer.assets.result.write_result`); ``summary.json`` (:func:`optimizer.assets.rundir.write_summary`)
compares the final render of each view with its background target, and the initial render with it, under the run's
loss inside its domain.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from optimizer.assets.rundir import write_summary
from optimizer.optimise.stage1 import Stage1Config


def finish(out: Path, res, history: list[dict[str, Any]], cfg: Stage1Config, initial_render: np.ndarray, *,
           method: str, seconds: dict[str, float], extra: dict[str, Any] | None = None) -> np.ndarray:
    """Every method's last step: write the result (:func:`optimizer.assets.result.write_result`: final render at the
    target spp with stream ``final_render``, previews, maps, meshes) and ``summary.json`` with the loss of the initial
    and the final render of each view (``cfg``'s loss inside its domain). Returns the final renders."""
    from optimizer.assets.result import final_render_seed, write_result
    from optimizer.optimise.loss import make_loss

    final = write_result(out, res, history, seed=cfg.seed)
    bg = res.targets.background
    lossfn = make_loss(cfg.loss, cfg.alpha, cfg.eps)
    dom = [None if cfg.domain == "frame" else res.targets.domain[v] for v in range(len(final))]
    per_view = [lossfn.numpy(final[v], bg[v], dom[v]) for v in range(len(final))]
    initial = [lossfn.numpy(initial_render[v], bg[v], dom[v]) for v in range(len(final))]
    write_summary(out, scene=res.pack.name, method=method, loss=cfg.loss, initial_per_view=initial,
                  final_per_view=per_view, history=history, seconds=seconds,
                  final_render={"integrator": res.integrator, "spp": res.spp, "seed": final_render_seed(cfg.seed)},
                  extra=extra)
    return final
