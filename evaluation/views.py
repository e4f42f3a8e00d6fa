"""Novel evaluation views of run directories and placed assets, rendered at evaluation quality (paper Sec. IV-B).

Three steps, each usable on its own:

* Inputs are read by their owners: a run directory by :mod:`optimizer.assets.rundir` (:func:`load_run` ->
  :class:`optimizer.assets.rundir.RunDir`: resolved scene pack, appearance config, method, ablation, seconds; its
  result as an :class:`optimizer.assets.asset.Asset`), an external glTF/GLB or OBJ asset by :mod:`optimizer.assets.asset`
  (placed in a scene pack). Both render through :meth:`optimizer.assets.asset.Asset.mesh`.
* :func:`evaluation_cameras` moves each of the pack's training cameras by an independent uniform offset of up
  to ``+-jitter`` units per axis at radius 4 (scaled with the radius; :func:`optimizer.scenes.cameras.jitter`),
  seeded. No evaluation camera equals a training camera (checked, not assumed). The cameras depend only on
  the pack's rig, the resolution, ``jitter`` and ``seed``, so every run of one scene is evaluated on
  identical views.
* :class:`ViewRenderer` renders, per view, the background without the object (cached per scene, camera set,
  spp, resolution, integrator and seed: several runs of one scene render it once), the scene with the object,
  the object's visible mask (coverage >= 0.5, occlusion aware) and the background depth, with the effect
  planner's ``purpose="evaluate"`` path tracer.

Roughness: assets hold the roughness *as rendered*; :meth:`optimizer.assets.asset.Asset.values` inverts the
renderer's affine map once before the BSDF applies it again, so the BSDF renders exactly the saved roughness.

Variance: the background and the with-object render of a view use the same sampler seed (common random
numbers). Paths that never meet the object then give identical radiance in both images, so the metrics see
the object's effect (and its shadow) rather than two independent noise patterns. Only the region the object can
change is rendered with it (the rest is the background's: the same paths). With noise matching
(``ViewRenderer(noise_match=True)``, the default of ``camo evaluate`` and ``camo study build-stimuli``) pixels
where the object's render is noisier than the background's get more samples (:mod:`optimizer.rendering.noise`), so
an object cannot be found by its fireflies.

Images are linear float32 ``(V, H, W, 3)``; masks ``(V, H, W)`` bool; depth ``(V, H, W)`` float32 in scene
units (0 = miss).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from optimizer.assets.asset import Asset
from optimizer.scenes.cameras import Camera
from camo_base import seeds
from camo_base.errors import SettingError
from optimizer.assets.rundir import RunDir, open_run
from optimizer.rendering.noise import groups_for
from evaluation.settings import DEFAULT_JITTER

#: Vertices of the object the evaluation's pilot renders (at the pilot's ~48 pixels).
PILOT_VERTICES = 4000


# --------------------------------------------------------------------------------------------------------------
# run directories and assets (read by optimizer.assets.rundir / optimizer.assets.asset; thin names kept for callers)
# --------------------------------------------------------------------------------------------------------------

def load_run(path: str | Path) -> RunDir:
    """Read a run directory's config (:func:`optimizer.assets.rundir.open_run`); CamoError for anything missing."""
    return open_run(path)


def load_result(run: RunDir) -> Asset:
    """The run's result as evaluation renders it (:meth:`optimizer.assets.rundir.RunDir.asset`)."""
    return run.asset()


def object_mesh_of(run: RunDir | None, asset: Asset):
    """A fresh ``mi.Mesh`` of a result or asset with its BSDF (:meth:`optimizer.assets.asset.Asset.mesh`)."""
    return asset.mesh()


# --------------------------------------------------------------------------------------------------------------
# cameras
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class EvalCameras:
    cams: list[Camera]  # evaluation cameras (jittered)
    base: list[int]  # index of the training camera each one was moved from
    training: list[Camera]  # the pack's training cameras at the evaluation resolution
    amount: float  # jitter at radius 4
    bound: float  # the per-axis bound actually used: amount * radius / 4
    seed: int

    def key(self) -> str:
        """Short hash of the camera set (identical for every run of the same scene and settings)."""
        blob = json.dumps([dataclasses.astuple(c) for c in self.cams]).encode()
        return hashlib.sha256(blob).hexdigest()[:12]


def evaluation_cameras(pack, views: int | None = None, jitter: float = DEFAULT_JITTER, seed: int = 0,
                       resolution: tuple[int, int] | None = None) -> EvalCameras:
    """Jittered novel views of ``pack``'s training cameras.

    ``views`` (default: the number of training cameras) below the training count takes evenly spaced
    cameras of the rig; above it the rig is jittered again (``repeats``), and the first ``views`` are kept.
    Every training camera's jitter is drawn in the same order whatever ``views`` is, so a smaller evaluation
    is a subset of a larger one.
    """
    from optimizer.scenes.cameras import cameras, evenly_spaced, jitter as jitter_cams, rig_radius

    if not (isinstance(jitter, (int, float)) and math.isfinite(jitter)) or jitter <= 0:
        raise SettingError(f"{{0}} must be > 0 (evaluation never uses the training cameras), got {jitter}", "jitter")
    training = cameras(pack, resolution)
    n_train = len(training)
    views = n_train if views is None else views
    if views < 1:
        raise SettingError(f"{{0}} must be >= 1, got {views}", "views")
    radius = rig_radius(pack, training)
    repeats = max(1, math.ceil(views / n_train))
    moved = jitter_cams(training, float(jitter), radius, seeds.seed("evaluation_cameras", int(seed)), repeats=repeats)
    if views <= n_train:
        idx = evenly_spaced(n_train, views)
    else:
        idx = list(range(views))
    cams = [moved[i] for i in idx]
    base = [i % n_train for i in idx]
    train_origins = {c.origin for c in training}
    bad = [i for i, c in enumerate(cams) if c in training or c.origin in train_origins]
    if bad:  # jitter() redraws such offsets; this must never happen
        raise RuntimeError(f"evaluation camera(s) {bad} coincide with a training camera")
    return EvalCameras(cams, base, training, float(jitter), float(jitter) * radius / 4.0, int(seed))


# --------------------------------------------------------------------------------------------------------------
# rendering
# --------------------------------------------------------------------------------------------------------------


def evaluation_plan(pack, env, cams: list[Camera] | None = None, spp: int = 64, seed: int = 0, measured: bool = True,
                    denoise: str = "", noise_match: bool = True, object_spp: bool = True, setting: str = "",
                    sampler: str | None = None):
    """The path tracer every input of a scene is evaluated with, planned for the most demanding material.

    Every method of a scene must be rendered by the same integrator (the background is shared, and a shallower
    path tracer for an opaque result would bias the comparison), so the plan does not depend on the particular
    result: with ``cams`` (the evaluation cameras) and ``measured``, the planner's pilot renders the pack's object
    made fully transmissive (the deepest light transport any result can have: light through it onto the ground,
    light seen through it) from those cameras, and keeps every bounce whose light over the whole frame is above
    0.3 x the noise at ``spp`` (:class:`optimizer.rendering.planner.Planner`, purpose ``evaluate``; stream
    ``evaluation_pilot`` of :mod:`camo_base.seeds`). Without cameras: the rule-based plan (every bounce). With
    ``denoise`` (opt-in, ``--denoise [VARIANT]``: a name of :data:`optimizer.rendering.planner.DENOISERS`, "" off)
    the measured plan denoises with it where the noise at ``spp`` is above its measured bias
    (:data:`optimizer.rendering.planner.DENOISER_BIASES`; ``plan.denoise``); then, with ``object_spp``,
    :func:`object_spp_pilot` measures how many times the spp the object needs to be no noisier than its
    surroundings after the denoiser (``plan.object_spp``; ``noise_match``: as the evaluation renders). ``setting``
    "auto" (``camo evaluate --setting auto``): instead, :func:`evaluation_setting_pilot` chooses the whole setting of
    the render with the object (denoiser ``denoise`` or ``oidn-through``); its figures and choice are in
    ``plan.pilot["setting"]`` (``"chosen"``: :meth:`EvaluationSetting.to_dict`, or None: the plan as without it), and
    ``plan.denoise`` / ``plan.object_spp`` are the chosen ones. ``sampler``: how each pixel's samples are drawn
    (:data:`optimizer.rendering.tracer.SAMPLERS`; default the planner's :data:`~optimizer.rendering.planner.
    EVALUATION_SAMPLER`, ``independent``; ``sobol`` stratifies them and the plan's integrator, measured or
    rule-based, carries it: ``camo evaluate --sampler``)."""
    from optimizer.rendering.planner import Planner, PlannerSettings, plan

    worst = dataclasses.replace(pack, material=dataclasses.replace(pack.material, transmittance=1.0, metallic=0.0))
    if cams is None or not measured:
        out = plan(worst, env, set(), "evaluate")
        if sampler not in (None, "independent"):  # the rule-based plan's path tracer with that sampler too
            PlannerSettings(sampler=sampler)  # refuses an unknown name, as the measured plan does
            if out.integrator.get("type") != "path":
                raise ValueError(f"sampler {sampler!r} needs the path integrator, not {out.integrator.get('type')!r}")
            out.integrator = dict(out.integrator, sampler=sampler)
            out.reasons.append(("sampler", f"{sampler} (--sampler)"))
        return out
    from optimizer.rendering.placement import prepare_object, static_object_fn

    # the pilot renders at ~48 px: a light mesh will do (and it is prepared once, then cached)
    mesh = static_object_fn(worst, prepare_object(worst, target_vertices=min(worst.object.target_vertices,
                                                                             PILOT_VERTICES)))
    planner = Planner(PlannerSettings(denoise=denoise) if sampler is None else
                      PlannerSettings(denoise=denoise, sampler=sampler))
    pilot = planner.pilot(env, mesh, cams, seed=seeds.seed("evaluation_pilot", seed))
    out = planner.plan(worst, env, set(), "evaluate", pilot, {"evaluation": int(spp)})
    if setting:
        if setting != "auto":
            raise SettingError.of("setting", f" {setting!r}: must be auto or absent")
        figs = evaluation_setting_pilot(pack, env, cams, out, spp, seed, denoise or "oidn-through")
        ch = figs.pop("setting")
        out.pilot = {**(out.pilot or {}), "setting": {**figs, "chosen": ch.to_dict() if ch else None}}
        out.denoise, out.object_spp = (ch.denoise, ch.object_spp) if ch else ("", 1)
        out.reasons.append(("evaluation setting", figs["why"]))
        return out
    if out.denoise and object_spp:
        obj = object_spp_pilot(pack, env, cams, out, spp, seed, noise_match)
        out.object_spp = obj["factor"]
        out.pilot = {**(out.pilot or {}), "object_spp": obj}
        out.reasons.append(("object spp", obj["why"]))
    return out


#: The denoised noise on the object's pixels falls as spp^-DENOISED_NOISE_EXPONENT (measured with
#: ``bench/bench_noise.py --denoise oidn-through --object-spp 2,4,8``, after noise matching, on the four built-in scenes
#: whose ratio is above 1: 0.26-0.46, median 0.31; slower than a raw render's 0.5: the denoiser removes more of the
#: noise of fewer samples).
DENOISED_NOISE_EXPONENT = 0.3
#: The largest object spp factor the pilot chooses (on top of noise matching's, itself up to 8x).
OBJECT_SPP_MAX = 8
#: Evaluation cameras the object-spp pilot renders (evenly spaced), at the evaluation's resolution and spp.
OBJECT_PILOT_VIEWS = 2


def denoised_noise_ratio(pack, env, mesh_fn, cams: list[Camera], plan, spp: int, seed: int, object_spp: int = 1,
                         noise_match: bool = True, renderers: list | None = None) -> tuple[float, float, float]:
    """``(object noise, background noise, ratio)`` (sRGB /255) of the evaluation renders as ``plan`` makes them
    (region, noise matching, the plan's denoiser on both, the object's ``object_spp`` factor): RMS difference of two
    independent renders (stream ``denoise_pilot``, pairs 0 and 1) over sqrt 2, on the object and a 2-pixel rim, the
    background's over the same pixels (:func:`optimizer.rendering.noise.noise_rms`). ``renderers``: two
    :class:`ViewRenderer` of those streams, reused across calls (their backgrounds are cached)."""
    from optimizer.rendering.noise import noise_rms
    from optimizer.rendering.region import dilate_px

    rs = renderers or [ViewRenderer(spp, seed, noise_match=noise_match,
                                    sampler_seed=seeds.seed("denoise_pilot", seed, pair=p)) for p in (0, 1)]
    thr = plan.region_threshold if plan.region_search else None
    out = []
    for r in rs:
        bg = r.background(pack, env, cams, plan.integrator, plan.denoise)
        out.append((bg.image, r.with_object(env, mesh_fn, cams, plan.integrator, bg, thr, object_spp=object_spp)))
    (b0, o0), (b1, o1) = out
    near = np.stack([dilate_px(m, 2) for m in o0.mask])
    on, bn = noise_rms(o0.image, o1.image, near), noise_rms(b0, b1, near)
    return on, bn, on / max(bn, 1e-9)


def object_spp_pilot(pack, env, cams: list[Camera], plan, spp: int, seed: int = 0, noise_match: bool = True,
                     mesh_fn=None, views: int = OBJECT_PILOT_VIEWS) -> dict[str, Any]:
    """How many times the spp the object and its rim need so that, after ``plan.denoise``, they are no noisier
    than the denoised background in the same pixels (issue 28 item 4), measured.

    A denoiser smooths the background's noise more than a see-through object's (its features there are themselves
    noisy and its colour has the rarer, brighter paths): at equal spp the denoised object and rim were 1.1-1.6x
    noisier than the denoised background (docs/results/planner.md). Noise matching equalises the noise *before*
    the denoiser; this pilot measures it *after*: it renders ``views`` of the evaluation cameras as the evaluation
    will (the pack's object at its starting material, ``mesh_fn`` to choose another), twice, and measures the
    ratio ``r`` (:func:`denoised_noise_ratio`). ``r <= 1``: factor 1. Otherwise the factor is the power of two at
    or above ``r ** (1 / DENOISED_NOISE_EXPONENT) / 1.1`` (noise matching's tolerance; at least 2, at most
    :data:`OBJECT_SPP_MAX`), verified by a second
    measurement at that factor; if the ratio is still above 1 the factor is doubled once more (unverified).
    Returns the factor, the ratios, the noises, the seconds and a one-line ``why``."""
    import math

    from optimizer.rendering.noise import TOLERANCE

    from optimizer.rendering.placement import prepare_object, static_object_fn
    from optimizer.scenes.cameras import evenly_spaced

    t = time.perf_counter()
    sub = [cams[i] for i in evenly_spaced(len(cams), min(int(views), len(cams)))]
    if mesh_fn is None:
        mesh_fn = static_object_fn(pack, prepare_object(pack, target_vertices=pack.object.target_vertices))
    rs = [ViewRenderer(spp, seed, noise_match=noise_match, sampler_seed=seeds.seed("denoise_pilot", seed, pair=p))
          for p in (0, 1)]
    o1, b1, r1 = denoised_noise_ratio(pack, env, mesh_fn, sub, plan, spp, seed, 1, noise_match, rs)
    factor, rk, ok = 1, r1, o1
    if r1 > 1.0:
        need = r1 ** (1.0 / DENOISED_NOISE_EXPONENT) / TOLERANCE  # within noise matching's tolerance: verified
        factor = min(OBJECT_SPP_MAX, 2 ** max(1, math.ceil(math.log2(max(need, 1.0)))))
        ok, _, rk = denoised_noise_ratio(pack, env, mesh_fn, sub, plan, spp, seed, factor, noise_match, rs)
    verified = factor
    if rk > 1.0 and factor < OBJECT_SPP_MAX:
        factor *= 2
    secs = time.perf_counter() - t
    why = (f"the denoised object and rim are {r1:.2f}x as noisy as the denoised background at {spp} spp "
           f"({o1:.2f} vs {b1:.2f}/255, {len(sub)} views, the pack's object)"
           + (f"; x{verified} spp on the object and a {OBJECT_MARGIN}-pixel rim: {rk:.2f}x"
              + (f", not <= 1, so x{factor} (unverified)" if factor != verified else "") if r1 > 1.0 else
              ": no extra samples")
           + f" (pilot {secs:.1f} s)")
    return {"factor": int(factor), "ratio": float(r1), "ratio_at_factor": float(rk), "verified_factor": int(verified),
            "object_noise": float(o1), "object_noise_at_factor": float(ok), "background_noise": float(b1),
            "views": len(sub), "spp": int(spp), "seconds": float(secs), "why": why}


# --------------------------------------------------------------------------------------------------------------
# the evaluation setting chosen per scene from a pilot (denoiser factor, combine rule, feature spp, spp level)
# --------------------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class EvaluationSetting:
    """How the with-object evaluation render is made (:meth:`ViewRenderer.with_object`): rendered at ``spp`` spp
    with noise matching, denoised by ``denoise`` ("" none), the object and its rim at ``object_spp`` x the spp
    combined with noise matching's factor by ``combine`` (:data:`optimizer.rendering.noise.COMBINE`), the
    with-object render's denoiser features at ``feature_spp`` on the object's box (None: the background's), the
    background's features at ``background_feature_spp`` (None: min(spp, :data:`FEATURE_SPP`); the background is
    rendered once per scene and shared by every input)."""

    denoise: str
    object_spp: int
    combine: str
    feature_spp: int | None
    spp: int
    background_feature_spp: int | None = None

    @property
    def label(self) -> str:
        """As ``bench/bench_planner.py --evaluate-as`` spells it, e.g. ``oidn-through:16:max:f16@4``."""
        return (f"{self.denoise or 'off'}:{self.object_spp}" + (":max" if self.combine == "max" else "")
                + (f":f{self.feature_spp}" if self.feature_spp else "")
                + (f":b{self.background_feature_spp}" if self.background_feature_spp else "") + f"@{self.spp}")

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "label": self.label}


#: The candidates of the setting pilot: per spp level (its spp at an evaluation spp of 64, scaled with the
#: evaluation's spp; the cheapest level first), the with-object variants ``(object_spp, combine, feature_spp,
#: background_feature_spp)`` measured there. At a quarter of the features' spp the denoised frame is above full
#: tracing's 64-spp error on four of six scenes (docs/results/planner.md), so at 4 spp the background's features get 8
#: or 16 spp (the frame's error falls by a quarter at 16: 2.61 -> 1.95/255 on room), which makes the background
#: smoother and so asks more of the object's samples (32x with its features at 32 spp). Without them 16x on the object
#: left it 0.55-0.92 as noisy as the background on five of six scenes (pilot figures, 2 views), so 8x is tried first.
#: 6 spp (groups of one sample for noise matching, :func:`optimizer.rendering.noise.groups_for`) lies between 4 and 8,
#: where meadow's error is reached only at 8 spp without the background's extra features.
SETTING_CANDIDATES = (
    (4, ((8, "max", 16, None), (16, "max", 16, None), (16, "max", 16, 8), (16, "max", 16, 16), (32, "max", 32, 16),
         (8, "product", None, 16))),
    (6, ((8, "max", 16, None), (16, "max", 16, None))),
    (8, ((8, "max", 16, None), (16, "max", 16, None), (8, "product", None, None))),
)
#: The candidates of the setting pilot before the 6-spp level and the cost model (levels 4 and 8 only): kept to
#: measure the choice against (``bench/bench_planner.py --evaluate-as auto:oidn-through:coarse``).
SETTING_CANDIDATES_COARSE = (
    (4, ((8, "max", 16, 16), (16, "max", 16, 16), (32, "max", 32, 16), (8, "product", None, 16),
         (16, "max", 16, None))),
    (8, ((8, "max", 16, None), (16, "max", 16, None), (8, "product", None, None))),
)
#: Named candidate sets (``evaluation_setting_pilot(candidates=NAME)``).
SETTING_CANDIDATE_SETS = {"default": SETTING_CANDIDATES, "coarse": SETTING_CANDIDATES_COARSE}
#: Evaluation cameras the setting pilot renders (evenly spaced).
SETTING_PILOT_VIEWS = 2
#: The largest noise ratio (denoised object and rim / denoised background, :func:`denoised_noise_ratio`'s measure)
#: a chosen setting may show in the pilot.
SETTING_RATIO_MAX = 1.0


def _srgb_mse(a: np.ndarray, b: np.ndarray) -> float:
    from camo_base.imaging import linear_to_srgb

    d = linear_to_srgb(np.clip(a, 0, None)).astype(np.float64) - linear_to_srgb(np.clip(b, 0, None))
    return float(np.mean(d ** 2))


def choose_setting(candidates: list[dict], target_error: float, ratio_max: float = SETTING_RATIO_MAX) -> dict | None:
    """The candidate (a dict with ``seconds``, ``error``, ``ratio``; sRGB /1 errors) the evaluation uses: of those
    whose noise ratio is at most ``ratio_max`` and whose error is at most ``target_error``, the one with the least
    seconds (ties: the lower error). None when no candidate meets both."""
    ok = [c for c in candidates if c["ratio"] <= ratio_max and c["error"] <= target_error]
    return min(ok, key=lambda c: (c["seconds"], c["error"])) if ok else None


#: Repetitions of each timing of the setting pilot's cost model (the least CPU seconds is kept: load only adds).
COST_REPS = 3


def setting_cost_model(env, mesh, cams: list[Camera], integrator: dict, spp: int, seed: int, denoise: str,
                       feature_spps, without: tuple | None, reps: int = COST_REPS) -> dict[str, Any]:
    """The CPU costs a with-object evaluation render at ``spp`` is made of, each timed ``reps`` times interleaved (the
    least kept: a machine's load only adds to a CPU time; measured under load 6-10, one with-object render's CPU
    seconds varied 1.6-2.7 s between repetitions) on ``cams``: ``frame``, CPU seconds per path sample of a
    full-frame render with the object (``integrator``); ``object``, per path sample of further samples on the object
    and its rim (:func:`object_pixels`: where the extra samples go); ``features``, seconds of the denoiser's features
    at each of ``feature_spps`` (keyed by the spp as a string: the model is written to TOML; ``without``: the
    background's, as the evaluation traces only the object's box);
    ``fixed``, seconds of the scene build, the coverage pass and the denoiser itself (the same for every
    candidate)."""
    from optimizer.rendering.denoise import denoise_variant, variant_features
    from optimizer.rendering.render import PathRenderer, object_coverage_views

    n = sum(c.width * c.height for c in cams)
    times: dict[str, list[float]] = {}

    def timed(name, fn):
        t = time.process_time()
        out = fn()
        times.setdefault(name, []).append(time.process_time() - t)
        return out

    obj_n = 0
    for _ in range(max(1, int(reps))):
        pr = timed("build", lambda: PathRenderer(env.build(), mesh, cams, integrator, spp, seed))
        cov = timed("coverage", lambda: object_coverage_views(pr.scene, cams, mesh, 4))
        img = timed("frame", lambda: pr())
        counts = object_pixels(cov).astype(np.int64)
        obj_n = int(counts.sum())
        timed("object", lambda: pr(None, None, spp, spp, counts=counts))
        feats = None
        for f in feature_spps:
            feats = timed(f"features{f}", lambda: variant_features(denoise, env.build(), mesh, cams, int(f), seed,
                                                                   scene=pr.scene, without=without))
        if denoise and feats is not None:
            timed("denoise", lambda: denoise_variant(img, feats[0], feats[1], denoise))
    best = {k: min(v) for k, v in times.items()}
    return {"frame": best["frame"] / (n * spp), "object": best["object"] / max(obj_n * spp, 1),
            "features": {str(int(f)): best[f"features{f}"] for f in feature_spps},
            "fixed": best["build"] + best["coverage"] + best.get("denoise", 0.0), "pixels": n,
            "object_pixels": obj_n, "spp": int(spp), "reps": int(reps)}


def modelled_seconds(model: dict, spp: int, rendered_pixels: int, extra_share: float, feature_spp: int) -> float:
    """CPU seconds of a with-object render by :func:`setting_cost_model`'s ``model``: ``rendered_pixels`` traced at
    ``spp`` (the frame's per-sample cost), ``extra_share`` x one full frame at ``spp`` further samples (noise matching's
    and the object's factor; the object's per-sample cost), the features at ``feature_spp``, and the fixed costs."""
    n = model["pixels"]
    return (model["frame"] * rendered_pixels * spp + model["object"] * extra_share * n * spp
            + model["features"][str(int(feature_spp))] + model["fixed"])


def level_may_be_cheaper(model: dict, pixels: int, spp: int, best_seconds: float) -> bool:
    """Whether a with-object render at ``spp`` can cost less than ``best_seconds`` by ``model`` (the cost model of a
    cheaper level, :func:`setting_cost_model`): its least possible cost is every one of ``pixels`` traced once at
    ``spp`` at the model's per-sample rate, plus the fixed costs (no further samples, no features)."""
    return model["frame"] * int(pixels) * int(spp) + model["fixed"] < float(best_seconds)


def evaluation_setting_pilot(pack, env, cams: list[Camera], plan, spp: int, seed: int = 0, denoise: str = "oidn-through",
                             mesh_fn=None, views: int = SETTING_PILOT_VIEWS,
                             candidates=SETTING_CANDIDATES, cost: str = "model") -> dict[str, Any]:
    """The evaluation setting of this scene, chosen from measurements (no per-scene table): the cheapest render that
    is as accurate as full path tracing at ``spp`` and leaves the object no noisier than the background.

    On ``views`` evenly spaced evaluation cameras and the pack's object at its starting material (``mesh_fn`` to
    choose another), it renders:

    * **the target**: full path tracing (:func:`optimizer.rendering.planner.full_plan`, depth 12, Russian roulette
      from 5) at ``spp``, two independent seeds (stream ``denoise_pilot``, pairs 2 and 3). Full tracing is unbiased,
      so its error at ``spp`` is its noise: ``target = |a - b| / sqrt 2`` (sRGB RMS over the frames), and the pair's
      mean ``(a + b) / 2`` is the reference the candidates are measured against;
    * **each candidate** (:class:`EvaluationSetting`: ``denoise`` with each variant of ``candidates`` -- or the name
      of a set of :data:`SETTING_CANDIDATE_SETS` -- at its level, the level's spp at 64 scaled by ``spp / 64``,
      :data:`SETTING_CANDIDATES`) exactly as the evaluation renders it (:meth:`ViewRenderer.with_object`, ``plan``'s
      integrator, noise matching), two seeds (pairs 0 and 1, with their denoised backgrounds): its error
      ``sqrt(mean |c_i - ref|^2 - target^2 / 2)`` (the reference's own noise subtracted), its noise ratio
      (:func:`denoised_noise_ratio`'s measure: the object and a 2-pixel rim against the background) and its cost in
      CPU seconds (the background, shared by every input of a scene, not counted): with ``cost="model"`` the
      samples it traced (rendered pixels, noise matching's and the object's further samples, the two seeds' mean)
      priced by :func:`setting_cost_model` of its level (each part timed 3 times interleaved, the least kept), so
      that a busy machine does not reorder the candidates; ``cost="measured"``: the faster seed's CPU seconds.

    The choice (:func:`choose_setting`): of the candidates with noise ratio <= :data:`SETTING_RATIO_MAX` and error
    <= the target, the least seconds. Levels are measured cheapest first; with the cost model a later level is
    measured only while its least possible cost (its full frame and the fixed costs, priced at the last level's
    rates) is below the best qualifying candidate's (``cost="measured"``: only when no candidate of the cheaper levels
    qualified). None qualifies: ``setting`` None (the evaluation keeps its default: noise matching at ``spp``, no
    denoiser). Returns ``{"setting": EvaluationSetting | None, "candidates": [...], "target_error", "full_seconds",
    "cost_models", "seconds", "why"}`` (errors sRGB /1; seconds CPU, ``seconds`` of the pilot wall)."""
    from optimizer.rendering.noise import noise_rms
    from optimizer.rendering.placement import prepare_object, static_object_fn
    from optimizer.rendering.planner import full_plan
    from optimizer.rendering.region import dilate_px
    from optimizer.rendering.render import render_shaded
    from optimizer.scenes.cameras import evenly_spaced

    if isinstance(candidates, str):
        if candidates not in SETTING_CANDIDATE_SETS:
            raise SettingError.of("candidates", f" {candidates!r}: must be one of {', '.join(SETTING_CANDIDATE_SETS)}")
        candidates = SETTING_CANDIDATE_SETS[candidates]
    if cost not in ("model", "measured"):
        raise ValueError(f"cost must be model or measured, got {cost!r}")
    t_all = time.perf_counter()
    sub = [cams[i] for i in evenly_spaced(len(cams), min(int(views), len(cams)))]
    n_px = sum(c.width * c.height for c in sub)
    if mesh_fn is None:
        mesh_fn = static_object_fn(pack, prepare_object(pack, target_vertices=pack.object.target_vertices))
    mesh = mesh_fn()
    full = dict(full_plan("evaluate").integrator, rr_depth=5)
    t = time.process_time()
    refs = [render_shaded(env.build(), mesh, sub, full, int(spp), seeds.seed("denoise_pilot", seed, pair=p))
            for p in (2, 3)]
    full_seconds = (time.process_time() - t) / 2
    target_var = _srgb_mse(refs[0], refs[1]) / 2.0
    tgt = math.sqrt(target_var)
    ref = (refs[0] + refs[1]) / 2.0
    thr = plan.region_threshold if plan.region_search else None
    cands: list[dict] = []
    models: dict[int, dict] = {}
    best = None
    model = None
    for level, variants in candidates:
        lv = max(1, int(round(int(level) * int(spp) / 64)))
        if best is not None and (cost == "measured" or model is None
                                 or not level_may_be_cheaper(model, n_px, lv, best["seconds"])):
            break  # no candidate of this level can be cheaper than the one found
        renderers: dict = {}  # per background feature spp: the two seeds' renderers and backgrounds
        level_cands = []
        for k, combine, fspp, bfspp in variants:
            if bfspp not in renderers:
                rs = [ViewRenderer(lv, seed, noise_match=True, sampler_seed=seeds.seed("denoise_pilot", seed, pair=p),
                                   feature_spp=bfspp) for p in (0, 1)]
                renderers[bfspp] = rs, [r.background(pack, env, sub, plan.integrator, denoise) for r in rs]
            rs, bgs = renderers[bfspp]
            if cost == "model" and lv not in models:
                fs = sorted({int(f or b or min(lv, FEATURE_SPP)) for _, _, f, b in variants} if denoise else set())
                models[lv] = model = setting_cost_model(env, mesh, sub, plan.integrator, lv,
                                                        seeds.seed("denoise_pilot", seed, pair=4), denoise, fs,
                                                        bgs[0].features)
            s = EvaluationSetting(denoise, int(k), combine, fspp, lv, bfspp)
            imgs, secs, modelled = [], [], []
            for r, bg in zip(rs, bgs):
                t = time.process_time()
                o = r.with_object(env, lambda: mesh, sub, plan.integrator, bg, thr, object_spp=s.object_spp,
                                  object_combine=s.combine, object_feature_spp=s.feature_spp)
                secs.append(time.process_time() - t)
                imgs.append(o)
                if cost == "model":
                    rendered = int(o.region.sum()) if o.region is not None else n_px
                    extra = o.noise.extra_samples if o.noise is not None else 0.0
                    modelled.append(modelled_seconds(model, lv, rendered, extra,
                                                     fspp or bfspp or min(lv, FEATURE_SPP)) if denoise else
                                    model["frame"] * rendered * lv + model["object"] * extra * n_px * lv
                                    + model["fixed"])
            near = np.stack([dilate_px(m, 2) for m in imgs[0].mask])
            on = noise_rms(imgs[0].image, imgs[1].image, near)
            bn = noise_rms(bgs[0].image, bgs[1].image, near)
            err2 = float(np.mean([_srgb_mse(o.image, ref) for o in imgs])) - target_var / 2.0
            c = {"setting": s.to_dict(), "seconds": float(np.mean(modelled)) if cost == "model" else float(min(secs)),
                 "measured_seconds": float(min(secs)), "error": math.sqrt(max(err2, 0.0)),
                 "ratio": on / max(bn, 1e-9), "object_noise": on, "background_noise": bn,
                 "extra_samples": float(np.mean([o.noise.extra_samples if o.noise is not None else 0.0
                                                 for o in imgs]))}
            cands.append(c)
            level_cands.append(c)
        lb = choose_setting(level_cands, tgt)
        if lb is not None and (best is None or lb["seconds"] < best["seconds"]):
            best = lb
    chosen = EvaluationSetting(**{k: v for k, v in best["setting"].items() if k != "label"}) if best else None
    secs_all = time.perf_counter() - t_all
    figs = "; ".join(f"{c['setting']['label']} {c['seconds']:.2f} s, error {c['error'] * 255:.2f}, "
                     f"noise ratio {c['ratio']:.2f}" for c in cands)
    how = "modelled" if cost == "model" else "measured"
    why = ((f"{chosen.label}: the least {how} CPU seconds of the candidates with error <= full tracing's at {spp} spp "
            f"({tgt * 255:.2f}/255, {full_seconds:.2f} s) and noise ratio <= {SETTING_RATIO_MAX:g}" if chosen else
            f"no candidate reached full tracing's error at {spp} spp ({tgt * 255:.2f}/255) with noise ratio <= "
            f"{SETTING_RATIO_MAX:g}: the default (noise matching at {spp} spp, no denoiser)")
           + f" ({len(sub)} views; {figs}; pilot {secs_all:.1f} s)")
    return {"setting": chosen, "candidates": cands, "target_error": tgt, "full_seconds": full_seconds,
            "cost": cost, "cost_models": {str(k): v for k, v in models.items()},
            "views": len(sub), "spp": int(spp), "seconds": secs_all, "why": why}


#: Pixels around the object's silhouette that get its spp factor (:func:`object_pixels`): the denoiser's
#: footprint spreads the object's noise over a few pixels beyond its silhouette.
OBJECT_MARGIN = 3


def object_pixels(coverage: np.ndarray, region: np.ndarray | None = None, margin: int = OBJECT_MARGIN) -> np.ndarray:
    """``(V, H, W)`` bool: the pixels the object covers at all (coverage > 0) and a ``margin``-pixel rim, within
    ``region`` (the pixels rendered with the object) when given. Decided by geometry alone, never by a pixel's
    samples, so extra samples there keep the render unbiased."""
    from optimizer.rendering.region import dilate_px

    px = np.stack([dilate_px(c > 0, int(margin)) for c in np.asarray(coverage)])
    return px & region if region is not None else px


#: The denoiser's features (albedo, normal: first-hit or see-through, as its variant says) are rendered at
#: min(spp, FEATURE_SPP) (bench/bench_planner.py ``--aux-spp``, the setting measured).
FEATURE_SPP = 16


def render_seed(seed: int) -> int:
    """Sampler seed of every evaluation render for evaluation seed ``seed`` (same for all runs and for
    the background and with-object images: common random numbers)."""
    return seeds.seed("evaluation_render", int(seed))


@dataclasses.dataclass
class Background:
    image: np.ndarray  # (V, H, W, 3) linear
    depth: np.ndarray  # (V, H, W)
    seconds: float
    key: str
    groups: np.ndarray | None = None  # (G, V, H, W, 3) means of groups of its samples (noise matching), or None
    raw: np.ndarray | None = None  # (V, H, W, 3) linear, before the denoiser (None: not denoised; ``image`` is raw)
    denoise: str = ""  # the denoiser applied to ``image`` (optimizer.rendering.denoise.VARIANTS), or ""
    denoise_seconds: float = 0.0  # of ``seconds``: the features' render and the denoising
    features: tuple | None = None  # (albedo, normal) (V, H, W, 3) the denoiser's features, or None

    @property
    def fill(self) -> np.ndarray:
        """The render the region renders take their other pixels from: the background before any denoiser."""
        return self.image if self.raw is None else self.raw


@dataclasses.dataclass
class ObjectRenders:
    image: np.ndarray  # (V, H, W, 3) linear
    coverage: np.ndarray  # (V, H, W) float32
    mask: np.ndarray  # (V, H, W) bool (coverage >= 0.5)
    seconds: float
    region: np.ndarray | None = None  # (V, H, W) bool: the pixels rendered (the rest is the background's), or None
    region_seconds: float = 0.0  # of ``seconds``: finding the region
    noise: Any = None  # optimizer.rendering.noise.NoiseMatch when the noise was matched
    denoise: str = ""  # the denoiser applied to ``image``, or ""
    denoise_seconds: float = 0.0  # of ``seconds``: the features' render and the denoising


class ViewRenderer:
    """Evaluation renders with a background cache (one entry per scene, camera set, spp, integrator, seed)."""

    def __init__(self, spp: int, seed: int = 0, ss: int = 4, noise_match: bool = False,
                 sampler_seed: int | None = None, feature_spp: int | None = None):
        """``noise_match``: renders with an object get more samples where they are noisier than the background
        (:mod:`optimizer.rendering.noise`; needs a ``path`` integrator and the background of the same seed).
        ``sampler_seed``: the renders' sampler seed (default :func:`render_seed` of ``seed``; the pilot of
        :func:`object_spp_pilot` uses its own stream). ``feature_spp``: the spp of the denoiser's features of the
        background and (unless ``with_object`` is given its own) of the renders with the object (default
        min(spp, :data:`FEATURE_SPP`))."""
        self.spp, self.seed, self.ss, self.noise_match = int(spp), int(seed), int(ss), bool(noise_match)
        self.sampler_seed = render_seed(self.seed) if sampler_seed is None else int(sampler_seed)
        if feature_spp is not None and int(feature_spp) < 1:
            raise ValueError(f"feature_spp must be >= 1, got {feature_spp}")
        self.feature_spp = min(self.spp, FEATURE_SPP) if feature_spp is None else int(feature_spp)
        self.cache: dict[str, Background] = {}
        self.background_renders = 0  # how many times a background was actually rendered
        self.region_cache: dict[str, dict] = {}  # per background: the region pass' renders without the object

    def _key(self, pack, cams: list[Camera], integrator: dict, denoise: str = "") -> str:
        blob = json.dumps({"env": dataclasses.asdict(pack.environment), "cams": [dataclasses.astuple(c) for c in cams],
                           "spp": self.spp, "integrator": integrator, "seed": self.seed,
                           **({"sampler_seed": self.sampler_seed} if self.sampler_seed != render_seed(self.seed)
                              else {}),
                           **({"denoise": denoise} if denoise else {}),
                           **({"feature_spp": self.feature_spp} if denoise and self.feature_spp != min(
                               self.spp, FEATURE_SPP) else {})}, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def _denoised(self, env, obj, cams: list[Camera], img: np.ndarray, denoise: str, scene=None,
                  without: tuple | None = None, feature_spp: int | None = None) -> tuple[np.ndarray, float, tuple]:
        """``img`` denoised by ``denoise`` with the features of the same scene, cameras and seed
        (:mod:`optimizer.rendering.denoise`: the variant's albedo and normal, first-hit or see-through, at up to
        :data:`FEATURE_SPP` spp); with the seconds it took and the features. ``scene``: the scene already built;
        ``without``: the background's features (see-through features are then traced only where a ray meets the
        object's box, :func:`optimizer.rendering.denoise.see_through_features`); ``feature_spp``: the features' spp
        (default the renderer's ``feature_spp``)."""
        from optimizer.rendering.denoise import denoise_variant, variant_features

        t = time.perf_counter()
        fspp = self.feature_spp if feature_spp is None else int(feature_spp)
        albedo, normal = variant_features(denoise, env.build(), obj, cams, fspp,
                                          self.sampler_seed, scene=scene, without=without)
        return denoise_variant(img, albedo, normal, denoise), time.perf_counter() - t, (albedo, normal)

    def background(self, pack, env, cams: list[Camera], integrator: dict, denoise: str = "") -> Background:
        """The scene without the object; ``denoise``: the denoiser of the evaluation plan (``plan.denoise``), or ""."""
        from optimizer.rendering import scene as scn
        from optimizer.rendering.render import coverage_and_depth_views, render_shaded

        key = self._key(pack, cams, integrator, denoise)
        if key not in self.cache:
            t = time.perf_counter()
            groups = None
            if self.noise_match and integrator.get("type") == "path" and groups_for(self.spp):
                from optimizer.rendering.render import PathRenderer

                img, groups = PathRenderer(env.build(), None, cams, integrator, self.spp,
                                           self.sampler_seed)(groups=groups_for(self.spp))
            else:
                img = render_shaded(env.build(), None, cams, integrator, self.spp, self.sampler_seed)
            raw, d_s, feats = None, 0.0, None
            if denoise:
                raw = img
                img, d_s, feats = self._denoised(env, None, cams, raw, denoise)
            depth = coverage_and_depth_views(scn.build_scene(env.build()), cams, None, self.ss)[1]
            self.cache[key] = Background(img, depth, time.perf_counter() - t, key, groups, raw, denoise, d_s, feats)
            self.background_renders += 1
        return self.cache[key]

    def with_object(self, env, mesh_fn, cams: list[Camera], integrator: dict,
                    background: Background | None = None, region_threshold: float | None = None,
                    denoise: str | None = None, object_spp: int = 1,
                    region_min_spp: int | None = None, object_combine: str = "product",
                    object_feature_spp: int | None = None) -> ObjectRenders:
        """The scene with the object ``mesh_fn()``. ``background``: the same cameras, spp, integrator and seed. With
        ``region_threshold`` (sRGB) and at least ``region_min_spp`` spp (default
        :data:`optimizer.rendering.planner.REGION_MIN_SPP`: below it whole frames are cheaper) only the region the
        object can change is rendered
        (:func:`optimizer.rendering.region.render_region`); every other pixel is the background's, which the same
        random numbers drew there (``tests/test_region.py``). With noise matching, pixels where the render is
        noisier than the background get more samples (:mod:`optimizer.rendering.noise`). ``denoise`` (default: the
        background's): the denoiser applied to the render (after noise matching), exactly as to the background (same
        features' spp and seed). Noise matching stays on beside it: alone, the denoiser leaves a transmissive
        object's fireflies (fewer, but more visible against a background it smooths: ``bench/bench_noise.py
        --denoise``). ``object_spp`` > 1 (the plan's ``object_spp``, :func:`object_spp_pilot`): the object and a
        :data:`OBJECT_MARGIN`-pixel rim get that many times the samples (on top of noise matching's factor; the
        further samples of the same streams, merged as one render at that spp), so that after the denoiser the
        object is no noisier than its denoised surroundings. ``object_combine`` (:data:`optimizer.rendering.noise.
        COMBINE`): ``product`` multiplies noise matching's factor by ``object_spp`` on those pixels, ``max`` takes the
        larger of the two. ``region_min_spp=0`` renders only the region at any spp: at a low spp (2-4) with a large
        ``object_spp`` the object's samples are the render's cost, so the frame need not be traced again
        (``bench/bench_planner.py --evaluate-as DENOISER:K:region``). ``object_feature_spp``: the denoiser's
        features of this render at that spp (default the background's, min(spp, :data:`FEATURE_SPP`)); with the
        see-through features only the pixels whose rays can meet the object's box are traced (the rest are the
        background's), so this gives the object's features the samples its colour has got: at 4 spp with the object
        at 8x, its denoised noise near the object fell from 0.96 to 0.79 of the background's on split."""
        from optimizer.rendering import scene as scn
        from optimizer.rendering.render import PathRenderer, object_coverage_views, render_shaded, render_with_region
        from optimizer.rendering.planner import REGION_MIN_SPP

        t = time.perf_counter()
        mesh = mesh_fn()
        seed = self.sampler_seed
        path = integrator.get("type") == "path"
        # one scene for every pass of a path render (coverage, region, further samples): a build costs 20-50 ms
        pr = PathRenderer(env.build(), mesh, cams, integrator, self.spp, seed) if path else None
        sc = pr.scene if pr is not None else scn.build_scene(env.build(), mesh)
        cov = object_coverage_views(sc, cams, mesh, self.ss)
        if denoise is None:
            denoise = background.denoise if background is not None else ""
        if background is not None and denoise != background.denoise:
            raise ValueError(f"the render with the object must be denoised as its background ({background.denoise!r}),"
                             f" not {denoise!r}")
        match_noise = self.noise_match and path and background is not None and background.groups is not None
        g = groups_for(self.spp) if match_noise else 1
        region, t_region, groups = None, 0.0, None
        if self.spp < (REGION_MIN_SPP if region_min_spp is None else region_min_spp):  # the search would not pay
            region_threshold = None
        if background is not None and path and region_threshold is not None:
            out = render_with_region(env.build, mesh, cams, integrator, self.spp, seed, background.fill, cov,
                                     region_threshold, groups=g, cache=self.region_cache.setdefault(background.key, {}),
                                     renderer=pr)
            img, reg = out[0], out[1]
            groups = out[2] if match_noise else None
            region, t_region = reg.masks, reg.seconds
        elif match_noise:
            img, groups = pr(groups=g)
        else:
            img = render_shaded(env.build(), mesh, cams, integrator, self.spp, seed)
        matched = None
        if int(object_spp) < 1:
            raise ValueError(f"object_spp must be >= 1, got {object_spp}")
        boost = object_pixels(cov, region) if int(object_spp) > 1 and path else None
        if boost is not None:
            boost = np.where(boost, int(object_spp), 1)
        more = (lambda counts, spp, first: pr(None, None, spp, first, counts=counts))
        if match_noise:
            from optimizer.rendering.noise import match

            img, matched = match(more, img, groups,
                                 background.groups, region if region is not None else np.ones(img.shape[:3], bool),
                                 self.spp, boost=boost, combine=object_combine)
        elif boost is not None:
            from optimizer.rendering.noise import more_samples

            img = more_samples(more, img, boost, self.spp)[0]
        d_s = 0.0
        if denoise:
            img, d_s, _ = self._denoised(env, mesh, cams, img, denoise, scene=sc,
                                         without=background.features if background is not None else None,
                                         feature_spp=object_feature_spp)
        return ObjectRenders(img, cov, cov >= 0.5, time.perf_counter() - t, region, t_region, matched, denoise, d_s)


def chosen_setting(plan) -> EvaluationSetting | None:
    """The setting :func:`evaluation_plan` ``(setting="auto")`` chose for ``plan``'s scene, or None (none chosen or
    no pilot run)."""
    ch = ((plan.pilot or {}).get("setting") or {}).get("chosen")
    return None if not ch else EvaluationSetting(**{k: v for k, v in ch.items() if k != "label"})
