"""Held-out views: keep the best iterate, and stop when it stops improving (beyond the paper; the ``fast`` preset).

The paper returns the last iterate of Stage 2. Its objective (Eq. 10-11, Eq. 14) is measured on the training views
only, at a few spp, so nothing in it says whether a step made the object harder or easier to see from *other*
viewpoints -- which is what the evaluation measures (jittered novel views). Two things make the last iterate a poor
choice on our CPU budget (docs/results/convergence.md):

* **Stage 2 can cost novel-view quality.** Its pseudo ground truths are inpainted per training view (offline: the
  patch inpainter) and its steps move the maps towards them; measured with the fast preset, the 4 Stage 2
  iterations cost 0.15 dB crop PSNR on gravel and 0.27 dB on meadow (``make demo``: Ours 31.20 against
  w/o Inpainting 31.47), and gained up to 0.11 dB elsewhere.
* **Runs drift late.** Under a time budget, or on scenes where the training views are matched early, further steps
  fit the training views' Monte Carlo noise.

A :class:`Holdout` is a small set of jittered views of the training rig, drawn like the evaluation's novel views
(jitter ``HOLDOUT_JITTER`` of the rig radius, the evaluation's default) but from a seed stream of their own
(``holdout_cameras`` of :mod:`camo_base.seeds`, never the evaluation's: selecting on the test views would leak).
Every ``every`` iterations of each stage (and at each stage's end) the current parameters are rendered from those
views with the run's path tracer and scored; the run's result is the best-scoring iterate, not the last
(``summary.json`` says which: ``holdout.chosen``). With ``patience`` > 0, Stage 1 also stops once that many checks
in a row found no better iterate.

The score is the squared error, in 8-bit-range sRGB ([0, 1], clipped) like the evaluation's PSNR, between the
render with the object and the render without it, over the held-out views' object+shadow domain (the training loss
domain's rule, :func:`optimizer.optimise.stage1.influence_domain`), *as the evaluation would see it*: the
evaluation renders at 64 spp, a check at ``spp`` (16). A plain 16-spp squared error is the object's squared bias
plus four times the evaluation's noise variance, and it was measured to prefer early, less transmissive iterates for
that noise alone (gravel: it chose iteration 30 at 29.96 dB / 0.240 LPIPS-proxy over iteration 40 at 29.98 /
0.233). So every check renders two independent pairs (with and without the object, stream ``holdout_render``, pairs 0
and 1; a pair shares its seed, so paths that miss the object cancel exactly, common random
numbers) and splits the error (:func:`split_error`): ``d1 d2`` estimates the squared bias without noise and
``(d1 - d2)^2 / 2`` the variance at ``spp``; the score is ``bias^2 + variance * spp / noise_spp`` (``noise_spp``: 64,
the evaluation's default).

Cost (demo sizes, 4 views at 96 px, 16 spp): about 0.25 s per check plus two background renders; every second of it
counts in the stage's seconds (the time budget, snapshots and ``summary.json`` include it). With a measured plan
(its ``region``), a check after the first renders only the domain's pixels (each pair's background fills the rest:
the same seed draws the same paths there, and the score reads only the domain).
"""

from __future__ import annotations

import dataclasses
import json
import time
from typing import Any, Callable

import numpy as np

from camo_base import imaging, seeds

#: The held-out views' jitter as a fraction of the rig radius (divided by 4, :func:`optimizer.scenes.cameras.jitter`):
#: the evaluation's default (``evaluation.views.DEFAULT_JITTER``), so the held-out views are drawn like the test views.
HOLDOUT_JITTER = 0.25


@dataclasses.dataclass
class HoldoutSettings:
    """``[holdout]`` of a run spec. The dataclass defaults are the paper's (off); the ``fast`` preset turns it on."""

    views: int = 0  # held-out jittered views (0: off, the last iterate is the result, as in the paper)
    every: int = 10  # iterations between checks within a stage (each stage's start and end are always checked)
    spp: int = 16  # samples per pixel of the held-out renders (background and with-object alike)
    patience: int = 0  # > 0: Stage 1 stops after this many checks in a row without a better iterate
    noise_spp: int = 64  # the score counts the noise variance of a render at this spp (the evaluation's default)


def holdout_cameras(pack, views: int, seed: int, resolution: tuple[int, int] | None = None) -> list:
    """``views`` jittered cameras of ``pack``'s training rig (evenly spaced over it), from stream ``holdout_cameras``."""
    from optimizer.scenes.cameras import cameras, evenly_spaced, jitter, rig_radius

    training = cameras(pack, resolution)
    n = len(training)
    repeats = max(1, -(-views // n))
    moved = jitter(training, HOLDOUT_JITTER, rig_radius(pack, training), seeds.seed("holdout_cameras", seed),
                   repeats=repeats)
    return [moved[i] for i in (evenly_spaced(n, views) if views <= n else range(views))]


def split_error(img1: np.ndarray, bg1: np.ndarray, img2: np.ndarray, bg2: np.ndarray,
                weight: np.ndarray) -> tuple[float, float]:
    """``(bias2, variance)`` of the sRGB difference ``d = srgb(img) - srgb(bg)`` from two independent pairs
    ``(img1, bg1)``, ``(img2, bg2)`` (each pair rendered with one seed, the pairs with different seeds), weighted
    means over pixels and channels (0, 0 when the weights are all 0): ``bias2 = mean(d1 d2)`` estimates ``E[d]^2`` without the
    noise (it can be slightly negative), ``variance = mean((d1 - d2)^2) / 2`` estimates ``Var d`` at the renders'
    spp; ``E[d1^2] = bias2 + variance``."""
    enc = imaging.linear_to_srgb
    d1 = enc(img1).astype(np.float64) - enc(bg1).astype(np.float64)
    d2 = enc(img2).astype(np.float64) - enc(bg2).astype(np.float64)
    w = np.asarray(weight, np.float64)[..., None]
    total = float(w.sum()) * d1.shape[-1]
    if total <= 0:
        return 0.0, 0.0
    return float((w * d1 * d2).sum() / total), float((w * (d1 - d2) ** 2).sum() / (2.0 * total))


def values_digest(values: dict[str, np.ndarray]) -> str:
    """A digest of parameter arrays (names, dtypes, shapes and bytes): equal digests, equal parameters."""
    import hashlib

    h = hashlib.sha1()
    for k in sorted(values):
        a = np.ascontiguousarray(values[k])
        h.update(f"{k}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def psnr_of(mse: float) -> float:
    """``-10 log10(mse)`` (sRGB in [0, 1]); inf for 0."""
    return float("inf") if mse <= 0 else float(-10.0 * np.log10(mse))


class Holdout:
    """The held-out views of one run and the best iterate seen so far (module doc).

    ``render(values, cams, spp, seed)`` renders parameter ``values`` from ``cams`` -> ``(V, H, W, 3)`` linear
    (:meth:`for_stage` builds it from a stage); ``background(cams, spp, seed)`` renders the scene without the object."""

    def __init__(self, settings: HoldoutSettings, pack, seed: int,
                 render: Callable[[dict[str, np.ndarray], list, int, int], np.ndarray],
                 background: Callable[[list, int, int], np.ndarray],
                 coverage: Callable[[dict[str, np.ndarray], list], np.ndarray],
                 shadow_threshold: float, dilate: float):
        self.settings = settings
        self._render, self._background, self._coverage = render, background, coverage
        self.cams = holdout_cameras(pack, settings.views, seed)
        self.render_seeds = (seeds.seed("holdout_render", seed, pair=0), seeds.seed("holdout_render", seed, pair=1))
        self._threshold, self._dilate = shadow_threshold, dilate
        self.bg: np.ndarray | None = None  # (2, V, H, W, 3): the background of each seed
        self.domain: np.ndarray | None = None
        self.checks: list[dict[str, Any]] = []
        self.best: dict[str, np.ndarray] | None = None
        self.best_check: dict[str, Any] | None = None
        self.since_best = 0  # checks since the best one (patience)
        self.seconds = 0.0
        self._memo: dict[str, tuple[float, float, float]] = {}  # digest of scored values -> score (see score)
        # render(values, cams, spp, seed, masks, fill) restricted to ``masks``: once the domain is known, a check
        # renders only it (the score reads nothing else); set by :meth:`for_stage` for a measured plan
        self.masked_render: Callable | None = None
        # what the renders depend on beside ``values`` (for_stage: the stage's IOR, which the clear-glass search
        # changes): part of the memo's key
        self.context: Callable[[], str] = lambda: ""

    @classmethod
    def for_stage(cls, settings: HoldoutSettings, stage) -> "Holdout":
        """The held-out views of a :class:`~optimizer.optimise.stage1.Stage1` run (its scene, seed, path tracer,
        geometry and loss-domain rule)."""
        from optimizer.rendering import scene as scn
        from optimizer.rendering.appearance import object_mesh
        from optimizer.rendering.render import coverage_and_depth_views, render_shaded

        integrator = stage.shading_integrator()

        def mesh(values):
            return object_mesh(stage.geometry, values, stage.app)

        def render(values, cams, spp, seed):
            return render_shaded(stage.env.build(), mesh(values), cams, integrator, spp, seed)

        def background(cams, spp, seed):
            return render_shaded(stage.env.build(), None, cams, integrator, spp, seed)

        def coverage(values, cams):
            m = mesh(values)
            sc = scn.build_scene(stage.env.build(), m)
            return coverage_and_depth_views(sc, cams, m)[0]

        def masked(values, cams, spp, seed, masks, fill):
            return render_shaded(stage.env.build(), mesh(values), cams, integrator, spp, seed, masks, fill)

        out = cls(settings, stage.pack, stage.cfg.seed, render, background, coverage, stage.cfg.shadow_threshold,
                  stage.cfg.domain_dilate)
        if getattr(stage.plan, "region", False) and integrator.get("type") == "path":
            out.masked_render = masked
        out.context = lambda: f"eta={stage.app.eta!r}"
        return out

    # ------------------------------------------------------------------------------------------------------
    def due(self, iteration: int, done: bool) -> bool:
        """Whether a stage at ``iteration`` (``done``: its last) is checked: its start, every ``every``, its end."""
        return done or iteration == 0 or iteration % max(self.settings.every, 1) == 0

    def score(self, values: dict[str, np.ndarray]) -> tuple[float, float, float]:
        """``(score, bias2, variance)`` of parameter ``values`` on the held-out views (module doc). The first call
        also renders the backgrounds and fixes the object+shadow domain from ``values``. Parameters scored before
        (the same arrays, :func:`values_digest`) are not rendered again: the renders' seeds are fixed, so the
        score would be the same up to the backend's multi-thread float order; the last 8 scores are kept."""
        from optimizer.optimise.stage1 import influence_domain

        key = values_digest(values) + self.context()  # the same maps at another IOR render differently
        if key in self._memo:  # e.g. Stage 1's first check of the start the start search just scored
            return self._memo[key]
        s = self.settings
        if self.bg is not None and self.masked_render is not None:  # only the domain: the score reads nothing else
            img = [self.masked_render(values, self.cams, s.spp, sd, self.domain > 0, self.bg[i])
                   for i, sd in enumerate(self.render_seeds)]
        else:
            img = [self._render(values, self.cams, s.spp, sd) for sd in self.render_seeds]
        if self.bg is None:  # first score: the backgrounds and the object+shadow domain of these views
            self.bg = np.stack([self._background(self.cams, s.spp, sd) for sd in self.render_seeds])
            cov = self._coverage(values, self.cams)
            px = max(1, round(self._dilate * max(self.cams[0].width, self.cams[0].height)))
            self.domain = np.stack([influence_domain(self.bg[0][v], img[0][v], cov[v], self._threshold, px)
                                    for v in range(len(self.cams))])
        bias2, var = split_error(img[0], self.bg[0], img[1], self.bg[1], self.domain)
        result = (max(bias2 + var * s.spp / max(s.noise_spp, 1), 0.0), bias2, var)
        if len(self._memo) >= 8:
            self._memo.pop(next(iter(self._memo)))
        self._memo[key] = result
        return result

    def check(self, values: dict[str, np.ndarray], stage: int, iteration: int, seconds: float) -> dict[str, Any]:
        """Score ``values`` (a stage's current parameters) and keep them if they are the best so far; returns the
        check's record ``{stage, iteration, seconds, mse, psnr, bias2, variance, best, check_seconds}`` (``mse``:
        the score, module doc). ``seconds``: the run's optimisation seconds at this point (for the record only)."""
        t0 = time.perf_counter()
        mse, bias2, var = self.score(values)
        better = self.best_check is None or mse < self.best_check["mse"]
        if better:
            self.best = {k: np.array(v, copy=True) for k, v in values.items()}
            self.since_best = 0
        else:
            self.since_best += 1
        dt = time.perf_counter() - t0
        self.seconds += dt
        rec = {"stage": int(stage), "iteration": int(iteration), "seconds": float(seconds + dt), "mse": mse,
               "psnr": psnr_of(mse), "bias2": bias2, "variance": var, "best": bool(better), "check_seconds": dt}
        if better:
            self.best_check = rec
        self.checks.append(rec)
        return rec

    def patience_spent(self) -> bool:
        """``patience`` > 0 and that many checks in a row found no better iterate."""
        p = self.settings.patience
        return p > 0 and self.since_best >= p

    def summary(self) -> dict[str, Any]:
        """``summary.json``'s ``holdout``: settings, every check, the chosen iterate, the seconds spent."""
        return {**dataclasses.asdict(self.settings), "jitter": HOLDOUT_JITTER, "seconds": self.seconds,
                "chosen": self.best_check, "checks": self.checks}

    # --- checkpoints ------------------------------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """Checkpoint entries (``holdout/...``): the best iterate, the checks, the background and domain renders."""
        if self.bg is None:
            return {}
        st = {"holdout/checks": np.array(json.dumps(self.checks)), "holdout/bg": self.bg, "holdout/domain": self.domain,
              "holdout/since_best": np.array(self.since_best), "holdout/seconds": np.array(self.seconds)}
        for k, v in (self.best or {}).items():
            st[f"holdout/best/{k}"] = v
        return st

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """Restore :meth:`state` (a run resumed from its checkpoint selects what an uninterrupted one would)."""
        from camo_base.errors import CamoError

        if "holdout/checks" not in st:
            return
        try:
            self.checks = json.loads(str(st["holdout/checks"]))
            self.bg, self.domain = np.asarray(st["holdout/bg"]), np.asarray(st["holdout/domain"])
            self.since_best = int(st["holdout/since_best"])
            self.seconds = float(st["holdout/seconds"])
        except (KeyError, ValueError, TypeError):
            raise CamoError("checkpoint is corrupt: bad holdout entries") from None
        best = {k[len("holdout/best/"):]: np.asarray(v) for k, v in st.items() if k.startswith("holdout/best/")}
        self.best = best or None
        chosen = [c for c in self.checks if c.get("best")]
        self.best_check = min(chosen, key=lambda c: c["mse"]) if chosen else None
