"""Effect planner: simulate only the light-transport effects a scene calls for.

From the scene (its emitters, geometry near the object, the object's material)
and the parameters being optimised, choose the integrator and its settings, and
say why. Rules (Mitsuba 3.9):

* **Gradients w.r.t. geometry** (pose, displacement) move silhouettes; plain
  ``prb`` is biased there, so a projective integrator is needed:
  ``direct_projective`` for an opaque object in an open scene (direct light
  dominates), else ``prb_projective``. Indirect-visibility sampling (``sppi``)
  costs ~35x and is off unless ``shadow_gradients`` asks for the object's
  shadow/reflection boundaries to drive the pose. Primary-silhouette samples
  are a budget per view, ``2 * (W + H) * spp`` (:func:`training_integrator`,
  :mod:`optimizer.rendering.projective`), not Mitsuba's ``sppp`` per *pixel*: a
  silhouette is a 1-D curve, and its term's variance stays ~1e-4 of the
  continuous term's or less (gravel, 128^2, 256 to 16384 samples).
* **Only material maps** optimised: ``prb`` (unbiased for BSDF parameters),
  and all views in one ``batch`` sensor.
* **max_depth** just deep enough: 3 for an opaque object outdoors (direct light
  plus one bounce: ground light under the object, its colour on the ground);
  +1 with nearby walls/occluders (interreflection); 6 for a transmissive object
  (camera -> front face -> back face -> background -> light, plus one bounce);
  ``rr_depth = max_depth`` so Russian roulette never truncates these short paths.
* **Masks and depth** come from a ray-cast AOV pass (no shading).
* Emitters: only those the scene has are sampled (Mitsuba samples the scene's
  own emitters; the planner adds none and reports which exist).

``FULL`` is the reference "always full path tracing" setting used by the bench.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from optimizer.scenes.environments import Environment
from optimizer.scenes.scenepack import ScenePack

PARAMETERS = ("pose", "displacement", "bsdf", "transmittance", "albedo")

FULL_MAX_DEPTH = 12
SILHOUETTE_SAMPLES_PER_EDGE = 2  # primary-silhouette samples per view = 2 * (W + H) * spp
PROJECTIVE = ("direct_projective", "prb_projective")


@dataclasses.dataclass
class Plan:
    integrator: dict[str, Any]
    batch: bool  # all views in one batch sensor
    max_depth: int
    aov_pass: str
    reasons: list[tuple[str, str]]  # (setting, why)
    silhouette_budget: bool = True  # projective: per-view silhouette sample budget (False: Mitsuba's sppp = spp)

    def describe(self) -> str:
        lines = [f"integrator: {self.integrator}", f"batch sensor: {'yes' if self.batch else 'no (one perspective sensor per view)'}"]
        lines += [f"- {k}: {v}" for k, v in self.reasons]
        return "\n".join(lines)


def plan(pack: ScenePack, env: Environment, params: set[str] | frozenset[str] = frozenset(), purpose: str = "optimize",
         shadow_gradients: bool = False, max_depth: int | None = None) -> Plan:
    """Decide integrator settings for ``purpose`` in {"optimize", "render", "evaluate"}.

    ``params`` are the optimised parameters (subset of :data:`PARAMETERS`);
    ignored unless ``purpose == "optimize"``.
    """
    unknown = set(params) - set(PARAMETERS)
    if unknown:
        raise ValueError(f"unknown parameters {sorted(unknown)}")
    reasons: list[tuple[str, str]] = []
    optimise = purpose == "optimize"
    geometry = optimise and bool({"pose", "displacement"} & set(params))
    transmissive = pack.material.transmittance > 0 or (optimise and "transmittance" in params)
    reflective = pack.material.metallic > 0 or (optimise and "bsdf" in params)

    depth = 3
    why = ["direct light + one bounce (ground light under the object, the object's colour on the ground)"]
    if env.nearby_geometry:
        depth += 1
        why.append("+1 for interreflection with nearby walls/occluders")
    if transmissive:
        depth = max(depth, 6)
        why.append("6 for refraction through a closed transmissive mesh (front face, back face, background, light)")
    if reflective:
        why.append("metallic reflections of the surroundings are covered by the same depth")
    if max_depth is not None:
        depth = max_depth
        why = [f"set explicitly to {max_depth}"]
    reasons.append(("max_depth", f"{depth}: " + "; ".join(why)))

    if geometry:
        open_opaque = not transmissive and not env.nearby_geometry and max_depth is None
        if open_opaque:
            integ: dict[str, Any] = {"type": "direct_projective"}
            depth = 2
            reasons.append(("integrator", "direct_projective: pose/displacement move silhouettes (prb is biased there); "
                            "opaque object in an open scene, direct light dominates"))
        else:
            integ = {"type": "prb_projective", "max_depth": depth, "rr_depth": depth}
            reasons.append(("integrator", "prb_projective: pose/displacement move silhouettes (prb is biased there); "
                            + ("transmission" if transmissive else "interreflection") + " needs multi-bounce paths"))
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
        integ = {"type": "prb", "max_depth": depth, "rr_depth": depth}
        reasons.append(("integrator", "prb: only material maps are optimised, prb is unbiased for them"))
        batch = True
        reasons.append(("sensors", "one batch sensor renders every view in one pass"))
    else:
        integ = {"type": "path", "max_depth": depth, "rr_depth": depth}
        reasons.append(("integrator", f"path: {purpose} needs radiance only, no gradients"))
        batch = True
        reasons.append(("sensors", "one batch sensor renders every view in one pass"))
    reasons.append(("emitters", f"scene has {', '.join(env.emitters)}; only these are sampled"))
    advice = glint_advice(pack, env, params) if optimise else None
    if advice:
        reasons.append(("initial roughness", advice))
    aov = "ray-cast AOV pass (no shading): visible-object coverage (4x4 rays/pixel, occlusion aware) and depth"
    reasons.append(("masks/depth", aov))
    return Plan(integ, batch, depth, aov, reasons)


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
    """The bench's reference: full path tracing, max_depth 12, projective sampling on."""
    if purpose == "optimize" and geometry:
        integ = {"type": "prb_projective", "max_depth": FULL_MAX_DEPTH}
        batch = False
    elif purpose == "optimize":
        integ = {"type": "prb", "max_depth": FULL_MAX_DEPTH}
        batch = True
    else:
        integ = {"type": "path", "max_depth": FULL_MAX_DEPTH}
        batch = True
    return Plan(integ, batch, FULL_MAX_DEPTH, "", [("integrator", "always full")], silhouette_budget=False)


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
