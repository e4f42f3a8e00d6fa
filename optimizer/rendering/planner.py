"""Effect planner: simulate only the light transport a scene calls for, decided from a measured pilot.

Two parts, kept apart:

**What correctness requires** (:func:`plan`, from the optimised parameters alone, no measurement): gradients with
respect to geometry (pose, displacement) move silhouettes, and plain ``prb`` is biased there, so they need a
projective integrator (``prb_projective``; ``direct_projective`` when the measured depth is 2); its primary-silhouette
samples are a budget per view, ``2 * (W + H) * spp`` (:func:`training_integrator`, :mod:`optimizer.rendering.projective`),
not Mitsuba's ``sppp`` per pixel; indirect-visibility sampling (``sppi``, the shadow's outline) costs ~35x per step
and is off unless ``shadow_gradients``; only material maps: ``prb``. Masks and depth come from a ray-cast AOV pass.
Without a pilot this plan keeps every bounce (``max_depth`` 12, the full setting) with Russian roulette from vertex
5 (Mitsuba's default; unbiased): it never drops what it has not measured.

**What the scene calls for** (:meth:`Planner.plan`, from a :class:`~optimizer.rendering.pilot.Pilot`): a few seconds
of rendering of the actual scene, object and stage (:meth:`Planner.pilot`, a named step; the constructor only reads
settings) measure, over the pixels that matter (the object's region when optimising, the whole frame for renders
shown whole), in sRGB units:

* each bounce: the light that needs path depth ``M``, and the bias of stopping before it;
* the transmissive chains (light through the object onto its surroundings: the caustics that lighten a
  transmissive object's shadow; light seen through it) and the light the object reflects onto its surroundings;
* each emitter's share of the light;
* with geometry gradients, where the image responds to the pose: on the silhouette (the projective term), inside the
  object, around it (its shadow: what only indirect visibility sampling differentiates);
* the Monte Carlo noise per sample, and the cost (path vertices per sample) of each depth.

``max_depth`` is the smallest depth whose dropped light (RMS over the pixels that matter) stays below
``bias_fraction`` (0.3) of the noise at the stage's spp (the largest spp the plan's depth serves: a squared error at
most 9 % above the noise alone). Training takes that cut only where it also saves at least ``min_cut_saving``
(:data:`MIN_CUT_SAVING`, 10 %) of a training render's seconds, timed at the stage's size (:meth:`Planner.time_cut`:
``cut_views`` of the stage's views at their resolution over the stage's window, its spp, a primal and adjoint render
with the training integrator at the cut and at full depth, interleaved, after an untimed warm-up); elsewhere it
keeps every bounce: a bias that buys no seconds is not taken. A timing is a measurement of this machine under its
load (near the 10 % line two timings of one scene decide differently), so a run's plan is **untimed**, to keep runs
reproducible (same spec and seed, same plan): there the pilot's path vertices over the object's region stand in,
and the cut must save at least ``min_cut_vertex_saving`` (:data:`MIN_CUT_VERTEX_SAVING`, 40 %) of them, the share
that the timed savings put at 10 % of the seconds. A timed plan (``cut_timing``) records its timing
(``plan.pilot.cut_timing``). Russian roulette stays on from vertex 5 (the full setting's; it is unbiased, and
``rr_depth = max_depth`` would turn it off). An emitter whose light is below the same bound is dropped. The plan
states the noise each stage's spp gives and the spp a stated accuracy (``accuracy``, sRGB RMS; 1/255) needs, and
the accuracy-vs-seconds curve of the plan and of full path tracing for the stage's render (:meth:`Plan.curve`).
Renders are restricted to the region the object can change (:mod:`optimizer.rendering.region`; training renders to
the loss domain's window, :func:`optimizer.optimise.stage1.training_windows`); ``region`` says so.

An evaluation plan also states how each pixel's samples are drawn (:data:`EVALUATION_SAMPLER`; ``sobol``, opt-in:
stratified across the pixel's samples, unbiased, the same cost per sample). Where the object changes most of the
frame (gravel's long soft shadow, the panorama's sky: whole frames rendered) neither the depth (Russian roulette from
vertex 5 already makes full tracing's deep paths cheap) nor the region can save seconds at equal error; what is left
is the error per sample, which the stratified sampler lowers, at the price of an object noisier than its cleaner
surroundings (docs/results/planner.md (a), the per-scene breakdown).

``FULL`` (:func:`full_plan`) is the reference "always full path tracing" setting (``--no-planner``, the bench).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Sequence

from optimizer.rendering.denoise import VARIANTS as DENOISE_VARIANTS
from optimizer.rendering.pilot import (FULL_DEPTH, RR_DEPTH, CutTiming, Pilot, PilotSettings, pick_views,
                                      run_pilot, time_depth_cut)
from optimizer.rendering.tracer import SAMPLERS
from optimizer.scenes.environments import Environment
from optimizer.scenes.scenepack import ScenePack

PARAMETERS = ("pose", "displacement", "bsdf", "transmittance", "albedo")
#: The parameters that move the object's geometry (its silhouette and shadows: projective integrators).
GEOMETRY = ("pose", "displacement")
PURPOSES = ("optimize", "render", "evaluate")

FULL_MAX_DEPTH = FULL_DEPTH
SILHOUETTE_SAMPLES_PER_EDGE = 2  # primary-silhouette samples per view = 2 * (W + H) * spp
PROJECTIVE = ("direct_projective", "prb_projective")
#: A transmissive chain (camera -> front face -> back face -> ground -> light, or ground -> object -> object ->
#: light) needs this depth; a plan for an optimisation that may make an opaque start transmissive keeps it.
TRANSMISSIVE_DEPTH = 4
#: Indirect-visibility sampling (``sppi``) multiplies a projective step's cost by about this much.
SPPI_COST = 35
#: A region render pays for the search (its growth steps) when the region holds at most this share of a full
#: render's cost (measured at 96 px, 4 views, 64 spp: meadow, 43 % of the pixels, 1.2-1.3x faster; gravel, 73 %,
#: not faster).
REGION_PAYS = 0.6
#: Below this spp an evaluation render with the object renders whole frames even where the plan searches the region:
#: the search's growth steps (one launch each, more of them at low spp: the noisier change grows the region further)
#: cost more than the pixels they leave out. Measured as ``camo evaluate`` renders (noise matching on, 4 views at
#: 96 px, process time, interleaved; meadow, split, room, occluded): at 8 spp whole frames take 0.77, 0.82, 0.97 and
#: 0.76x the region's seconds, at 16 spp 0.98, 0.95, 1.14, 0.93x, at 32 spp 1.06, 0.88, 1.17, 1.10x, at 64 spp
#: 1.20, 1.07, 1.30, 1.27x (``evaluation.views.ViewRenderer.with_object`` applies it).
REGION_MIN_SPP = 16
#: Each denoiser's bias on the object: the largest RMS (sRGB) by which the mean of its output at 64 spp departed from
#: a converged render over the object's own pixels (coverage >= 0.5; the six built-in scenes' objects at their
#: see-through start, 2 views at 64 px, 3 seeds against 1024 spp; ``bench/bench_planner.py --denoisers``,
#: docs/results/planner.md "The denoiser on the object's own pixels"), rounded up. The object's pixels, not the whole
#: frame's: the frame averages the denoiser's error over pixels the object never touches, and the object is where a
#: participant looks. ``oidn-raw`` (first-hit features): 1.26-1.83/255 (meadow the largest; whole frame
#: 0.77-1.97); ``oidn-through`` (see-through features): 1.31-1.69/255 (split; whole frame 0.79-1.92).
DENOISER_BIASES = {"oidn-raw": 1.9 / 255, "oidn-through": 1.7 / 255}
#: A training plan cuts the path depth only where the cut saves at least this share of a training render's seconds,
#: timed at the stage's size (Planner.time_cut; untimed: of the path vertices over the object's region, the pilot's
#: counts), and where its bias is below bias_fraction x the noise; below it every bounce is kept (depth 12, Russian
#: roulette from vertex 5). 10 %: about the timing's spread between interleaved rounds on the shared machine.
#: Measured (issue 28, docs/results/planner.md "(b) A Stage 1 gradient"): at 4 views x 64 px the cut to 4 saves
#: 3-7 % of the path vertices on the open scenes and the panorama, 32 % in the room, while a Stage 1 step's seconds
#: moved by 0-17 % (within the spread; the room's 5.40 against 5.23 s) and the cut's gradient cosine at equal spp was
#: 0.92-1.14 of full tracing's. Timed with the training integrator (camo_prb_projective, geometry gradients, 4 views
#: x 64 px, 4 spp): the cut saves 2.5 % (occluded), 8 % (split, the room with a transmissive start), 17 % (the room,
#: opaque: depth 3); a plain prb render + adjoint overstates it (18, 16, 25, 32 %): the silhouette terms do not
#: shorten with the depth.
MIN_CUT_SAVING = 0.10
#: The sampler of an evaluation plan's renders (:data:`optimizer.rendering.tracer.SAMPLERS`; the integrator dict's
#: ``sampler``, read by :class:`optimizer.rendering.render.PathRenderer`; ``PlannerSettings.sampler``,
#: ``evaluation_plan(sampler=...)``). ``sobol`` stratifies, across each pixel's samples, the position in the pixel and
#: the first vertex's emitter and BSDF samples (Owen-scrambled Sobol pairs,
#: :func:`optimizer.rendering.tracer.sobol_samples`): unbiased like the independent sampler, the same cost per sample,
#: and the region render, noise matching's further samples and common random numbers with the background work alike
#: (sample ``s`` of pixel ``p`` is fixed whatever else is rendered). Measured (``bench/bench_planner.py --samplers
#: independent,sobol``, docs/results/planner.md (a)): it is the lever that takes the plan past full tracing at equal
#: error where the region render cannot (whole frames): gravel 1.02x -> 2.25x, the panorama 1.01x -> 2.64x (full
#: tracing with it alone: 2.12x, 2.63x). It stays **opt-in** because it cleans the pixels the object does not touch
#: far more than the object's own (their noise is light through the see-through object, deeper than the first
#: vertex): near the object the with-object render's noise against the background's went from 3.15 / 2.34 to
#: 2.54 / 0.84 (/255, gravel), so the object stands out by its noise more (issue 28 item 4), and noise matching (on in
#: ``camo evaluate``) would spend up to its 8x cap on those pixels, a cost not measured with it yet.
EVALUATION_SAMPLER = "independent"
#: The untimed stand-in for MIN_CUT_SAVING (a run's plan: deterministic): the share of the pilot's path vertices over
#: the object's region a training depth cut must save. Calibrated on the timed savings with the training integrator
#: (4 views x 64 px, 4 spp; docs/results/planner.md): the room's transmissive start, cut to 4, saves 32 % of the
#: vertices and 8 % of the seconds (not taken either way); its opaque start, cut to 3, 49 % and 17 % (taken); the
#: open scenes 3-9 % and 2.5-8 % (not taken). The vertex rule before (10 %) took the room's 32 % cut that buys ~5 %.
MIN_CUT_VERTEX_SAVING = 0.40
#: The denoisers an evaluation plan may apply (``PlannerSettings.denoise``, ``--denoise [VARIANT]``): the variants of
#: :data:`optimizer.rendering.denoise.VARIANTS` whose bias on the object is measured (:data:`DENOISER_BIASES`).
DENOISERS = tuple(DENOISER_BIASES)
#: The denoiser ``--denoise`` alone chooses, and its bias on the object. A plan denoises where the noise at the
#: stage's spp is above the chosen denoiser's bias: the
#: denoiser then trades noise for a smaller, stated bias; where the noise is below it (high spp) it would add more
#: error than it removes. It is opt-in (``PlannerSettings.denoise``, ``--denoise``): neither feature kind meets
#: both tests on the object's pixels on every built-in scene (detail within 0.9-1.1 of the converged render's:
#: 0.81-1.14 first-hit, 0.84-1.11 see-through; bias below the denoised render's remaining noise: not on gravel and
#: the panorama), and the see-through kind needs the object's extra samples (``evaluation.views.object_spp_pilot``)
#: to leave it no noisier than its denoised surroundings; counting those and the features, an evaluation render as
#: ``camo evaluate`` makes it is short of the 2x speed target against full path tracing at equal error
#: (``bench/bench_planner.py --evaluate-as``), docs/results/planner.md.
DENOISER = "oidn-raw"
DENOISER_BIAS = DENOISER_BIASES[DENOISER]


@dataclasses.dataclass
class Effect:
    """One measured effect and the planner's decision about it (sRGB units over the pixels that matter)."""

    name: str
    contribution: float | None  # RMS of the light the effect adds (None: not measured)
    noise: float | None  # RMS Monte Carlo noise of the stage's render at its spp
    kept: bool
    why: str

    def to_dict(self) -> dict[str, Any]:
        r = (lambda x: None if x is None else float(x))
        return {"name": self.name, "contribution": r(self.contribution), "noise": r(self.noise), "kept": self.kept,
                "why": self.why}


@dataclasses.dataclass
class Plan:
    integrator: dict[str, Any]
    batch: bool  # all views in one batch sensor
    max_depth: int
    aov_pass: str
    reasons: list[tuple[str, str]]  # (setting, why)
    silhouette_budget: bool = True  # projective: per-view silhouette sample budget (False: Mitsuba's sppp = spp)
    rr_depth: int = RR_DEPTH
    region: bool = False  # renders restricted to the region the object can change
    purpose: str = "optimize"
    effects: list[Effect] = dataclasses.field(default_factory=list)
    spp: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)  # stage -> spp, noise, spp for accuracy
    pilot: dict[str, Any] | None = None  # the pilot's figures (Pilot.to_dict)
    curve: dict[str, Any] | None = None  # accuracy vs seconds of the plan and of full path tracing
    drop_emitters: list[str] = dataclasses.field(default_factory=list)
    region_threshold: float = 0.5 / 255  # sRGB: a change below this is left to the background render
    region_search: bool = False  # searching the region of a render with the object pays (evaluation, targets)
    denoise: str = ""  # evaluation: the denoiser (optimizer.rendering.denoise.VARIANTS) applied to both renders, or ""
    object_spp: int = 1  # evaluation with a denoiser: the object and its rim get this many times the spp (measured)

    @property
    def measured(self) -> bool:
        return self.pilot is not None

    def shading_integrator(self) -> dict[str, Any]:
        """The path tracer of the plan's radiance renders (targets, final renders, evaluation)."""
        return {"type": "path", "max_depth": int(self.max_depth), "rr_depth": int(self.rr_depth)}

    def describe(self) -> str:
        lines = [f"integrator: {self.integrator}",
                 f"batch sensor: {'yes' if self.batch else 'no (one perspective sensor per view)'}"]
        lines += [f"- {k}: {v}" for k, v in self.reasons]
        if self.effects:
            lines.append("measured effects (sRGB, RMS over the pixels that matter; noise at the stage's spp):")
            w = max(len(e.name) for e in self.effects)
            for e in self.effects:
                c = "-" if e.contribution is None else f"{e.contribution * 255:7.3f}/255"
                n = "-" if e.noise is None else f"{e.noise * 255:6.3f}/255"
                lines.append(f"  {'keep' if e.kept else 'drop'}  {e.name:<{w}}  {c:>12}  noise {n:>11}  {e.why}")
        if self.spp:
            lines.append("spp per stage (noise: sRGB RMS over the pixels that matter):")
            for stage, d in self.spp.items():
                lines.append(f"  {stage:<12} {d['spp']:>6} spp  noise {d['noise'] * 255:6.3f}/255  "
                             f"{d['accuracy'] * 255:.2f}/255 needs {d['spp_for_accuracy']} spp")
        if self.curve:
            lines.append(curve_text(self.curve))
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {"purpose": self.purpose, "integrator": dict(self.integrator), "batch": self.batch,
                "max_depth": int(self.max_depth), "rr_depth": int(self.rr_depth), "region": self.region,
                "silhouette_budget": self.silhouette_budget, "aov_pass": self.aov_pass,
                "reasons": [[k, v] for k, v in self.reasons], "effects": [e.to_dict() for e in self.effects],
                "spp": self.spp, "pilot": self.pilot, "curve": self.curve, "drop_emitters": list(self.drop_emitters),
                "region_threshold": float(self.region_threshold), "region_search": self.region_search,
                "denoise": self.denoise, "object_spp": int(self.object_spp)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Plan":
        """A plan recorded by :meth:`to_dict` (a resumed run uses it instead of running the pilot again)."""
        return cls(dict(d["integrator"]), bool(d["batch"]), int(d["max_depth"]), str(d.get("aov_pass", "")),
                   [(str(k), str(v)) for k, v in d.get("reasons", [])], bool(d.get("silhouette_budget", True)),
                   int(d.get("rr_depth", RR_DEPTH)), bool(d.get("region", False)), str(d.get("purpose", "optimize")),
                   [Effect(**e) for e in d.get("effects", [])], dict(d.get("spp", {})), d.get("pilot"),
                   d.get("curve"), list(d.get("drop_emitters", [])), float(d.get("region_threshold", 0.5 / 255)),
                   bool(d.get("region_search", False)), str(d.get("denoise", "")), int(d.get("object_spp", 1)))

    def environment(self, env: Environment) -> Environment:
        """``env`` without the emitters the plan dropped (``env`` itself when none)."""
        if not self.drop_emitters:
            return env
        drop = set(self.drop_emitters)
        build = env.build

        def filtered() -> dict[str, Any]:
            return {k: v for k, v in build().items() if k not in drop}

        return dataclasses.replace(env, build=filtered)


AOV = "ray-cast AOV pass (no shading): visible-object coverage (4x4 rays/pixel, occlusion aware) and depth"


def plan(pack: ScenePack, env: Environment, params: set[str] | frozenset[str] = frozenset(), purpose: str = "optimize",
         shadow_gradients: bool = False, max_depth: int | None = None) -> Plan:
    """The integrator correctness requires for ``purpose`` in :data:`PURPOSES` and the optimised ``params``
    (subset of :data:`PARAMETERS`; read when ``purpose == "optimize"``), with every bounce kept (``max_depth``: 12,
    or as given). :meth:`Planner.plan` refines it from a pilot."""
    unknown = set(params) - set(PARAMETERS)
    if unknown:
        raise ValueError(f"unknown parameters {sorted(unknown)}")
    if purpose not in PURPOSES:
        raise ValueError(f"unknown purpose {purpose!r}; one of {', '.join(PURPOSES)}")
    depth = FULL_MAX_DEPTH if max_depth is None else int(max_depth)
    reasons: list[tuple[str, str]] = [
        ("max_depth", f"{depth}: " + ("set explicitly" if max_depth is not None else
                                      "every bounce (no pilot measured what could be dropped)")),
        ("rr_depth", f"{RR_DEPTH}: Russian roulette from vertex {RR_DEPTH} (Mitsuba's default; unbiased)")]
    return _structure(pack, env, params, purpose, shadow_gradients, depth, RR_DEPTH, reasons)


def moves_geometry(params) -> bool:
    """Whether optimised ``params`` (:data:`PARAMETERS`) move the geometry (:data:`GEOMETRY`)."""
    return bool(set(GEOMETRY) & set(params))


def _structure(pack, env, params, purpose, shadow_gradients, depth, rr_depth, reasons) -> Plan:
    optimise = purpose == "optimize"
    geometry = optimise and moves_geometry(params)
    if geometry:
        if depth <= 2:
            integ: dict[str, Any] = {"type": "direct_projective"}
            reasons.append(("integrator", "direct_projective: pose/displacement move silhouettes (prb is biased "
                            "there); direct light is all the measured transport needs"))
        else:
            integ = {"type": "prb_projective", "max_depth": depth, "rr_depth": rr_depth}
            reasons.append(("integrator", "prb_projective: pose/displacement move silhouettes (prb is biased there); "
                            f"paths up to depth {depth}"))
        if not shadow_gradients:
            integ["sppi"] = 0
        reasons.append(("sppi", "default (on): shadow/reflection boundaries drive the pose (~35x cost)" if shadow_gradients
                        else "0: indirect visibility (the shadow's outline) does not drive the pose; ~35x cheaper"))
        reasons.append(("silhouette samples", f"{SILHOUETTE_SAMPLES_PER_EDGE} * (width + height) * spp per view "
                        "(camo_" + integ["type"] + "), not Mitsuba's sppp per pixel: a silhouette is a 1-D curve; "
                        "the silhouette term's variance is ~1e-4 of the continuous term's or less, and the "
                        "silhouette pass costs ~1/8 at 128^2"))
        batch = False
        reasons.append(("sensors", "one perspective sensor per view (the batch sensor crashes projective integrators)"))
    elif optimise:
        integ = {"type": "prb", "max_depth": depth, "rr_depth": rr_depth}
        reasons.append(("integrator", "prb: only material maps are optimised, prb is unbiased for them"))
        batch = True
        reasons.append(("sensors", "one batch sensor renders every view in one pass"))
    else:
        integ = {"type": "path", "max_depth": depth, "rr_depth": rr_depth}
        reasons.append(("integrator", f"path: {purpose} needs radiance only, no gradients"))
        batch = True
        reasons.append(("sensors", "one batch sensor renders every view in one pass"))
    reasons.append(("emitters", f"scene has {', '.join(env.emitters)}"))
    advice = glint_advice(pack, env, params) if optimise else None
    if advice:
        reasons.append(("initial roughness", advice))
    reasons.append(("masks/depth", AOV))
    return Plan(integ, batch, depth, AOV, reasons, rr_depth=rr_depth, purpose=purpose)


@dataclasses.dataclass(frozen=True)
class PlannerSettings:
    """What the measured planner reads (:class:`Planner`)."""

    pilot: PilotSettings = PilotSettings()
    bias_fraction: float = 0.3  # an effect is dropped when its RMS is below this fraction of the stage's noise
    accuracy: float = 1.0 / 255  # the stated accuracy (sRGB RMS noise) the spp table is computed for
    rr_depth: int = RR_DEPTH
    min_cut_saving: float = MIN_CUT_SAVING  # training: a depth cut is taken only where it saves this share of a
    # training render's seconds (timed; untimed: of the path vertices over the object's region; 0: always)
    min_cut_vertex_saving: float = MIN_CUT_VERTEX_SAVING  # untimed (a run's plan): the share of the pilot's path
    # vertices over the object's region a training depth cut must save (0: always)
    cut_reps: int = 3  # interleaved timed rounds of the cut and of full depth (Planner.time_cut)
    cut_views: int = 4  # the stage's views those rounds render (evenly spaced; a ratio of seconds is timed)
    region: bool = True  # restrict renders to what the object can change
    denoise: str = ""  # evaluation renders, opt-in: the denoiser (one of DENOISERS) applied where the noise at the
    # stage's spp is above its bias, or "" (off, the default: it smooths what a see-through object shows of the ground)
    sampler: str = EVALUATION_SAMPLER  # evaluation renders: how a pixel's samples are drawn (tracer.SAMPLERS)

    def __post_init__(self):
        if self.denoise and self.denoise not in DENOISERS:
            raise ValueError(f"unknown denoiser {self.denoise!r}; choose one of {', '.join(DENOISERS)}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"unknown sampler {self.sampler!r}; choose one of {', '.join(SAMPLERS)}")


class Planner:
    """The measured planner (module doc). ``Planner(settings)`` only keeps its settings; :meth:`pilot` renders,
    :meth:`plan` decides (pure, from the pilot's figures)."""

    def __init__(self, settings: PlannerSettings = PlannerSettings()):
        self.settings = settings

    def pilot(self, env: Environment, mesh_fn: Callable[[], Any], cams: Sequence, seed: int = 0,
              geometry: bool = False, size: float = 1.0) -> Pilot:
        """The pilot of the object ``mesh_fn()`` in ``env`` seen from (a few of) ``cams``
        (:func:`optimizer.rendering.pilot.run_pilot`)."""
        return run_pilot(env.build, mesh_fn, cams, self.settings.pilot, seed=seed, geometry=geometry, size=size)

    def _admissible(self, pilot: Pilot, params, purpose: str, spp: dict[str, int]):
        """The shallowest depth whose dropped light is below ``bias_fraction`` x the noise at the largest spp (at
        least the transmissive floor when an optimised transmittance may open chains), with the figures it used:
        ``(depth, figures, floor, s_max, noise_full, limit)``."""
        if not spp:
            raise ValueError("spp: at least one stage")
        optimise = purpose == "optimize"
        pixels = pilot.region() if optimise else None
        # what the stage's comparison sees: optimising, the loss compares the render with the object to background
        # targets of the same depth (the light both lack cancels): the bias of the object's effect; rendered whole
        # (evaluation, stimuli), the image itself
        f = pilot.depth_figures(pixels, difference=optimise)
        K = pilot.K
        s_max = max(int(v) for v in spp.values())
        noise_full = math.sqrt(f.variance[K - 1] / s_max)
        limit = self.settings.bias_fraction * noise_full
        floor = 2
        if optimise and "transmittance" in params:
            floor = TRANSMISSIVE_DEPTH
        depth = next((M for M in range(floor, K + 1) if f.bias[M - 1] <= limit), K)
        return depth, f, floor, s_max, noise_full, limit

    def admissible_cut(self, pilot: Pilot, params: set[str] | frozenset[str], spp: dict[str, int]) -> int | None:
        """The training depth cut whose bias the pilot puts below the noise (:meth:`plan`'s accuracy criterion), or
        None where every bounce is needed: the depth :meth:`time_cut` should price."""
        depth = self._admissible(pilot, params, "optimize", spp)[0]
        return depth if depth < pilot.K else None

    def time_cut(self, pack: ScenePack, env: Environment, params: set[str] | frozenset[str],
                 mesh_fn: Callable[[], Any], cams: Sequence, pilot: Pilot, depth: int, spp: int, seed: int = 0,
                 shadow_gradients: bool = False, clock: Callable[[], float] | None = None) -> CutTiming:
        """Time the cut to ``depth`` against full depth at the stage's size (``cut_views`` of the stage's ``cams``,
        evenly spaced, at their resolution, over the window bounding the pilot's object region, ``spp``: the
        training renders'), each with the training integrator its plan for the optimised ``params`` would have
        (projective, with the silhouette budget, where they move the geometry) and Russian roulette as that plan has
        it (:func:`optimizer.rendering.pilot.time_depth_cut`; a named step, like :meth:`pilot`). ``clock``: seconds
        (default: process CPU seconds)."""
        kw = {} if clock is None else {"clock": clock, "clock_name": "injected"}
        cams = [cams[i] for i in pick_views(cams, self.settings.cut_views)]
        rr = min(self.settings.rr_depth, FULL_DEPTH)
        # the training integrator of each depth's plan (params: the optimised parameters; projective when they move
        # the geometry, with its silhouette budget), as Stage 1 renders with it
        integrators = {d: training_integrator(_structure(pack, env, params, "optimize", shadow_gradients, d, rr, []),
                                              int(spp), (cams[0].width, cams[0].height))
                       for d in (int(depth), FULL_DEPTH)}
        return time_depth_cut(env.build, mesh_fn, cams, pilot.region(), depth, spp, seed=seed, rr_depth=rr,
                              reps=self.settings.cut_reps, integrators=integrators,
                              geometry=moves_geometry(params), **kw)

    def plan(self, pack: ScenePack, env: Environment, params: set[str] | frozenset[str], purpose: str, pilot: Pilot,
             spp: dict[str, int], shadow_gradients: bool = False, cut_timing: CutTiming | None = None) -> Plan:
        """The plan for ``purpose`` from ``pilot``; ``spp``: each stage's samples per pixel served by the plan's
        depth (``training``, ``targets``, ``holdout``; ``evaluation``; ...). The depth is decided at the largest.
        ``cut_timing`` (:meth:`time_cut` of :meth:`admissible_cut`): the seconds a training depth cut saves; without
        it the pilot's path vertices stand in."""
        st = self.settings
        if not spp:
            raise ValueError("spp: at least one stage")
        optimise = purpose == "optimize"
        pixels = pilot.region() if optimise else None
        where = "the object's region" if optimise else "the whole frame"
        depth, f, floor, s_max, noise_full, limit = self._admissible(pilot, params, purpose, spp)
        K = pilot.K
        rr = min(st.rr_depth, FULL_DEPTH)
        effects: list[Effect] = []
        # a training depth cut trades a bias for the seconds it saves: taken where its bias is below the noise (the
        # depth above is the shallowest such) AND it saves at least min_cut_saving of a training render's seconds,
        # timed at the stage's size (cut_timing); untimed, the pilot's path vertices stand in (module doc)
        vsaving = 1.0 - float(f.cost[depth - 1]) / max(float(f.cost[K - 1]), 1e-12)
        timed = cut_timing if (cut_timing is not None and optimise and depth < K and cut_timing.depth == depth) \
            else None
        saving = timed.saving if timed is not None else vsaving
        priced = (f"{saving:.1%} of a training render's seconds ({timed.describe()}; path vertices: {vsaving:.1%})"
                  if timed is not None else f"{vsaving:.1%} of the path vertices (not timed)")
        accuracy = (f"its bias {f.bias[depth - 1] * 255:.3f}/255 RMS over {where} is below {st.bias_fraction:g} x the "
                    f"noise at {s_max} spp ({limit * 255:.3f}/255)")
        need = st.min_cut_saving if timed is not None else st.min_cut_vertex_saving
        cut = depth if optimise and depth < K and saving < need else None
        if cut is not None:
            depth = K
            effects.append(Effect(f"depth cut to {cut} (saves {priced})",
                                  float(f.bias[cut - 1]), math.sqrt(f.variance[cut - 1] / s_max), False,
                                  f"not taken: saves below {need:.0%}, not worth its bias ({accuracy})"))
        elif optimise and depth < K:
            effects.append(Effect(f"depth cut to {depth} (saves {priced})", float(f.bias[depth - 1]),
                                  math.sqrt(f.variance[depth - 1] / s_max), True,
                                  f"taken: saves at least {need:.0%} and {accuracy}"))
        noise_at = math.sqrt(f.variance[depth - 1] / s_max)
        last = min(K, (depth if cut is None else cut) + 1)  # bounces listed one by one; the deeper ones in one row
        for M in range(2, last + 1):
            kept = M <= depth
            why = "kept" if kept else f"dropped: it and every deeper bounce {f.bias[depth - 1] * 255:.3f}/255 RMS"
            if cut is not None and M > cut:
                why = f"kept: every bounce (a cut at {cut} saves {saving:.1%})"
            elif kept and M == depth and depth > floor:
                why = f"kept: stopping before it would leave {f.bias[M - 2] * 255:.3f}/255 > {limit * 255:.3f}/255"
            elif kept and M == floor and floor > 2 and f.bias[M - 2] <= limit:
                why = "kept: an optimised transmittance may open transmissive chains (they need depth 4)"
            effects.append(Effect(f"bounce {M} (depth {M})", float(f.bounce[M - 1]), noise_at, kept, why))
        if last < K:
            effects.append(Effect(f"bounces {last + 1}-{K}", float(f.bias[last - 1]), noise_at, cut is not None,
                                  "kept with the one above" if cut is not None else "dropped with the one above"))
        for name, label in (("via_t", "light through the object onto its surroundings (transmissive chains)"),
                            ("seen_t", "light seen through the object"),
                            ("via", "light the object reflects or lets through onto its surroundings")):
            rms, per_sample = pilot.category(name, pixels)
            need = TRANSMISSIVE_DEPTH if name in ("via_t", "seen_t") else 3
            kept = depth >= need
            why = (f"{'kept' if kept else 'dropped'} (needs depth >= {need})" +
                   (f"; its own noise {per_sample * 255:.2f}/255 per sample" if per_sample else ""))
            effects.append(Effect(label, rms, noise_at, kept, why))
        drop: list[str] = []
        shares = pilot.emitter_shares(pixels)
        mean_y = _mean_srgb_light(pilot, pixels)
        keys = _element_ids(env) if len(shares) > 1 else set()
        for i, share in enumerate(shares):
            label = pilot.emitters[i] if i < len(pilot.emitters) else f"emitter {i}"
            key = label.split(" (")[0]
            contribution = share * mean_y
            dropped = len(shares) > 1 and contribution < limit and key in keys
            if dropped:
                drop.append(key)
            effects.append(Effect(f"emitter {label}: {share:.0%} of the light", contribution, noise_at, not dropped,
                                  "dropped: below the noise" if dropped else
                                  ("kept" if len(shares) > 1 else "kept: the only emitter")))
        deeper = "changes the object's effect (with minus without it) by" if optimise else "is"
        if cut is None:
            why_depth = (f"{depth}: the light of deeper paths {deeper} {f.bias[depth - 1] * 255:.3f}/255 RMS over "
                         f"{where}, below {st.bias_fraction:g} x the noise at {s_max} spp ({noise_full * 255:.3f}/255)"
                         + (f"; at least {floor}: an optimised transmittance may open transmissive chains"
                            if floor > 2 else ""))
            if optimise and depth < K:
                why_depth += f"; the cut saves {priced} (at least {need:.0%} pays for its bias)"
        else:
            why_depth = (f"{depth} (every bounce): stopping at {cut} would change the object's effect by only "
                         f"{f.bias[cut - 1] * 255:.3f}/255 RMS over {where} (below {st.bias_fraction:g} x the noise at "
                         f"{s_max} spp, {noise_full * 255:.3f}/255) but save only {priced} (below "
                         f"{need:.0%}): a training step's seconds hardly depend on the depth here "
                         f"(Russian roulette from vertex {rr} makes the deeper paths cheap; the silhouette terms do "
                         "not shorten), so the cut's bias would buy too few seconds")
        reasons: list[tuple[str, str]] = [
            ("max_depth", why_depth),
            ("rr_depth", f"{rr}: Russian roulette from vertex {rr} as in full path tracing (unbiased; "
                         "rr_depth = max_depth would turn it off)" + (f"; paths stop at depth {depth} before it"
                                                                       if depth <= rr else "")),
        ]
        geometry = optimise and moves_geometry(params)
        out = _structure(pack, env, params, purpose, shadow_gradients, depth, rr, reasons)
        if geometry and pilot.sensitivity:
            sens = pilot.sensitivity
            effects.append(Effect(f"silhouette term ({sens['silhouette']:.0%} of the image's response to the pose)",
                                  None, None, True, "kept: projective sampling (camo_" + out.integrator["type"] +
                                  ", a per-view budget)"))
            effects.append(Effect(f"indirect visibility ({sens['surroundings']:.0%} of the response: the shadow)",
                                  None, None, bool(shadow_gradients),
                                  "on (--shadow-gradients)" if shadow_gradients else
                                  f"off: sppi costs ~{SPPI_COST}x per step; the pose follows the silhouette "
                                  f"({sens['silhouette']:.0%}) and the inside ({sens['inside']:.0%}); "
                                  "--shadow-gradients turns it on"))
        out.region_threshold = max(0.5 / 255, limit)
        reg = pilot.region()
        share, cost_share = float(reg.mean()), pilot.cost_share(reg)
        pays = cost_share <= REGION_PAYS
        out.region = bool(st.region) and (pays or optimise)
        out.region_search = bool(st.region) and pays
        if st.region:
            changed = (f"the pilot's object changes {share:.0%} of its frames, {cost_share:.0%} of a render's cost, "
                       f"by more than {out.region_threshold * 255:.2f}/255 (half an 8-bit step, or "
                       f"{st.bias_fraction:g} x the noise if larger)")
            if pays:
                why = f"renders cover only what the object can change ({changed}), the rest is the background render's"
                if purpose == "evaluate":
                    why += f" (below {REGION_MIN_SPP} spp whole frames: the search's launches would cost more)"
            else:
                why = (f"whole frames: {changed}; above {REGION_PAYS:.0%} of the cost, finding the region would not "
                       "pay for the pixels it leaves out")
            if optimise:
                why += "; training renders the loss domain's window" + ("" if pays else
                                                                       " (its domain is known: no search)")
            out.reasons.append(("region", why))
            effects.append(Effect(f"pixels the object does not change ({1 - share:.0%} of the frame, "
                                  f"{1 - cost_share:.0%} of the cost)", None, None, not (pays or optimise),
                                  "taken from the background render" if pays else "rendered: too little to gain"))
        out.effects = effects
        out.drop_emitters = drop
        acc = st.accuracy
        out.spp = {stage: {"spp": int(n), "noise": math.sqrt(f.variance[depth - 1] / max(int(n), 1)),
                           "accuracy": acc, "spp_for_accuracy": int(math.ceil(f.variance[depth - 1] / acc ** 2))}
                   for stage, n in spp.items()}
        if purpose == "evaluate":
            noise_eval = math.sqrt(f.variance[depth - 1] / s_max)
            den = st.denoise or DENOISER  # the rule stated when off is the default denoiser's
            bias = DENOISER_BIASES[den]
            use = bool(st.denoise) and noise_eval > bias
            out.denoise = den if use else ""
            measured = (f"the noise at {s_max} spp ({noise_eval * 255:.2f}/255 over the whole frame) is "
                        f"{'above' if noise_eval > bias else 'not above'} the denoiser's measured bias "
                        f"({bias * 255:.1f}/255, {den})")
            feats = "see-through" if DENOISE_VARIANTS[den].see_through else "first-hit"
            why = (f"{den} (Open Image Denoise with {feats} albedo and normal, on the renders with and without "
                   f"the object alike, after noise matching; --denoise {den}): {measured}" if use else
                   (f"off by default (--denoise [VARIANT] turns it on where {measured}): the first-hit albedo of a "
                    "see-through object is its own smooth map, so oidn-raw wipes the ground texture seen through it "
                    "and the object reads as a smooth patch on grainy ground; oidn-through (see-through features) "
                    "keeps it, and with the object's spp factor its own pilot measures the object is no noisier than "
                    "its denoised surroundings, but counting those samples and its features it is short of the "
                    "planner's 2x speed target against full path tracing at equal error (docs/results/planner.md)" if not st.denoise else f"off: {measured}"))
            out.reasons.append(("denoise", why))
            if st.sampler != "independent":  # the default plan's integrator stays as it was (no key Mitsuba lacks)
                out.integrator = dict(out.integrator, sampler=st.sampler)
            out.reasons.append(("sampler", f"{st.sampler}: " + (
                "each pixel's samples stratified (Owen-scrambled Sobol pairs: the position in the pixel, the first "
                "vertex's emitter and BSDF samples), unbiased at the independent sampler's cost per sample; lower "
                "error at equal spp, but the object's surroundings come out noisier than the background's "
                "(docs/results/planner.md (a))" if st.sampler == "sobol" else
                "every sample drawn independently (sampler=sobol stratifies them: 2.1-2.6x less time at equal error "
                "on whole frames, but the object's noise then stands out against a cleaner background; "
                "docs/results/planner.md (a))")))
            effects.append(Effect(f"denoiser ({den}: Open Image Denoise; its bias)", bias, noise_eval, use,
                                  "applied to both renders" if use else why))
        out.pilot = pilot.to_dict()
        if timed is not None:
            out.pilot["cut_timing"] = timed.to_dict()
        out.curve = curve(pilot, depth, rr, pilot.region(), out.region_search)
        return out


def _mean_srgb_light(pilot: Pilot, pixels) -> float:
    """RMS sRGB-slope-weighted luminance over ``pixels`` (what a light's share of the pixels is worth in sRGB)."""
    import numpy as np

    from optimizer.rendering.pilot import srgb_slope

    sel = np.ones(pilot.obj.shape[:3], bool) if pixels is None else pixels
    y = pilot.luminance(pilot.obj)[sel]
    return float(np.sqrt(np.mean((srgb_slope(y) * y) ** 2))) if y.size else 0.0


def _element_ids(env: Environment) -> set[str]:
    try:
        return set(env.build())
    except Exception:  # pragma: no cover - a build that needs a variant; nothing can be dropped then
        return set()


def curve(pilot: Pilot, depth: int, rr: int, pixels, region: bool,
          spps: Sequence[int] = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)) -> dict[str, Any]:
    """Predicted accuracy (sRGB RMS error over the frame against converged full path tracing) against seconds of one
    render of the pilot's views at the pilot's resolution, for the plan (depth ``depth``; with ``region`` only the
    region's pixels rendered, the rest from the background render at the same spp) and for full path tracing
    (depth 12, every pixel). Seconds: the vertices traced times the pilot's own seconds per vertex."""
    import numpy as np

    K = pilot.K
    sel = np.ones(pilot.obj.shape[:3], bool) if pixels is None else np.asarray(pixels, bool)
    if not region:
        sel = np.ones_like(sel)
    inside = pilot.depth_figures(sel)
    full = pilot.depth_figures(None)
    outside = pilot.depth_figures(~sel, with_object=False) if (~sel).any() else None
    n_all = sel.size
    n_in = int(sel.sum())
    spv = pilot.seconds_per_vertex()
    rows = []
    for s in spps:
        e_full = math.sqrt(full.variance[K - 1] / s)
        t_full = spv * s * n_all * full.cost[K - 1]
        mse = n_in * (inside.bias[depth - 1] ** 2 + inside.variance[depth - 1] / s)
        if outside is not None:
            mse += (n_all - n_in) * outside.variance[K - 1] / s
        e_plan = math.sqrt(mse / n_all)
        t_plan = spv * s * n_in * inside.cost[depth - 1]
        rows.append({"spp": int(s), "plan_seconds": t_plan, "plan_error": e_plan, "full_seconds": t_full,
                     "full_error": e_full})
    return {"views": int(pilot.obj.shape[0]), "width": pilot.width, "height": pilot.height, "rows": rows,
            "note": "predicted from the pilot: error = sRGB RMS against converged full path tracing over the frame; "
                    "seconds = path vertices x the pilot's seconds per vertex"}


def curve_text(c: dict[str, Any]) -> str:
    lines = [f"accuracy vs seconds ({c['views']} views at {c['width']}x{c['height']}; {c['note']}):",
             "   spp   plan s    plan err   full s    full err"]
    for r in c["rows"]:
        lines.append(f"  {r['spp']:>5}  {r['plan_seconds']:7.3f}  {r['plan_error'] * 255:7.3f}/255  "
                     f"{r['full_seconds']:7.3f}  {r['full_error'] * 255:7.3f}/255")
    return "\n".join(lines)


def curve_png(c: dict[str, Any], path, title: str = "") -> None:
    """The accuracy-vs-seconds curve of a plan and of full path tracing (log-log), as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from camo_base import atomic

    rows = c["rows"]
    fig, ax = plt.subplots(figsize=(5.2, 3.6), dpi=120)
    ax.loglog([r["full_seconds"] for r in rows], [r["full_error"] * 255 for r in rows], "o-", label="full path tracing")
    ax.loglog([r["plan_seconds"] for r in rows], [r["plan_error"] * 255 for r in rows], "s-", label="plan")
    for r in rows[::2]:
        ax.annotate(f"{r['spp']}", (r["plan_seconds"], r["plan_error"] * 255), fontsize=7, xytext=(3, 3),
                    textcoords="offset points")
    ax.set_xlabel("seconds (predicted from the pilot)")
    ax.set_ylabel("RMS error (sRGB, /255)")
    ax.set_title(title or "accuracy vs seconds", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


COMPACT_EMITTERS = ("sun", "area")
#: Below this map roughness a facet that mirrors the sun into a camera is brighter than twice the background's
#: 99.5th percentile on every sunlit built-in scene (ratio 2.0-2.8 at 0.3, 1.0-1.3 at 0.4, 0.6-0.9 at 0.5:
#: ``bench/glint_roughness.py``). Evaluated views cover many facet orientations, so such a start keeps glints.
GLINT_ROUGHNESS = 0.5


def glint_advice(pack: ScenePack, env: Environment, params: set[str] | frozenset[str]) -> str | None:
    """A warning when a smooth start meets a compact light (see ``optimizer.scenes.builtin_scenes.INITIAL_MATERIAL``)."""
    compact = [e for e in env.emitters if e in COMPACT_EMITTERS]
    if env.compact_envmap_light:
        compact.append("a sun-like spot in the envmap")
    if "bsdf" not in params or pack.material.roughness >= GLINT_ROUGHNESS or not compact:
        return None
    return (f"{pack.material.roughness:g} with a compact light ({', '.join(compact)}): specular glints may stay. "
            f"A facet mirroring the light outshines the background below roughness ~{GLINT_ROUGHNESS:g} "
            "(bench/glint_roughness.py), no gradient raises the roughness while the lobe is narrower than the light, "
            "and Adam moves a map value by about one learning rate per step; --init roughness=0.5 avoids them "
            "(docs/optimizer.md, 'Why the built-in scenes start rough')")


def full_plan(purpose: str = "optimize", geometry: bool = True) -> Plan:
    """The bench's reference: full path tracing, max_depth 12, Russian roulette from 5 (Mitsuba's defaults),
    projective sampling on (indirect visibility included), Mitsuba's per-pixel silhouette samples, full frames."""
    if purpose == "optimize" and geometry:
        integ = {"type": "prb_projective", "max_depth": FULL_MAX_DEPTH}
        batch = False
    elif purpose == "optimize":
        integ = {"type": "prb", "max_depth": FULL_MAX_DEPTH}
        batch = True
    else:
        integ = {"type": "path", "max_depth": FULL_MAX_DEPTH}
        batch = True
    return Plan(integ, batch, FULL_MAX_DEPTH, "", [("integrator", "always full")], silhouette_budget=False,
                rr_depth=RR_DEPTH, purpose=purpose)


def silhouette_samples(width: int, height: int, spp: int) -> int:
    """Primary-silhouette samples per view: ``SILHOUETTE_SAMPLES_PER_EDGE * (W + H) * spp``.

    A silhouette is a 1-D curve whose length in pixels grows like ``W + H``, so this keeps the samples per
    silhouette pixel fixed at any resolution (Mitsuba's ``sppp`` grows them like ``W * H``)."""
    return max(1, SILHOUETTE_SAMPLES_PER_EDGE * (int(width) + int(height)) * int(spp))


def training_integrator(plan: Plan, spp: int, size: tuple[int, int]) -> tuple[dict[str, Any], int]:
    """The integrator dict Stage 1 trains with at ``spp`` on ``size = (width, height)`` views, and the
    ``spp`` to pass to ``mi.render``.

    Projective integrators become :mod:`optimizer.rendering.projective`'s ``camo_*`` variants (when
    ``plan.silhouette_budget``) with ``sppc = spp`` (continuous part), ``sppp = 1`` (switches the
    primary-silhouette pass on) and ``silhouette_samples`` = :func:`silhouette_samples`; without the budget
    (the bench's full plan) ``sppp = spp``. An ``sppi`` the plan set stays (unset: ``spp``). Mitsuba lets a
    non-zero ``spp`` argument override all of these, so they are rendered with ``spp=0``: the primal pass
    then takes the sensor sampler's ``sample_count``, which must equal ``spp``. Other integrators are
    returned as is with ``spp``.
    """
    integrator = plan.integrator
    if integrator.get("type") not in PROJECTIVE:
        return dict(integrator), spp
    if plan.silhouette_budget:
        from optimizer.rendering.projective import NAMES

        out = dict(integrator, type=NAMES[integrator["type"]], sppc=int(spp), sppp=1,
                   silhouette_samples=silhouette_samples(size[0], size[1], spp))
    else:
        out = dict(integrator, sppc=int(spp), sppp=int(spp))
    if "sppi" not in integrator:
        out["sppi"] = int(spp)
    return out, 0
