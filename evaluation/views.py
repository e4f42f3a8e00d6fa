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
from optimizer.rendering.noise import GROUPS
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
                    denoise: str = ""):
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
    (:data:`optimizer.rendering.planner.DENOISER_BIASES`; ``plan.denoise``)."""
    from camo_base import seeds
    from optimizer.rendering.planner import Planner, PlannerSettings, plan

    worst = dataclasses.replace(pack, material=dataclasses.replace(pack.material, transmittance=1.0, metallic=0.0))
    if cams is None or not measured:
        return plan(worst, env, set(), "evaluate")
    from optimizer.rendering.placement import prepare_object, static_object_fn

    # the pilot renders at ~48 px: a light mesh will do (and it is prepared once, then cached)
    mesh = static_object_fn(worst, prepare_object(worst, target_vertices=min(worst.object.target_vertices,
                                                                             PILOT_VERTICES)))
    planner = Planner(PlannerSettings(denoise=denoise))
    pilot = planner.pilot(env, mesh, cams, seed=seeds.seed("evaluation_pilot", seed))
    return planner.plan(worst, env, set(), "evaluate", pilot, {"evaluation": int(spp)})


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

    def __init__(self, spp: int, seed: int = 0, ss: int = 4, noise_match: bool = False):
        """``noise_match``: renders with an object get more samples where they are noisier than the background
        (:mod:`optimizer.rendering.noise`; needs a ``path`` integrator and the background of the same seed)."""
        self.spp, self.seed, self.ss, self.noise_match = int(spp), int(seed), int(ss), bool(noise_match)
        self.cache: dict[str, Background] = {}
        self.background_renders = 0  # how many times a background was actually rendered
        self.region_cache: dict[str, dict] = {}  # per background: the region pass' renders without the object

    def _key(self, pack, cams: list[Camera], integrator: dict, denoise: str = "") -> str:
        blob = json.dumps({"env": dataclasses.asdict(pack.environment), "cams": [dataclasses.astuple(c) for c in cams],
                           "spp": self.spp, "integrator": integrator, "seed": self.seed,
                           **({"denoise": denoise} if denoise else {})}, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def _denoised(self, env, obj, cams: list[Camera], img: np.ndarray, denoise: str) -> tuple[np.ndarray, float]:
        """``img`` denoised by ``denoise`` with the features of the same scene, cameras and seed
        (:mod:`optimizer.rendering.denoise`: the variant's albedo and normal, first-hit or see-through, at up to
        :data:`FEATURE_SPP` spp); with the
        seconds it took."""
        from optimizer.rendering.denoise import denoise_variant, variant_features

        t = time.perf_counter()
        albedo, normal = variant_features(denoise, env.build(), obj, cams, min(self.spp, FEATURE_SPP),
                                          render_seed(self.seed))
        return denoise_variant(img, albedo, normal, denoise), time.perf_counter() - t

    def background(self, pack, env, cams: list[Camera], integrator: dict, denoise: str = "") -> Background:
        """The scene without the object; ``denoise``: the denoiser of the evaluation plan (``plan.denoise``), or ""."""
        from optimizer.rendering import scene as scn
        from optimizer.rendering.render import coverage_and_depth, render_shaded

        key = self._key(pack, cams, integrator, denoise)
        if key not in self.cache:
            t = time.perf_counter()
            groups = None
            if self.noise_match and integrator.get("type") == "path" and self.spp % GROUPS == 0:
                from optimizer.rendering.render import PathRenderer

                img, groups = PathRenderer(env.build(), None, cams, integrator, self.spp,
                                           render_seed(self.seed))(groups=GROUPS)
            else:
                img = render_shaded(env.build(), None, cams, integrator, self.spp, render_seed(self.seed))
            raw, d_s = None, 0.0
            if denoise:
                raw = img
                img, d_s = self._denoised(env, None, cams, raw, denoise)
            sc = scn.build_scene(env.build())
            depth = np.stack([coverage_and_depth(sc, c, None, self.ss)[1] for c in cams])
            self.cache[key] = Background(img, depth, time.perf_counter() - t, key, groups, raw, denoise, d_s)
            self.background_renders += 1
        return self.cache[key]

    def with_object(self, env, mesh_fn, cams: list[Camera], integrator: dict,
                    background: Background | None = None, region_threshold: float | None = None,
                    denoise: str | None = None) -> ObjectRenders:
        """The scene with the object ``mesh_fn()``. ``background``: the same cameras, spp, integrator and seed. With
        ``region_threshold`` (sRGB) only the region the object can change is rendered
        (:func:`optimizer.rendering.region.render_region`); every other pixel is the background's, which the same
        random numbers drew there (``tests/test_region.py``). With noise matching, pixels where the render is
        noisier than the background get more samples (:mod:`optimizer.rendering.noise`). ``denoise`` (default: the
        background's): the denoiser applied to the render (after noise matching), exactly as to the background (same
        features' spp and seed). Noise matching stays on beside it: alone, the denoiser leaves a transmissive
        object's fireflies (fewer, but more visible against a background it smooths: ``bench/bench_noise.py
        --denoise``)."""
        from optimizer.rendering import scene as scn
        from optimizer.rendering.render import PathRenderer, coverage_and_depth, render_shaded, render_with_region

        t = time.perf_counter()
        mesh = mesh_fn()
        sc = scn.build_scene(env.build(), mesh)
        cov = np.stack([coverage_and_depth(sc, c, mesh, self.ss)[0] for c in cams]).astype(np.float32)
        seed = render_seed(self.seed)
        path = integrator.get("type") == "path"
        if denoise is None:
            denoise = background.denoise if background is not None else ""
        if background is not None and denoise != background.denoise:
            raise ValueError(f"the render with the object must be denoised as its background ({background.denoise!r}),"
                             f" not {denoise!r}")
        match_noise = self.noise_match and path and background is not None and background.groups is not None
        g = GROUPS if match_noise else 1
        region, t_region, groups = None, 0.0, None
        if background is not None and path and region_threshold is not None:
            out = render_with_region(env.build, mesh, cams, integrator, self.spp, seed, background.fill, cov,
                                     region_threshold, groups=g, cache=self.region_cache.setdefault(background.key, {}))
            img, reg = out[0], out[1]
            groups = out[2] if match_noise else None
            region, t_region = reg.masks, reg.seconds
        elif match_noise:
            img, groups = PathRenderer(env.build(), mesh, cams, integrator, self.spp, seed)(groups=g)
        else:
            img = render_shaded(env.build(), mesh, cams, integrator, self.spp, seed)
        matched = None
        if match_noise:
            from optimizer.rendering.noise import match

            more = PathRenderer(env.build(), mesh, cams, integrator, self.spp, seed)
            img, matched = match(lambda sel, spp, first: more(sel, None, spp, first), img, groups,
                                 background.groups, region if region is not None else np.ones(img.shape[:3], bool),
                                 self.spp)
        d_s = 0.0
        if denoise:
            img, d_s = self._denoised(env, mesh, cams, img, denoise)
        return ObjectRenders(img, cov, cov >= 0.5, time.perf_counter() - t, region, t_region, matched, denoise, d_s)
