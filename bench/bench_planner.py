"""The measured effect planner against full path tracing, at equal error, per scene (built-in and real packs).

For every scene, measured side by side in one run (plan and full interleaved at every sample count):

**(a) An evaluation render** of the scene's object (its starting material) from jittered evaluation cameras: the
plan (:func:`evaluation.views.evaluation_plan`: the pilot's depth, Russian roulette from 5, only the region the
object can change rendered, the rest the background render's of the same seed) and full path tracing (depth 12,
Russian roulette from 5, every pixel). Error: RMS over the frame of the sRGB with-object image against a converged
full render (``--ref-spp``, its own noise subtracted). Seconds: the with-object render (the plan's includes finding
its region; the background render is shared by every input of a scene in both and not counted; the pilot, once
per scene, is listed apart).

**(b) A Stage 1 iteration's loss and gradient** at the run's starting state: the plan (:mod:`optimizer.optimise.
planning`: measured depth, the loss domain's window, the silhouette budget, ``sppi = 0``), ``full`` (what
``--no-planner`` runs: depth 12, Mitsuba's per-pixel silhouette samples, indirect visibility on, full frames) and
``full-lt`` (full light transport with the plan's projective settings: depth 12, ``sppi = 0``, the silhouette
budget, full frames -- it isolates what the measured depth and the window buy). Error: 1 - cosine similarity of the
map gradients (albedo, metallic, roughness, transmittance; blurred by ``--grad-blur`` texels, as the fast preset's
Adam sees them) with a high-spp gradient of full path tracing (prb, depth 12, ``--ref-grad-spp`` x
``--ref-grad-seeds``); the loss' RMS deviation from the reference loss.

Equal-error speed-up: the seconds full tracing takes at the stage's spp (evaluation ``--eval-spp``; training
``--train-spp``) over the seconds the plan takes to reach the same error (log-log interpolation along its curve).
Gradient ratio: the plan's cosine at full tracing's seconds (interpolated) over full tracing's cosine.

With ``--denoisers``, the denoised plan is also measured on the object's own pixels (its coverage in the
with-object render): its bias and noise there beside the whole frame's, and its detail ratio against the reference
(:func:`object_region`): the denoiser smooths what a see-through object shows of the ground behind it.

    python bench/bench_planner.py [--scenes meadow,room] [--real] [--views 4] [--resolution 64] [--out DIR]

Prints Markdown tables and writes ``DIR/bench_planner.json`` (every measured point).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

from optimizer.scenes.bsdf_maps import MAPS

REAL_PACKS = ("sky-duck", "city-cone", "forest-teddy", "dawn-soccerball", "sunset-mug", "venice-duplo",
              "apartment-bunny", "warehouse-tray")


def say(msg: str) -> None:
    import sys

    print(msg, file=sys.stderr, flush=True)


#: The clock of the timed renders and probes (``--clock``): ``cpu`` = this process's CPU seconds (every thread), the
#: fair measure on a shared, oversubscribed machine where wall seconds depend on the other jobs; ``wall`` = elapsed.
CLOCK = {"cpu": time.process_time, "wall": time.perf_counter}
clock = time.process_time


def srgb_rms(a: np.ndarray, b: np.ndarray) -> float:
    from camo_base.imaging import linear_to_srgb

    d = linear_to_srgb(np.clip(a, 0, None)).astype(np.float64) - linear_to_srgb(np.clip(b, 0, None))
    return float(np.sqrt(np.mean(d ** 2)))


def seconds_at(curve: list[tuple[float, float]], error: float) -> float:
    """Seconds a curve ``[(seconds, error), ...]`` (error falling with seconds) needs to reach ``error``
    (log-log interpolation; extrapolated from the last two points beyond the ends)."""
    pts = sorted(curve)
    xs = np.log([p[0] for p in pts])
    ys = np.log([max(p[1], 1e-12) for p in pts])
    y = math.log(max(error, 1e-12))
    if len(pts) == 1:  # one level measured: error as seconds^-0.5 through it
        return float(math.exp(xs[0] + (y - ys[0]) / -0.5))
    for i in range(len(pts) - 1):
        if (ys[i] - y) * (ys[i + 1] - y) <= 0 and ys[i] != ys[i + 1]:
            t = (y - ys[i]) / (ys[i + 1] - ys[i])
            return float(math.exp(xs[i] + t * (xs[i + 1] - xs[i])))
    i = 0 if y > ys[0] else len(pts) - 2
    slope = (ys[i + 1] - ys[i]) / (xs[i + 1] - xs[i]) if xs[i + 1] != xs[i] else -0.5
    slope = slope if slope < 0 else -0.5
    return float(math.exp(xs[i] + (y - ys[i]) / slope))


def value_at(curve: list[tuple[float, float]], seconds: float) -> float:
    """A curve's value at ``seconds`` (linear in log seconds; clamped at the ends)."""
    pts = sorted(curve)
    xs = np.log([p[0] for p in pts])
    return float(np.interp(math.log(seconds), xs, [p[1] for p in pts]))


def real_pack_path(name: str) -> str | None:
    """The pack file of a real scene (data in data/real: ``camo data fetch data_manifests/pmndrs_hdris.toml`` and
    ``registry_objects.toml``): one of :data:`REAL_PACKS` (packs/real, the HDRI-object diagonal of grids/real.toml)
    or ``cross/HDRI-OBJECT`` (packs/real/cross, the 8 x 8 of grids/real_cross.toml); None for other names (a
    built-in scene or a pack path, resolved as ``camo`` resolves them)."""
    real = Path(__file__).resolve().parent.parent / "packs" / "real"
    if name in REAL_PACKS:
        return str(real / f"{name}.toml")
    if name.startswith("cross/"):
        p = real / f"{name}.toml"
        if not p.is_file():
            raise SystemExit(f"no real pack {name!r}: {p} does not exist (packs/real/cross holds HDRI-OBJECT.toml)")
        return str(p)
    return None


def load_pack(name: str, views: int, resolution: int, target_vertices: int):
    from optimizer.scenes.builtin_scenes import resolve_scene

    pack = resolve_scene(real_pack_path(name) or name)
    pack.cameras = dataclasses.replace(pack.cameras, views=views)
    pack.render = dataclasses.replace(pack.render, resolution=(resolution, resolution))
    pack.object = dataclasses.replace(pack.object, target_vertices=target_vertices)
    return pack


# ------------------------------------------------------------------------------------------------------------------
# (a) evaluation render
# ------------------------------------------------------------------------------------------------------------------

class _SharedCache(dict):
    """A ViewRenderer's region cache that gives every background the one dict of the scene (what it holds -- the
    background scene, its compact lights -- does not depend on the seed or spp)."""

    def __init__(self, shared: dict):
        super().__init__()
        self.shared = shared

    def setdefault(self, key, default=None):
        return self.shared


def bench_evaluation(name: str, args) -> dict:
    from evaluation.views import evaluation_cameras, evaluation_plan, render_seed
    from optimizer.rendering.placement import prepare_object, static_object_fn
    from optimizer.rendering.planner import full_plan
    from optimizer.rendering.render import coverage_and_depth, render_shaded, render_with_region
    from optimizer.rendering import scene as scn
    from optimizer.scenes.environments import get_environment

    pack = load_pack(name, args.views, args.resolution, args.target_vertices)
    env = get_environment(pack.environment)
    cams = evaluation_cameras(pack, args.views, seed=args.seed).cams
    mesh_fn = static_object_fn(pack, prepare_object(pack, target_vertices=args.target_vertices))
    t0 = time.perf_counter()
    plan = evaluation_plan(pack, env, cams, args.eval_spp, args.seed, sampler=args.plan_sampler)
    pilot_seconds = time.perf_counter() - t0
    say(f"{name}: evaluation plan max_depth {plan.max_depth} ({pilot_seconds:.1f} s)")
    full = full_plan("evaluate").integrator
    full = dict(full, rr_depth=5)
    integ = plan.integrator
    mesh = mesh_fn()
    sc = scn.build_scene(env.build(), mesh)
    cov = np.stack([coverage_and_depth(sc, c, mesh)[0] for c in cams])
    cache: dict = {}  # what the region renders keep across objects of one scene (the compact lights, the costs)

    def alloc_render(spp, seed, variant):
        """The plan's depth and region, samples allocated per pixel (optimizer/rendering/allocation.py) on the
        per-pixel variances and object floor of ``variant`` (allocation.VARIANTS)."""
        from optimizer.rendering.allocation import VARIANTS

        estimator, object_floor = VARIANTS[variant]
        from optimizer.rendering.allocation import background_groups
        from optimizer.rendering.render import PathRenderer, render_allocated

        # the background and its group means: shared by every input of a scene, not timed
        bg, bg_groups = PathRenderer(env.build(), None, cams, integ, spp, seed)(groups=background_groups(spp))
        t = clock()
        img, reg, alloc = render_allocated(env.build, mesh, cams, integ, spp, seed, bg, bg_groups, cov,
                                           plan.region_threshold, region=plan.region_search and args.region,
                                           noise_floor=args.noise_floor, cache=cache, estimator=estimator,
                                           object_floor=object_floor)
        return img, clock() - t, alloc.to_dict()

    def plan_render(spp, seed, with_background=False, rr_depth=None, sampler=None):
        """The plan's render (``rr_depth``: Russian roulette from that vertex instead of the plan's; ``sampler``:
        that sampler (tracer.SAMPLERS) instead of the plan's; both in the background render too)."""
        it = integ if rr_depth is None else dict(integ, rr_depth=int(rr_depth))
        it = it if sampler is None else dict(it, sampler=sampler)
        bg = render_shaded(env.build(), None, cams, it, spp, seed)  # shared by every input: not timed
        t = clock()
        if not plan.region_search:  # the plan renders whole frames here
            out = render_shaded(env.build(), mesh, cams, it, spp, seed), clock() - t, 1.0, 0
        else:
            img, reg = render_with_region(env.build, mesh, cams, it, spp, seed, bg, cov, plan.region_threshold,
                                          cache=cache)
            out = img, clock() - t, float(reg.masks.mean()), reg.steps
        return (*out, bg) if with_background else out

    from optimizer.rendering.denoise import VARIANTS as denoise_vars, denoise_variant, variant_features
    from optimizer.rendering.region import dilate_px
    from optimizer.rendering.noise import noise_rms

    dens = args.denoisers
    near = np.stack([dilate_px(m, 2) for m in cov >= 0.5])  # the object and a 2-pixel rim (item 4's pixels)
    obj_mask = cov >= 0.5  # the object's own pixels (what a participant searches; the metrics' mask)

    def features(obj, spp, seed):
        """The denoisers' features at min(spp, --aux-spp), the colour's seed, one render per kind the variants use
        (first-hit, see-through): ``{variant: (albedo, normal, seconds)}``, each timed."""
        kinds: dict = {}
        for d in dens:
            kind = (denoise_vars[d].see_through, denoise_vars[d].sharp)
            if kind not in kinds:
                t = clock()
                a, n = variant_features(d, env.build(), obj, cams, min(spp, args.aux_spp), seed)
                kinds[kind] = (a, n, clock() - t)
        return {d: kinds[(denoise_vars[d].see_through, denoise_vars[d].sharp)] for d in dens}

    def denoised(img, feats, variant):
        t = clock()
        out = denoise_variant(img, feats[variant][0], feats[variant][1], variant)
        return out, clock() - t

    def full_render(spp, seed, sampler=None):
        t = clock()
        img = render_shaded(env.build(), mesh, cams, full if sampler is None else dict(full, sampler=sampler), spp,
                            seed)
        return img, clock() - t

    # the evaluation render as `camo evaluate` makes it (evaluation.views.ViewRenderer: region, noise matching, the
    # denoiser and the object's spp factor), each setting "DENOISER:FACTOR" ("off" no denoiser; "auto": the factor
    # the evaluation's pilot chooses, its seconds listed apart)
    from evaluation.views import ViewRenderer, object_spp_pilot

    as_eval: dict[str, tuple[str, int, dict]] = {}
    as_eval_pilots: dict = {}
    for setting in args.evaluate_as:
        d, k, opts = parse_evaluate_as(setting)
        if k == "setting":  # "auto": the whole setting chosen by the evaluation's setting pilot
            from evaluation.views import evaluation_setting_pilot

            pilot = evaluation_setting_pilot(pack, env, cams, plan, args.eval_spp, args.seed, d, mesh_fn,
                                             candidates=opts["candidates"], cost=opts["cost"])
            ch = pilot.pop("setting")
            as_eval_pilots[setting] = {**pilot, "chosen": ch.to_dict() if ch else None,
                                       "wall_seconds": pilot["seconds"]}
            say(f"{name}: setting pilot: {pilot['why']}")
            if ch is None:  # the default: noise matching at the evaluation's spp, no denoiser
                as_eval[setting] = ("", 1, {**opts, "levels": (args.eval_spp,)})
            else:
                if ch.spp not in args.eval_levels:
                    raise SystemExit(f"--evaluate-as {setting}: the pilot chose {ch.spp} spp, not in --eval-levels "
                                     f"{args.eval_levels}")
                as_eval[setting] = (ch.denoise, ch.object_spp, {**opts, "combine": ch.combine,
                                                                "feature_spp": ch.feature_spp,
                                                                "bg_feature_spp": ch.background_feature_spp,
                                                                "levels": (ch.spp,)})
            continue
        if k == "auto":
            pl = dataclasses.replace(plan, denoise=d)
            t = time.perf_counter()
            pilot = object_spp_pilot(pack, env, cams, pl, args.eval_spp, args.seed, True, mesh_fn)
            as_eval_pilots[setting] = {**{a: b for a, b in pilot.items()}, "wall_seconds": time.perf_counter() - t}
            say(f"{name}: object-spp pilot ({d}): {pilot['why']}")
            k = pilot["factor"]
        as_eval[setting] = (d, int(k), opts)

    def eval_render(spp, seed, setting):
        """``(image, seconds, background image, ObjectRenders)``: the with-object render timed, the background
        (shared by every input of a scene, its denoising too) not."""
        d, k, opts = as_eval[setting]
        r = ViewRenderer(spp, args.seed, noise_match=True, sampler_seed=seed, feature_spp=opts.get("bg_feature_spp"))
        r.region_cache = _SharedCache(cache)  # the scene's compact lights: found once, as for plan_render
        it = eval_integrator(integ, opts.get("sampler"))
        bg = r.background(pack, env, cams, it, d)
        t = clock()
        o = r.with_object(env, lambda: mesh, cams, it, bg,
                          plan.region_threshold if plan.region_search else None, object_spp=k,
                          region_min_spp=0 if opts["region"] else None, object_combine=opts["combine"],
                          object_feature_spp=opts["feature_spp"])
        return o.image, clock() - t, bg.image, o

    base = render_seed(args.seed)
    ref, _ = full_render(args.ref_spp, base + 999)
    full_ref, _ = full_render(args.ref_spp, base + 998)  # its distance to ref: twice the reference noise
    plan_ref, _, _, _ = plan_render(args.ref_spp, base + 997)
    ests = args.estimators if args.allocation else []
    alloc_ref = {e: alloc_render(args.ref_spp, base + 996, e)[0] for e in ests}
    ref_var = srgb_rms(full_ref, ref) ** 2 / 2.0
    bias = math.sqrt(max(srgb_rms(plan_ref, ref) ** 2 - srgb_rms(full_ref, ref) ** 2, 0.0))
    den_out: dict = {}
    if dens:  # the denoiser on a converged render: what it changes where there is (almost) no noise left
        f_ref = features(mesh, args.ref_spp, base + 997)
        for d in dens:
            den_out[d] = {"bias_at_ref_spp": math.sqrt(max(srgb_rms(denoised(plan_ref, f_ref, d)[0], ref) ** 2
                                                           - srgb_rms(full_ref, ref) ** 2, 0.0))}
    at_spp: dict = {"plan": [], "bg": [], **{d: [] for d in dens}, **{f"bg-{d}": [] for d in dens},
                    **{f"eval-{e}": [] for e in as_eval}, **{f"eval-bg-{e}": [] for e in as_eval}}
    rows = []
    by_level: dict = {}  # (setting, spp) -> [(with-object, background)] of each repetition (its own seed)
    for spp in args.eval_levels:
        for k in range(args.warmup):  # untimed: the JIT compiles of this spp's kernels (a render at a new spp, a
            plan_render(spp, base + k)  # region's growth steps: each a kernel of its own), paid once per scene
            full_render(spp, base + k)
            for e in ests:
                alloc_render(spp, base + k, e)
            for rr in args.rr_depths:
                plan_render(spp, base + k, rr_depth=rr)
            if args.whole_frames:
                render_shaded(env.build(), mesh, cams, integ, spp, base + k)
            for smp in args.samplers:
                plan_render(spp, base + k, sampler=smp)
                if smp != "independent":
                    full_render(spp, base + k, sampler=smp)
                for rr in args.rr_depths:
                    plan_render(spp, base + k, rr_depth=rr, sampler=smp)
            for e in as_eval:
                if measured_at(as_eval[e], spp):
                    eval_render(spp, base + k, e)
            if dens:
                w_img = plan_render(spp, base + k)[0]
                fw = features(mesh, spp, base + k)
                features(None, spp, base + k)
                for d in dens:
                    denoised(w_img, fw, d)
        for rep in range(args.reps):
            seed = base + 17 * spp + rep
            p_img, p_s, share, steps, p_bg = plan_render(spp, seed, with_background=True)
            f_img, f_s = full_render(spp, seed)
            row = {"spp": spp, "rep": rep, "plan_seconds": p_s, "full_seconds": f_s, "region_share": share,
                   "region_launches": steps}
            for rr in args.rr_depths:
                r_img, r_s = plan_render(spp, seed, rr_depth=rr)[:2]
                row[f"plan-rr{rr}_seconds"] = r_s
                row[f"plan-rr{rr}_error"] = math.sqrt(max(srgb_rms(r_img, ref) ** 2 - ref_var, 0.0))
            if args.whole_frames:  # the plan's integrator on every pixel: what its region render buys
                t_ = clock()
                w_img = render_shaded(env.build(), mesh, cams, integ, spp, seed)
                row["plan-whole_seconds"] = clock() - t_
                row["plan-whole_error"] = math.sqrt(max(srgb_rms(w_img, ref) ** 2 - ref_var, 0.0))
            for smp in args.samplers:  # the plan and full tracing with another sampler than their own, interleaved
                for who, (img_, s_) in (((f"plan-{smp}", plan_render(spp, seed, sampler=smp)[:2]),)
                                        if smp != integ.get("sampler", "independent") else ()) + \
                                       (((f"full-{smp}", full_render(spp, seed, sampler=smp)),)
                                        if smp != "independent" else ()):
                    row[f"{who}_seconds"] = s_
                    row[f"{who}_error"] = math.sqrt(max(srgb_rms(img_, ref) ** 2 - ref_var, 0.0))
                for rr in args.rr_depths:
                    r_img, r_s = plan_render(spp, seed, rr_depth=rr, sampler=smp)[:2]
                    row[f"plan-{smp}-rr{rr}_seconds"] = r_s
                    row[f"plan-{smp}-rr{rr}_error"] = math.sqrt(max(srgb_rms(r_img, ref) ** 2 - ref_var, 0.0))
            if dens:
                fe = features(mesh, spp, seed)
                bg_fe = features(None, spp, seed) if spp == args.eval_spp else None  # shared: not timed
                for d in dens:
                    for who, img, s_ in (("plan", p_img, p_s), ("full", f_img, f_s)):
                        out, d_s = denoised(img, fe, d)
                        row[f"{d}_features_seconds"] = fe[d][2]
                        row[f"{who}+{d}_seconds"] = s_ + fe[d][2] + d_s
                        row[f"{who}+{d}_error"] = math.sqrt(max(srgb_rms(out, ref) ** 2 - ref_var, 0.0))
                        row[f"{who}+{d}_denoise_seconds"] = d_s
                        if who == "plan" and spp == args.eval_spp:
                            at_spp[d].append(out)
                            at_spp[f"bg-{d}"].append(denoised(p_bg, bg_fe, d)[0])
            for e in as_eval:
                if not measured_at(as_eval[e], spp):
                    continue
                e_img, e_s, e_bg, e_o = eval_render(spp, seed, e)
                row[f"eval-{e}_seconds"] = e_s
                row[f"eval-{e}_error"] = math.sqrt(max(srgb_rms(e_img, ref) ** 2 - ref_var, 0.0))
                row[f"eval-{e}_extra_samples"] = e_o.noise.extra_samples if e_o.noise is not None else 0.0
                row[f"eval-{e}_denoise_seconds"] = e_o.denoise_seconds
                by_level.setdefault((e, spp), []).append((e_img, e_bg))
                if spp == args.eval_spp:
                    at_spp[f"eval-{e}"].append(e_img)
                    at_spp[f"eval-bg-{e}"].append(e_bg)
            if spp == args.eval_spp:
                at_spp["plan"].append(p_img)
                at_spp["bg"].append(p_bg)
            for e in ests:
                a_img, a_s, a_stats = alloc_render(spp, seed, e)
                row.update({f"alloc-{e}": a_stats, f"alloc-{e}_seconds": a_s,
                            f"alloc-{e}_error": math.sqrt(max(srgb_rms(a_img, ref) ** 2 - ref_var, 0.0))})
            rows.append({**row,
                         "plan_error": math.sqrt(max(srgb_rms(p_img, ref) ** 2 - ref_var, 0.0)),
                         "full_error": math.sqrt(max(srgb_rms(f_img, ref) ** 2 - ref_var, 0.0))})
    plan_curve = _mean_curve(rows, "plan")
    full_curve = _mean_curve(rows, "full")
    s = args.eval_spp
    t_full = value_at([(k, v[0]) for k, v in _by_spp(rows, "full").items()], s)
    e_full = math.exp(value_at([(k, math.log(v[1])) for k, v in _by_spp(rows, "full").items()], s))
    t_plan = seconds_at(plan_curve, e_full)
    e_plan_at_s = math.exp(value_at([(k, math.log(v[1])) for k, v in _by_spp(rows, "plan").items()], s))
    top = max(args.eval_levels)
    equal_spp = _by_spp(rows, "full")[top][0] / _by_spp(rows, "plan")[top][0]
    allocs = {}
    for est in ests:
        who = f"alloc-{est}"
        timed = [r[who] for r in rows if r["spp"] == s]
        a_curve = _mean_curve(rows, who)
        a_t = seconds_at(a_curve, e_full)
        allocs[est] = {"estimator": est, "samples_share": float(np.mean([a["samples_share"] for a in timed])),
                 "control_variate_share": float(np.mean([a["control_variate_share"] for a in timed])),
                 "floor_share": float(np.mean([a["floor_share"] for a in timed])),
                 "costs": cache.get("costs"), "costs_seconds": cache.get("costs_seconds", 0.0),
                 "seconds_at_equal_error": a_t, "speedup": t_full / a_t,
                 "speedup_equal_spp": _by_spp(rows, "full")[top][0] / _by_spp(rows, who)[top][0],
                 "error_at_spp": math.exp(value_at([(k, math.log(v[1])) for k, v in _by_spp(rows, who).items()], s)),
                 "bias": math.sqrt(max(srgb_rms(alloc_ref[est], ref) ** 2 - srgb_rms(full_ref, ref) ** 2, 0.0)),
                 "curve": a_curve, "noise_floor": args.noise_floor}
    for d in dens:  # the denoised plan: its curve, speed-up, bias at the stage's spp, noise around the object
        who = f"plan+{d}"
        d_curve = _mean_curve(rows, who)
        d_t = seconds_at(d_curve, e_full)
        imgs = at_spp[d]
        mean_bias = float("nan")
        if len(imgs) >= 2:  # bias^2 = |mean - ref|^2 - var/K - ref noise, var from the spread of the K seeds
            from camo_base.imaging import linear_to_srgb

            e = [linear_to_srgb(np.clip(x, 0, None)).astype(np.float64) for x in imgs]
            m = np.mean(e, axis=0)
            var = float(np.mean(np.var(e, axis=0, ddof=1)))
            r_ = linear_to_srgb(np.clip(ref, 0, None)).astype(np.float64)
            mean_bias = math.sqrt(max(float(np.mean((m - r_) ** 2)) - var / len(e) - ref_var, 0.0))
        noise = {}
        if len(imgs) >= 2:
            noise = {"object": noise_rms(imgs[0], imgs[1], near), "background": noise_rms(
                at_spp[f"bg-{d}"][0], at_spp[f"bg-{d}"][1], near)}
        on_object = {"denoised": object_region(imgs, ref, full_ref, obj_mask),
                     "plan": object_region(at_spp["plan"], ref, full_ref, obj_mask)}
        den_out[d].update({
            "curve": d_curve, "seconds_at_equal_error": d_t, "speedup": t_full / d_t,
            "speedup_equal_spp": _by_spp(rows, "full")[top][0] / _by_spp(rows, who)[top][0],
            "error_at_spp": math.exp(value_at([(k, math.log(v[1])) for k, v in _by_spp(rows, who).items()], s)),
            "full_denoised_error_at_spp": math.exp(value_at(
                [(k, math.log(v[1])) for k, v in _by_spp(rows, f"full+{d}").items()], s)),
            "full_denoised_speedup": t_full / seconds_at(_mean_curve(rows, f"full+{d}"), e_full),
            "full_curve": _mean_curve(rows, f"full+{d}"),
            "bias_at_spp": mean_bias, "seeds_at_spp": len(imgs), "noise_near_object": noise, "object": on_object,
            "features_seconds": float(np.min([r[f"{d}_features_seconds"] for r in rows if r["spp"] == s])),
            "denoise_seconds": float(np.min([r[f"{who}_denoise_seconds"] for r in rows if r["spp"] == s]))})
    eval_out = {}
    for e, (d, k, opts) in as_eval.items():
        who = f"eval-{e}"
        e_t = seconds_at(_mean_curve(rows, who), e_full)
        imgs, bgs = at_spp[who], at_spp[f"eval-bg-{e}"]
        by_spp = _by_spp(rows, who)
        # the noise near the object at every level (two seeds: the first two repetitions), and at the level where
        # the setting reaches full tracing's error (the first level at or below it; the cheapest if all are): the
        # speed-up is read there, so the noise it would show is judged there too, not only at --eval-spp
        noise_lv = {str(lv): {"object": noise_rms(x[0][0], x[1][0], near), "background": noise_rms(x[0][1], x[1][1],
                                                                                                    near)}
                    for (e_, lv), x in by_level.items() if e_ == e and len(x) >= 2}
        below = [lv for lv, (_, err) in sorted(by_spp.items()) if err <= e_full]
        eq_level = below[0] if below else None
        eval_out[e] = {"denoise": d, "object_spp": k, "pilot": as_eval_pilots.get(e), "curve": _mean_curve(rows, who),
                       "seconds_at_equal_error": e_t, "speedup": t_full / e_t,
                       "seconds_at_spp": value_at([(k_, v[0]) for k_, v in _by_spp(rows, who).items()], s),
                       "error_at_spp": math.exp(value_at([(k_, math.log(v[1])) for k_, v in
                                                          _by_spp(rows, who).items()], s)),
                       "extra_samples": float(np.mean([r[f"{who}_extra_samples"] for r in rows if r["spp"] == s]))
                       if s in by_spp else float("nan"),
                       "extra_samples_by_spp": {str(lv): float(np.mean([r[f"{who}_extra_samples"] for r in rows
                                                                        if r["spp"] == lv and f"{who}_seconds" in r]))
                                                for lv in by_spp},
                       "levels": sorted(by_spp), "region_any_spp": opts["region"], "combine": opts["combine"],
                       "feature_spp": opts["feature_spp"], "bg_feature_spp": opts.get("bg_feature_spp"),
                       "sampler": eval_integrator(integ, opts.get("sampler")).get("sampler", "independent"),
                       "noise_near_object": ({"object": noise_rms(imgs[0], imgs[1], near),
                                              "background": noise_rms(bgs[0], bgs[1], near)} if len(imgs) >= 2
                                             else {}),
                       "noise_by_spp": noise_lv, "equal_error_level": eq_level}
    rr_out = {}
    for rr in args.rr_depths:
        who = f"plan-rr{rr}"
        r_t = seconds_at(_mean_curve(rows, who), e_full)
        rr_out[str(rr)] = {"curve": _mean_curve(rows, who), "seconds_at_equal_error": r_t, "speedup": t_full / r_t,
                           "speedup_equal_spp": _by_spp(rows, "full")[top][0] / _by_spp(rows, who)[top][0],
                           "error_at_spp": math.exp(value_at([(k, math.log(v[1])) for k, v in
                                                              _by_spp(rows, who).items()], s))}
    variants = {}  # every other measured curve (--rr-depths, --samplers): its speed-up against full tracing
    for who in sorted({k[:-len("_seconds")] for r in rows for k in r if k.endswith("_seconds")
                       and k[:-len("_seconds")] + "_error" in r and k.startswith(("plan-", "full-"))}):
        v_t = seconds_at(_mean_curve(rows, who), e_full)
        variants[who] = {"curve": _mean_curve(rows, who), "seconds_at_equal_error": v_t, "speedup": t_full / v_t,
                         "speedup_equal_spp": _by_spp(rows, "full")[top][0] / _by_spp(rows, who)[top][0],
                         "error_at_spp": math.exp(value_at([(k, math.log(v[1])) for k, v in
                                                            _by_spp(rows, who).items()], s))}
    plain_noise = ({"object": noise_rms(at_spp["plan"][0], at_spp["plan"][1], near),
                    "background": noise_rms(at_spp["bg"][0], at_spp["bg"][1], near)}
                   if len(at_spp["plan"]) >= 2 else {})
    return {"scene": name, "pilot_seconds": pilot_seconds, "allocations": allocs, "denoisers": den_out,
            "evaluate_as": eval_out,
            "rr_depths": rr_out, "variants": variants, "plan_sampler": integ.get("sampler", "independent"),
            "plan_integrator": dict(integ),
            "noise_near_object": plain_noise,
            "region_search": bool(plan.region_search), "max_depth": plan.max_depth, "rr_depth": plan.rr_depth,
            "region_share": float(np.mean([r["region_share"] for r in rows])), "bias": bias,
            "noise_at_spp": e_plan_at_s, "full_error_at_spp": e_full, "full_seconds_at_spp": t_full,
            "plan_seconds_at_equal_error": t_plan, "speedup": t_full / t_plan, "rows": rows,
            "top_spp": top, "speedup_equal_spp": equal_spp,
            "region_launches": float(np.mean([r["region_launches"] for r in rows])),
            "plan_curve": plan_curve, "full_curve": full_curve,
            "effects": [e.to_dict() for e in plan.effects]}


def parse_evaluate_as(setting: str) -> tuple[str, int | str, dict]:
    """``DENOISER:FACTOR[:OPTION...][@LEVEL/LEVEL...]`` or ``auto[:DENOISER]`` (``--evaluate-as``) -> ``(denoiser or
    "", factor or "auto",
    {"region": bool, "combine": str, "levels": tuple of spp or None})``. Options: ``region`` renders only the region
    the object can change at every spp (``ViewRenderer.with_object(region_min_spp=0)``; by default whole frames
    below :data:`optimizer.rendering.planner.REGION_MIN_SPP`); ``max``: the object's factor and noise matching's
    combined by their larger (``object_combine="max"``; default their product); ``fN``: the with-object render's
    denoiser features at N spp (``object_feature_spp``; see-through features: on the object's box only; default the
    background's, min(spp, 16)); ``bN``: the background's denoiser features at N spp (``ViewRenderer(feature_spp=N)``;
    the with-object render's too unless ``fN``; the background is shared by every input of a scene, so not timed); a
    sampler's name (:data:`optimizer.rendering.tracer.SAMPLERS`, e.g. ``sobol``): both renders with that sampler
    instead of the plan's (as ``camo evaluate --sampler``; default the plan's, ``--plan-sampler``).
    ``@LEVELS``: measure the setting at these of ``--eval-levels`` only (a setting with a large factor at 64 spp costs
    minutes and is never read there).
    ``auto[:DENOISER[:SET]]`` (denoiser default ``oidn-through``): the whole setting (factor, rule, feature spp, spp
    level) chosen per scene by :func:`evaluation.views.evaluation_setting_pilot`, returned as ``(denoiser, "setting",
    options)``; ``SET`` ``coarse``: the pilot as it was before the 6-spp level and the cost model (levels 4 and 8,
    :data:`evaluation.views.SETTING_CANDIDATES_COARSE`, candidates ranked by their measured CPU seconds).
    Raises ``ValueError`` with a one-line reason."""
    if setting == "auto" or setting.startswith("auto:"):
        d, _, cset = setting.partition(":")[2].partition(":")
        d = d or "oidn-through"
        from optimizer.rendering.denoise import VARIANTS as DENOISERS

        if d not in DENOISERS:
            raise ValueError(f"{setting!r}: denoiser {d!r} is not one of {', '.join(DENOISERS)}")
        if cset not in ("", "coarse"):
            raise ValueError(f"{setting!r}: candidate set {cset!r} is not coarse (or absent)")
        return d, "setting", {"region": False, "combine": "product", "feature_spp": None, "bg_feature_spp": None,
                              "levels": None, "candidates": cset or "default",
                              "cost": "measured" if cset == "coarse" else "model"}
    head, _, lv = setting.partition("@")
    d, _, rest = head.partition(":")
    k, *flags = rest.split(":") if rest else ["1"]
    from optimizer.rendering.denoise import VARIANTS as DENOISERS
    from optimizer.rendering.tracer import SAMPLERS

    if d != "off" and d not in DENOISERS:
        raise ValueError(f"{setting!r}: denoiser {d!r} is not off or one of {', '.join(DENOISERS)}")
    if not (k == "auto" or (k.isdigit() and int(k) >= 1)):
        raise ValueError(f"{setting!r}: FACTOR {k!r} is not an integer >= 1 or auto")
    feature_spp = bg_feature_spp = None
    for f in flags:
        if f.startswith("f") and f[1:].isdigit() and int(f[1:]) >= 1:
            feature_spp = int(f[1:])
        elif f.startswith("b") and f[1:].isdigit() and int(f[1:]) >= 1:
            bg_feature_spp = int(f[1:])
        elif f not in ("region", "max") and f not in SAMPLERS:
            raise ValueError(f"{setting!r}: unknown option {f!r} (region, max, fN, bN, {', '.join(SAMPLERS)})")
    try:
        levels = tuple(int(x) for x in lv.split("/")) if lv else None
    except ValueError:
        raise ValueError(f"{setting!r}: levels {lv!r} are not spp separated by /") from None
    return ("" if d == "off" else d, k if k == "auto" else int(k),
            {"region": "region" in flags, "combine": "max" if "max" in flags else "product",
             "feature_spp": feature_spp, "bg_feature_spp": bg_feature_spp, "levels": levels,
             "sampler": next((f for f in flags if f in SAMPLERS), None)})


def eval_integrator(integrator: dict, sampler: str | None) -> dict:
    """``integrator`` with ``sampler`` (None: as it is; ``independent``: without the key, as the default plan's)."""
    if sampler is None:
        return integrator
    out = {k: v for k, v in integrator.items() if k != "sampler"}
    return out if sampler == "independent" else dict(out, sampler=sampler)


def measured_at(setting: tuple, spp: int) -> bool:
    """Whether a parsed ``--evaluate-as`` setting ``(denoiser, factor, options)`` is measured at ``spp``."""
    lv = setting[2]["levels"]
    return lv is None or spp in lv


def object_region(imgs: list[np.ndarray], ref: np.ndarray, ref2: np.ndarray, mask: np.ndarray) -> dict:
    """What the seeds ``imgs`` (V, H, W, 3 linear, >= 2) of a render do to the object's pixels ``mask`` (V, H, W)
    against the converged reference ``ref`` (``ref2``: a second one, for its noise), all in sRGB /1:

    ``bias``: RMS over the mask of the seeds' mean minus the reference, the seeds' spread (/K) and the reference's
    noise subtracted; ``noise``: one seed's RMS deviation from the seeds' mean over the mask (ddof 1);
    ``detail``: mean over seeds and views of :func:`evaluation.metrics.detail_ratio.detail_ratio` of the render
    against the reference in the mask (1 = the reference's texture energy, < 1 smoothed, > 1 speckle: noise adds
    to it). The reference has noise of its own on a see-through object (its caustics converge slowly), which adds
    to its texture energy: ``ref_detail_2x`` is the detail of the two references' mean (twice the spp) against
    ``ref``, and ``converged`` its extrapolation to infinite spp, ``sqrt(2 d^2 - 1)`` (the reference's Laplacian
    energy = texture + noise / spp, the detail ratio taken as its square root), so that ``detail / converged`` is
    the render's detail against the converged render's. NaNs where fewer than two seeds or no mask."""
    from camo_base.imaging import linear_to_srgb
    from evaluation.metrics.detail_ratio import detail_ratio

    nan = {"bias": float("nan"), "noise": float("nan"), "detail": float("nan"), "pixels": int(mask.sum())}
    if len(imgs) < 2 or not mask.any():
        return nan
    e = np.stack([linear_to_srgb(np.clip(x, 0, None)).astype(np.float64) for x in imgs])  # (K, V, H, W, 3)
    r_ = linear_to_srgb(np.clip(ref, 0, None)).astype(np.float64)
    r2 = linear_to_srgb(np.clip(ref2, 0, None)).astype(np.float64)
    m = e.mean(0)
    var = float(np.mean(np.var(e, axis=0, ddof=1)[mask]))
    ref_var = float(np.mean((r2 - r_)[mask] ** 2)) / 2.0
    bias = math.sqrt(max(float(np.mean((m - r_)[mask] ** 2)) - var / len(e) - ref_var, 0.0))
    det = [float(detail_ratio(np.clip(x[v], 0, 1).astype(np.float32), np.clip(r_[v], 0, 1).astype(np.float32),
                              mask[v]))
           for x in e for v in range(len(mask)) if mask[v].any()]
    det = [x for x in det if math.isfinite(x)]
    both = linear_to_srgb(np.clip((ref + ref2) / 2, 0, None)).astype(np.float64)
    d2 = [float(detail_ratio(np.clip(both[v], 0, 1).astype(np.float32), np.clip(r_[v], 0, 1).astype(np.float32),
                             mask[v])) for v in range(len(mask)) if mask[v].any()]
    d2 = float(np.mean([x for x in d2 if math.isfinite(x)] or [float("nan")]))
    return {"bias": bias, "noise": math.sqrt(var), "detail": float(np.mean(det)) if det else float("nan"),
            "pixels": int(mask.sum()), "ref_detail_2x": d2, "converged": math.sqrt(max(2 * d2 ** 2 - 1, 1e-6))}


def clamped_seconds(curve: list[tuple[float, float]], error: float, seconds: float) -> tuple[float, bool]:
    """``seconds`` (a curve's seconds at ``error``, :func:`seconds_at`) kept within the measured levels: where the
    curve's cheapest level is already below ``error`` its seconds are taken (the speed-up then a lower bound,
    ``True``) rather than an extrapolation below the levels measured."""
    first = min(curve)
    if first[1] <= error and seconds < first[0]:
        return first[0], True
    return seconds, False


def _by_spp(rows, who):
    """``{spp: (seconds, error)}``: the least seconds of the repetitions (what the render costs undisturbed: on a
    shared machine a repetition can be slowed several-fold by other jobs, CPU seconds included, as threads spin
    waiting for a core) and the mean error."""
    out = {}
    for spp in sorted({r["spp"] for r in rows}):
        rs = [r for r in rows if r["spp"] == spp and f"{who}_seconds" in r]
        if not rs:  # a setting measured at some levels only (--evaluate-as ...@LEVELS)
            continue
        out[spp] = (float(np.min([r[f"{who}_seconds"] for r in rs])), float(np.mean([r[f"{who}_error"] for r in rs])))
    return out


def _mean_curve(rows, who):
    return [v for _, v in sorted(_by_spp(rows, who).items())]


# ------------------------------------------------------------------------------------------------------------------
# (b) Stage 1 loss and gradient
# ------------------------------------------------------------------------------------------------------------------

def bench_gradient(name: str, args) -> dict:
    args = argparse.Namespace(**{**vars(args), "views": args.grad_views, "resolution": args.grad_resolution})
    from optimizer.optimise.planning import measure_plan
    from optimizer.optimise.stage1 import Stage1, Stage1Config
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.rendering.placement import prepare_object
    from optimizer.rendering.planner import Plan, full_plan
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment

    pack = load_pack(name, args.views, args.resolution, args.target_vertices)
    env = get_environment(pack.environment)
    prepared = prepare_object(pack, target_vertices=args.target_vertices)
    cams = cameras(pack)
    app = AppearanceConfig(map_resolution=args.map_resolution, displacement_resolution=args.map_resolution // 2)
    t0 = time.perf_counter()
    plan = measure_plan(pack, env, prepared, cams, app, args.seed,
                        {"training": args.train_spp, "targets": args.target_spp})
    pilot_seconds = time.perf_counter() - t0
    say(f"{name}: training plan max_depth {plan.max_depth} ({pilot_seconds:.1f} s)")
    full = full_plan("optimize", geometry=True)
    full.integrator = dict(full.integrator, rr_depth=5)
    full_lt = dataclasses.replace(plan, integrator={"type": "prb_projective", "max_depth": 12, "rr_depth": 5, "sppi": 0},
                                  max_depth=12, region=False)
    ref_plan = Plan({"type": "prb", "max_depth": 12, "rr_depth": 5}, False, 12, "", [], rr_depth=5)
    base_cfg = Stage1Config(spp=args.train_spp, target_spp=args.target_spp, seed=args.seed)
    # the targets (background, domain) once, rendered with the plan's depth as a run would
    first = Stage1(pack, env, prepared, cams, plan, base_cfg, app).prepare()
    targets, values = first.targets, first.current_values()

    def stage(pl: Plan, spp: int) -> Stage1:
        return Stage1(pack, env, prepared, cams, pl, dataclasses.replace(base_cfg, spp=spp), app,
                      initial=values).prepare(targets=targets)

    def maps_vector(g: dict[str, np.ndarray]) -> np.ndarray:
        # as Adam sees them in the fast preset: blurred by --grad-blur texels (AppearanceConfig.grad_blur)
        from scipy.ndimage import gaussian_filter

        return np.concatenate([gaussian_filter(g[k].astype(np.float64), (args.grad_blur, args.grad_blur, 0)).ravel()
                               for k in MAPS if k in g])

    def probe(s1: Stage1, k: int) -> tuple[float, np.ndarray, float]:
        s1.iteration = k
        t = clock()
        loss, g = s1.gradient()
        return loss, maps_vector(g), clock() - t

    ref_stage = stage(ref_plan, args.ref_grad_spp)
    probe(ref_stage, 10_000)  # compile
    ref_sum, ref_losses = None, []
    for k in range(args.ref_grad_seeds):
        loss, g, _ = probe(ref_stage, 20_000 + k)
        ref_sum = g if ref_sum is None else ref_sum + g
        ref_losses.append(loss)
    ref_g = ref_sum / args.ref_grad_seeds
    ref_loss = float(np.mean(ref_losses))

    def cosine(g):
        n = np.linalg.norm(g) * np.linalg.norm(ref_g)
        return float(g @ ref_g / n) if n > 0 else 0.0

    kinds = {"plan": plan, "full-lt": full_lt, "full": full}
    rows = []
    stages = {}
    warm = {}
    for spp in args.train_levels:
        for who, pl in kinds.items():
            if who == "full" and spp not in args.full_levels:
                continue
            stages[(who, spp)] = st = stage(pl, spp)
            # untimed: the JIT compiles of every view's kernels, including each view's silhouette pass (it runs
            # on a random 1/4 of the views per step, and a windowed view's costs ~8 CPU s the first time)
            t = clock()
            its = warmup_iterations(st, args.warmup, 30_000)
            for k in its:
                probe(st, k)
            warm[f"{who}@{spp}"] = {"probes": len(its), "seconds": clock() - t}
    # untimed again, once per setting in the timed order: a setting's first probe after the other settings' warm-up
    # compiled its kernels again (meadow, 4 views at 64 px: 21-24 CPU s against 3.2-4.5, kernel history shows the
    # codegen; the cause is not found), and after that switching between settings compiled nothing
    for (who, spp), st in stages.items():
        t = clock()
        probe(st, 35_000)
        warm[f"{who}@{spp}"]["settle"] = clock() - t
    for spp in args.train_levels:
        for rep in range(args.reps):
            for who in kinds:
                if (who, spp) not in stages:
                    continue
                loss, g, secs = probe(stages[(who, spp)], 40_000 + 97 * spp + rep)
                rows.append({"who": who, "spp": spp, "rep": rep, "seconds": secs, "cosine": cosine(g),
                             "loss_error": abs(loss - ref_loss)})
    out = {"scene": name, "pilot_seconds": pilot_seconds, "max_depth": plan.max_depth, "ref_loss": ref_loss,
           "window_share": float(np.mean([(b[2] - b[0]) * (b[3] - b[1]) / (args.resolution ** 2)
                                          for b in first.windows])) if first.windows else 1.0,
           "rows": rows, "warmup": warm}
    return summarise_gradient(out, args.train_spp, list(kinds))


def warmup_iterations(s1, n: int, start: int) -> list[int]:
    """The untimed warm-up probes' iteration numbers for Stage 1 ``s1``: ``n`` of them from ``start``, more until
    every view has had its primary-silhouette pass (:func:`optimizer.rendering.projective.silhouette_view_weights`
    picks a random ``1 / silhouette_every`` of the views per iteration). Timing before that times the JIT: a step
    whose silhouette view is new cost ~8 CPU s more when each view rendered its own window (a kernel per crop
    window), once per view and run (meadow, 4 views at 64 px, 4 spp: 9-10 against 1.3-1.5 CPU s); the views now
    share one window and its kernels, and a new silhouette view compiles only a few small kernels (0.2-0.7 s)."""
    from optimizer.rendering.projective import silhouette_view_weights

    its = list(range(start, start + max(int(n), 0)))
    integ = s1.scene.integrator()
    if not hasattr(integ, "silhouette_views"):
        return its
    ids = [s.id() for s in s1.scene.sensors()]
    views = s1.views_for_step()
    seen = set()
    for k in its:
        w = silhouette_view_weights([ids[v] for v in views], s1.cfg.silhouette_every, k, s1.cfg.seed)
        seen |= set(w) if w is not None else set(ids)
    k = start + len(its)
    while not {ids[v] for v in views} <= seen and k < start + 64 * len(views):
        w = silhouette_view_weights([ids[v] for v in views], s1.cfg.silhouette_every, k, s1.cfg.seed)
        if w is None or not set(w) <= seen:
            its.append(k)
            seen |= set(w) if w is not None else set(ids)
        k += 1
    return its


def summarise_gradient(out: dict, train_spp: int, kinds=("plan", "full-lt", "full")) -> dict:
    """The gradient figures of one scene from its measured ``out["rows"]`` (also run by ``--tables`` on a saved
    JSON).

    A Stage 1 step's seconds are ``a + b spp`` (a fixed part -- the loss, the AD graph, the silhouette pass, the
    launches -- that dominates at small sizes: at 32 px a step takes about the same seconds at 1 and 8 spp), so
    each setting's seconds are fitted by that line over its spp levels (least seconds of the repetitions per level),
    and its cosine is interpolated in log spp (mean of the repetitions). Equal seconds: the plan's cosine at the spp
    its line affords in full tracing's seconds at ``train_spp`` (clamped to the measured levels: ``clamped``);
    equal cosine: the plan's seconds (its line) at the smallest spp whose cosine reaches full tracing's."""
    rows = out["rows"]
    curves = {}
    for who in kinds:
        pts = {}
        for r in rows:
            if r["who"] == who:
                pts.setdefault(r["spp"], []).append(r)
        curves[who] = {spp: (float(np.min([r["seconds"] for r in rs])), float(np.mean([r["cosine"] for r in rs])),
                             float(np.sqrt(np.mean([r["loss_error"] ** 2 for r in rs]))))
                       for spp, rs in sorted(pts.items())}
    out["curves"] = {w: {str(k): v for k, v in c.items()} for w, c in curves.items()}
    plan = curves.get("plan", {})
    if len(plan) < 2:
        return out
    spps = np.array(sorted(plan), float)
    secs = np.array([plan[k][0] for k in sorted(plan)])
    cos = np.array([plan[k][1] for k in sorted(plan)])
    slope, icept = np.polyfit(spps, secs, 1)
    slope = max(float(slope), 1e-9)
    out["plan_seconds_fit"] = {"fixed": float(icept), "per_spp": slope}
    for who in ("full", "full-lt"):
        c = curves.get(who, {})
        if train_spp not in c:
            continue
        t_f, cos_f, loss_f = c[train_spp]
        s_aff = (t_f - icept) / slope
        clamped = not (spps[0] <= s_aff <= spps[-1])
        s_aff = float(np.clip(s_aff, spps[0], spps[-1]))
        cos_p = float(np.interp(math.log2(s_aff), np.log2(spps), cos))
        reach = [k for k in range(len(spps)) if cos[k] >= cos_f]
        if reach and reach[0] > 0:
            k = reach[0]  # first level at or above full's cosine: interpolate the spp between it and the one before
            t = (cos_f - cos[k - 1]) / max(cos[k] - cos[k - 1], 1e-12)
            s_eq = float(2 ** (math.log2(spps[k - 1]) + t * (math.log2(spps[k]) - math.log2(spps[k - 1]))))
        elif reach:
            s_eq = float(spps[0])
        else:
            s_eq = float("nan")  # never reached within the measured levels
        t_p = icept + slope * s_eq
        eq = {}
        if train_spp in plan:  # at equal spp: what "equal seconds" is where a step's seconds do not grow with spp
            eq = {"cosine_ratio_equal_spp": plan[train_spp][1] / cos_f if cos_f > 0 else float("nan"),
                  "seconds_ratio_equal_spp": plan[train_spp][0] / t_f}
        out[who] = {**eq, "seconds_at_spp": t_f, "cosine_at_spp": cos_f, "loss_error_at_spp": loss_f,
                    "plan_spp_at_same_seconds": s_aff, "clamped": clamped,
                    "plan_seconds_at_equal_cosine": t_p, "speedup": t_f / t_p if t_p == t_p else float("nan"),
                    "plan_cosine_at_same_seconds": cos_p,
                    "cosine_ratio": cos_p / cos_f if cos_f > 0 else float("nan")}
    if train_spp in plan:
        out["plan_at_spp"] = {"seconds": plan[train_spp][0], "cosine": plan[train_spp][1],
                              "loss_error": plan[train_spp][2]}
    return out


# ------------------------------------------------------------------------------------------------------------------

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="", help="comma list (default: the six built-in scenes); also real packs: "
                    f"{', '.join(REAL_PACKS)}, or cross/HDRI-OBJECT (packs/real/cross), or a pack path")
    ap.add_argument("--real", action="store_true", help="also the real packs (packs/real, data in data/real)")
    ap.add_argument("--only", choices=("eval", "grad", "both"), default="both")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--target-vertices", type=int, default=8000)
    ap.add_argument("--map-resolution", type=int, default=128)
    ap.add_argument("--eval-spp", type=int, default=64, help="the evaluation's spp (equal error is taken there)")
    ap.add_argument("--eval-levels", default="16,32,64,128,256")
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--allocation", action="store_true", help="also the plan with per-pixel sample allocation "
                    "(optimizer/rendering/allocation.py: the background as a control variate), interleaved")
    ap.add_argument("--estimators", default="sturdy-floor", help="with the allocation: comma list of its variants "
                    "(per-pixel variance estimate, object floor), each measured interleaved (optimizer/rendering/"
                    "allocation.py VARIANTS: local, sturdy, sturdy-floor)")
    ap.add_argument("--denoisers", default="", help="also the plan and full tracing denoised by Open Image Denoise "
                    "(comma list of optimizer/rendering/denoise.py VARIANTS: oidn, oidn-balanced, oidn-raw, "
                    "oidn-through, oidn-through-sharp, oidn-color), interleaved; the features' render (one per kind: "
                    "first-hit, see-through, see-through sharp) and the denoising are timed")
    ap.add_argument("--samplers", default="", help="also the plan and full tracing with these samplers "
                    "(optimizer/rendering/tracer.py SAMPLERS, e.g. sobol), interleaved; with --rr-depths the plan "
                    "with both")
    ap.add_argument("--plan-sampler", default=None, help="the evaluation plan's sampler (tracer.SAMPLERS; default "
                    "the planner's EVALUATION_SAMPLER): e.g. sobol, to measure it as camo evaluate renders it "
                    "(--evaluate-as) or with the denoisers")
    ap.add_argument("--whole-frames", action="store_true", help="also the plan's integrator on every pixel "
                    "(plan-whole: the plan without its region render)")
    ap.add_argument("--rr-depths", default="", help="also the plan with Russian roulette from these vertices "
                    "(comma list; the plan's own is 5), interleaved")
    ap.add_argument("--evaluate-as", default="", help="also the evaluation render exactly as camo evaluate makes it "
                    "(evaluation.views.ViewRenderer: region, noise matching, denoiser, the object's spp factor), "
                    "interleaved: comma list of DENOISER:FACTOR[:OPTION...][@LEVEL/LEVEL...] (DENOISER 'off' or a "
                    "variant; FACTOR an integer or 'auto', the factor the evaluation's pilot chooses; OPTION 'region': "
                    "only the region the object can change at every spp, 'max': the object's factor and noise "
                    "matching's combined by their larger, not their product; 'fN': the with-object render's denoiser "
                    "features at N spp; 'bN': the background's; 'independent' / 'sobol': both renders with that "
                    "sampler (camo evaluate --sampler) instead of the plan's; LEVELS: of --eval-levels, measure the "
                    "setting there only), e.g. off:1,off:1:sobol,oidn-through:auto,oidn-through:8:region@4/8")
    ap.add_argument("--aux-spp", type=int, default=16, help="with --denoisers: spp of the features' render "
                    "(at most the colour's)")
    ap.add_argument("--no-region", dest="region", action="store_false", help="with the allocation: its base pass "
                    "over every pixel, not only the region the object can change (exact everywhere)")
    ap.add_argument("--no-noise-floor", dest="noise_floor", action="store_false", help="allocation without the "
                    "floor that keeps every pixel no noisier than the background's")
    ap.add_argument("--train-spp", type=int, default=4, help="the training spp (equal error is taken there)")
    ap.add_argument("--target-spp", type=int, default=32)
    ap.add_argument("--train-levels", default="1,2,4,8")
    ap.add_argument("--full-levels", default="4", help="spp levels of full (indirect visibility on: ~35x a step) "
                    "(default: the training spp only)")
    ap.add_argument("--grad-views", type=int, default=4)
    ap.add_argument("--grad-resolution", type=int, default=64)
    ap.add_argument("--ref-grad-spp", type=int, default=64)
    ap.add_argument("--ref-grad-seeds", type=int, default=8)
    ap.add_argument("--grad-blur", type=float, default=2.0, help="texels (sigma) the map gradients are blurred by "
                    "before the cosine, as the fast preset's Adam sees them (0: raw)")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=1, help="untimed Stage 1 probes per setting before timing (JIT "
                    "compiles of every view's kernels; more are added until every view has had its silhouette pass; "
                    "a run amortises them over its steps)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clock", choices=tuple(CLOCK), default="cpu", help="seconds of the timed renders: the "
                    "process's CPU seconds (default: fair on a shared machine) or wall seconds")
    ap.add_argument("--out", default="bench_out")
    ap.add_argument("--tables", nargs="+", metavar="JSON", help="print the tables of saved bench_planner.json files "
                    "(merged in order; the gradient figures recomputed from their rows) and measure nothing")
    args = ap.parse_args()
    if args.tables:
        merged: dict = {}
        for path in args.tables:
            r = json.loads(Path(path).read_text())
            if not merged:
                merged = {**r, "eval": [], "grad": [], "seconds": 0.0}
            merged["eval"] += r.get("eval", [])
            merged["grad"] += [summarise_gradient(g, r["args"]["train_spp"]) for g in r.get("grad", [])]
            merged["seconds"] += r.get("seconds", 0.0)
            if r.get("grad"):
                merged["grad_args"] = r["args"]
        print_tables(merged)
        return
    from optimizer.rendering.allocation import VARIANTS as ESTIMATORS

    args.estimators = [e for e in args.estimators.split(",") if e]
    bad = [e for e in args.estimators if e not in ESTIMATORS]
    if bad or not args.estimators:
        ap.error(f"--estimators: unknown {', '.join(bad) or '(none given)'}; choose from {', '.join(ESTIMATORS)}")
    from optimizer.rendering.denoise import VARIANTS as DENOISERS

    args.denoisers = [d for d in args.denoisers.split(",") if d]
    bad = [d for d in args.denoisers if d not in DENOISERS]
    if bad:
        ap.error(f"--denoisers: unknown {', '.join(bad)}; choose from {', '.join(DENOISERS)}")
    args.evaluate_as = [x for x in args.evaluate_as.split(",") if x]
    args.rr_depths = [int(x) for x in args.rr_depths.split(",") if x]
    from optimizer.rendering.tracer import SAMPLERS

    args.samplers = [x for x in args.samplers.split(",") if x]
    bad = [x for x in args.samplers + [args.plan_sampler or SAMPLERS[0]] if x not in SAMPLERS]
    if bad:
        ap.error(f"--samplers / --plan-sampler: unknown {', '.join(bad)}; choose from {', '.join(SAMPLERS)}")
    args.eval_levels = [int(x) for x in args.eval_levels.split(",")]
    for x in args.evaluate_as:
        try:
            lv = parse_evaluate_as(x)[2]["levels"]
        except ValueError as e:
            ap.error(f"--evaluate-as: {e}")
        if lv is not None and not set(lv) <= set(args.eval_levels):
            ap.error(f"--evaluate-as: {x!r}: levels {sorted(set(lv) - set(args.eval_levels))} are not in "
                     f"--eval-levels {args.eval_levels}")
    args.train_levels = [int(x) for x in args.train_levels.split(",")]
    args.full_levels = [int(x) for x in args.full_levels.split(",")]
    global clock
    clock = CLOCK[args.clock]

    from optimizer import backend
    from optimizer.scenes import builtin_scenes

    info = backend.init()
    names = args.scenes.split(",") if args.scenes else list(builtin_scenes.names())
    if args.real:
        names += list(REAL_PACKS)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"args": vars(args), "backend": f"{info.variant}, {info.threads} threads", "eval": [], "grad": []}
    t_all = time.perf_counter()
    for name in names:
        if args.only in ("eval", "both"):
            r = bench_evaluation(name, args)
            results["eval"].append(r)
            print(f"{name}: evaluation render {r['speedup']:.2f}x at equal error", flush=True)
        if args.only in ("grad", "both"):
            r = bench_gradient(name, args)
            results["grad"].append(r)
            print(f"{name}: gradient " + ", ".join(f"vs {w} {r[w]['speedup']:.2f}x (cosine ratio "
                                                     f"{r[w]['cosine_ratio']:.3f})" for w in ("full", "full-lt") if w in r),
                  flush=True)
        (out / "bench_planner.json").write_text(json.dumps(results, indent=1))
    results["seconds"] = time.perf_counter() - t_all
    (out / "bench_planner.json").write_text(json.dumps(results, indent=1))
    print_tables(results)


def print_variants(results: dict) -> None:
    """The table of every other measured curve of (a) (``--samplers``, ``--rr-depths``): each one's speed-up at
    equal error against the same full tracing (``plan-sobol``: the plan with the ``sobol`` sampler; ``full-sobol``:
    full tracing with it, what the sampler alone buys; ``plan-sobol-rr3``: with Russian roulette from vertex 3)."""
    ev = [r for r in results["eval"] if r.get("variants")]
    if not ev:
        return
    a = results["args"]
    names = list(dict.fromkeys(k for r in ev for k in r["variants"]))
    print("Other settings of the evaluation render, measured in the same run against the same full tracing: speed-up "
          f"at equal error (full tracing's error at {a['eval_spp']} spp) / error at {a['eval_spp']} spp (/255); the "
          f"plan as it is (sampler {ev[0].get('plan_sampler', 'independent')}, Russian roulette from vertex "
          f"{ev[0].get('rr_depth', 5)}) in the last column\n")
    print("| scene | " + " | ".join(names) + " | plan |")
    print("|---|" + "---|" * len(names) + "---|")
    def read(r, x):  # the speed-up, clamped to the levels measured (">=": the cheapest level already below)
        if "curve" not in x:
            return x["speedup"], False
        t, low = clamped_seconds(x["curve"], r["full_error_at_spp"], x["seconds_at_equal_error"])
        return r["full_seconds_at_spp"] / t, low

    plans = {r["scene"]: read(r, {"curve": r["plan_curve"], "seconds_at_equal_error":
                                  r["plan_seconds_at_equal_error"]}) if "plan_curve" in r else (r["speedup"], False)
             for r in ev}
    cols: dict = {k: [] for k in names + ["plan"]}
    for r in ev:
        cells = []
        for k in names + ["plan"]:
            if k == "plan":
                (sp, low), err = plans[r["scene"]], r["noise_at_spp"]
            elif k in r["variants"]:
                (sp, low), err = read(r, r["variants"][k]), r["variants"][k]["error_at_spp"]
            else:
                cells.append("-")
                continue
            cols[k].append(sp)
            cells.append(f"{'>= ' * low}{sp:.2f}x / {err * 255:.2f}")
        print(f"| {r['scene']} | " + " | ".join(cells) + " |")
    print("| mean / min | " + " | ".join(f"{np.mean(cols[k]):.2f}x / {np.min(cols[k]):.2f}x" for k in names + ["plan"])
          + " |\n")
    print("(>=: the setting's cheapest level is already below full tracing's error: its seconds, so a lower bound)\n")


def print_evaluate_as(results: dict) -> None:
    """The table of ``--evaluate-as``: the evaluation render as ``camo evaluate`` makes it, per setting."""
    a = results["args"]
    sets = list(dict.fromkeys(e for r in results["eval"] for e in (r.get("evaluate_as") or {})))
    if not sets:
        return
    print(f"The evaluation render as camo evaluate makes it (evaluation.views.ViewRenderer: the plan's depth and "
          f"region, noise matching, the denoiser on both renders, the object and a 3-pixel rim at k x the spp), "
          f"measured in the same run against the same full tracing; the with-object render timed whole (region "
          f"search, noise matching's and the object's extra samples, features, denoising), the background not. "
          f"Noise near the object: the object and a 2-pixel rim at {a['eval_spp']} spp, two seeds, with-object / "
          "background (both denoised alike)\n")
    print("| scene | setting | k | CPU s @ equal error | speed-up | CPU s @"
          f"{a['eval_spp']} spp (full's) | extra samples @{a['eval_spp']} spp | error @{a['eval_spp']} spp (/255) | "
          "noise near the object / bg (/255) = ratio | noise ratio at the equal-error level (spp) | pilot s |")
    # a setting measured at some levels only (@LEVELS, not the evaluation's spp): its most expensive level's seconds,
    # error and extra samples, and where it never reached full tracing's error, its noise ratio there
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    sp: dict = {e: [] for e in sets}
    worst: dict = {e: [] for e in sets}  # the noise ratios at the equal-error level
    extrapolated: dict = {e: 0 for e in sets}  # scenes where the setting's measured levels never reached the error
    for r in results["eval"]:
        for e in sets:
            x = (r.get("evaluate_as") or {}).get(e)
            if x is None:
                continue
            t_eq, low = clamped_seconds(x["curve"], r["full_error_at_spp"], x["seconds_at_equal_error"])
            speed = r["full_seconds_at_spp"] / t_eq
            sp[e].append(speed)
            nz = x.get("noise_near_object") or {}
            ratio = (f"{nz['object']:.2f} / {nz['background']:.2f} = {nz['object'] / max(nz['background'], 1e-9):.2f}"
                     if nz else "-")
            pil = x.get("pilot") or {}
            lv = x.get("equal_error_level")
            at_s = a["eval_spp"] in x.get("levels", [a["eval_spp"]])  # measured at the evaluation's spp
            extra = (f"+{x['extra_samples']:.0%}" if at_s else
                     f"+{(x.get('extra_samples_by_spp') or {}).get(str(lv), float('nan')):.0%} ({lv} spp)")
            top_s, top_err = max(x["curve"], key=lambda p: p[0])  # its most expensive level measured
            top_lv = max(x.get("levels") or [a["eval_spp"]])
            beyond = lv is None and top_err > r["full_error_at_spp"]  # never reached full's error: extrapolated
            nl = (x.get("noise_by_spp") or {}).get(str(lv if lv is not None else top_lv))
            eq_ratio = (f"{nl['object'] / max(nl['background'], 1e-9):.2f} ({lv if lv is not None else top_lv}"
                        f"{', error above' if beyond else ''})" if nl else "-")
            if nl:
                worst[e].append(nl["object"] / max(nl["background"], 1e-9))
            if beyond:
                extrapolated[e] += 1
                extra = f"+{(x.get('extra_samples_by_spp') or {}).get(str(top_lv), float('nan')):.0%} ({top_lv} spp)"
            err = f"{x['error_at_spp'] * 255:.3f}" if at_s else f"{top_err * 255:.3f} ({top_lv} spp)"
            lab = e + (f" -> {pil['chosen']['label']}" if pil.get("chosen") else " -> default" if "chosen" in pil
                       else "")
            print(f"| {r['scene']} | {lab} | {x['object_spp']} | {t_eq:.2f}{' (lowest level)' if low else ''}"
                  f"{' (extrapolated)' if beyond else ''} | {'>= ' if low else '~' if beyond else ''}{speed:.2f}x | "
                  f"{x['seconds_at_spp'] if at_s else top_s:.2f}{'' if at_s else f' ({top_lv} spp)'} "
                  f"({r['full_seconds_at_spp']:.2f}) | {extra} | {err} | {ratio if at_s else '-'} | "
                  f"{eq_ratio} | "
                  f"{pil.get('wall_seconds', 0):.1f} |")
    for e in sets:
        print(f"\n{e}: mean speed-up {np.mean(sp[e]):.2f}x, minimum {np.min(sp[e]):.2f}x (>= where the cheapest level "
              "is already below the target error"
              + (f"; ~ on {extrapolated[e]} scene(s): error above full tracing's at every level measured, seconds "
                 "extrapolated as error ~ seconds^-1/2 from the most expensive level" if extrapolated[e] else "") + ")"
              + (f"; noise ratio at the equal-error level: worst {np.max(worst[e]):.2f}, "
                 f"{sum(w <= 1.0 for w in worst[e])} of {len(worst[e])} scenes <= 1" if worst[e] else ""))
    print()


def print_gradient_probes(grads: list[dict]) -> None:
    """The check behind the gradient table: every timed probe's CPU seconds in run order per level (a compile or a
    load spike shows as one probe far above the others; the table keeps the least), the untimed warm-up's seconds
    per probe, and the spread of the probes' cosines (sample sd; the mean's standard error is sd / sqrt(reps))."""
    print("\nProbes per level: step seconds of each repetition in run order; warm-up seconds per probe (probes; "
          "then the settling probe's just before the timed ones); cosine mean +- sd over the repetitions:\n")
    print("| scene | setting | spp | step s | warm-up s / probe | cosine mean +- sd |")
    print("|---|---|---|---|---|---|")
    for r in grads:
        for who in ("plan", "full-lt", "full"):
            for spp in sorted({x["spp"] for x in r["rows"] if x["who"] == who}):
                xs = [x for x in r["rows"] if x["who"] == who and x["spp"] == spp]
                c = np.array([x["cosine"] for x in xs])
                w = r.get("warmup", {}).get(f"{who}@{spp}")
                warm = f"{w['seconds'] / max(w['probes'], 1):.2f} ({w['probes']})" if w else "-"
                if w and "settle" in w:  # the untimed probe just before the timed ones
                    warm += f"; {w['settle']:.2f}"
                sd = f"{c.std(ddof=1):.3f}" if len(c) > 1 else "-"
                secs = ", ".join(f"{x['seconds']:.2f}" for x in xs)
                print(f"| {r['scene']} | {who} | {spp} | {secs} | {warm} | "
                      f"{c.mean():.3f} +- {sd} |")


def print_tables(results: dict) -> None:
    a = results["args"]
    print(f"\nbackend {results['backend']}; {a['views']} views at {a['resolution']}^2; seconds = {a.get('clock', 'wall')} seconds; "
          f"{results.get('seconds', 0):.0f} s in all\n")
    if results["eval"]:
        print(f"(a) evaluation render, error = sRGB RMS over the frame vs full path tracing at {a['ref_spp']} spp "
              f"(its noise subtracted); equal error at full tracing's error at {a['eval_spp']} spp\n")
        top = results["eval"][0].get("top_spp", "top")
        print(f"| scene | plan depth | region rendered (launches) | pilot s | full CPU s @{a['eval_spp']} spp | "
              f"plan CPU s @ equal error | speed-up | speed-up at {top} spp (equal spp) | bias (/255) | "
              f"noise @{a['eval_spp']} spp (/255) | noise near the object: with it / background (/255) |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        sp, lows = [], 0
        for r in results["eval"]:
            t_eq, low = clamped_seconds(r["plan_curve"], r["full_error_at_spp"], r["plan_seconds_at_equal_error"])
            sp.append(r["full_seconds_at_spp"] / t_eq)
            lows += low
            print(f"| {r['scene']} | {r['max_depth']} | {r['region_share']:.0%} ({r.get('region_launches', 0):.1f}) | "
                  f"{r['pilot_seconds']:.1f} | {r['full_seconds_at_spp']:.2f} | {t_eq:.2f}{' (lowest level)' * low} | "
                  f"{'>= ' * low}{sp[-1]:.2f}x | {r.get('speedup_equal_spp', float('nan')):.2f}x | "
                  f"{r['bias'] * 255:.3f} | {r['noise_at_spp'] * 255:.3f} | " +
                  ("{object:.2f} / {background:.2f}".format(**r["noise_near_object"]) if r.get("noise_near_object")
                   else "-") + " |")
        print(f"\nmean speed-up {np.mean(sp):.2f}x, minimum {np.min(sp):.2f}x" +
              (" (where the plan's cheapest level is already below the target error, its seconds: a lower bound, "
               ">=)" if lows else "") + "\n")
        for r in results["eval"]:  # a JSON of the earlier layout: one allocation, the local estimate
            if r.get("allocation") and not r.get("allocations"):
                r["allocations"] = {"local": dict(r["allocation"], estimator="local")}
        ests = list(dict.fromkeys(e for r in results["eval"] for e in (r.get("allocations") or {})))
        for est in ests:
            al = [r for r in results["eval"] if est in (r.get("allocations") or {})]
            floor = "with" if al[0]["allocations"][est].get("noise_floor") else "without"
            print(f"The plan with per-pixel sample allocation, variant {est} ({floor} the noise floor), "
                  "measured in the same run: its seconds and error against the same full tracing\n")
            print(f"| scene | plan + allocation CPU s @ equal error | speed-up | speed-up at {top} spp (equal spp) | "
                  f"error @{a['eval_spp']} spp, plan + allocation / full (/255) | bias (/255) | samples (share of a "
                  "full frame's) | pixels on the control variate | cost per sample, object / other | (plan alone) |")
            print("|---|---|---|---|---|---|---|---|---|---|")
            for r in al:
                x = r["allocations"][est]
                c = x.get("costs") or [float("nan"), float("nan")]
                print(f"| {r['scene']} | {x['seconds_at_equal_error']:.2f} | {x['speedup']:.2f}x | "
                      f"{x['speedup_equal_spp']:.2f}x | {x['error_at_spp'] * 255:.3f} / {r['full_error_at_spp'] * 255:.3f} | "
                      f"{x['bias'] * 255:.3f} | {x['samples_share']:.0%} | {x['control_variate_share']:.0%} | "
                      f"{c[0] / c[1]:.1f}x | {r['speedup']:.2f}x |")
            sa = [r["allocations"][est]["speedup"] for r in al]
            print(f"\nwith the allocation ({est}): mean speed-up {np.mean(sa):.2f}x, minimum {np.min(sa):.2f}x\n")
            if "region_search" in al[0]:
                rule = [(r["scene"], r["allocations"][est]["speedup"] if not r["region_search"] else r["speedup"],
                         "allocation" if not r["region_search"] else "region") for r in al]
                print(f"The plan's rule (the allocation, {est}, where the plan renders whole frames; its region "
                      "elsewhere): " + ", ".join(f"{n} {v:.2f}x ({k})" for n, v, k in rule) +
                      f"; mean {np.mean([v for _, v, _ in rule]):.2f}x, minimum {np.min([v for _, v, _ in rule]):.2f}x\n")
    rrs = list(dict.fromkeys(k for r in results["eval"] for k in (r.get("rr_depths") or {})))
    if rrs:
        print("The plan with Russian roulette from an earlier vertex (the plan's depth and region; its own: from "
              f"vertex {results['eval'][0].get('rr_depth', 5)}), measured in the same run against the same full tracing\n")
        print("| scene | " + " | ".join(f"from vertex {k}: CPU s @ equal error, speed-up, @{top} spp (equal spp), "
                                         f"error @{a['eval_spp']} spp (/255)" for k in rrs) + " | (plan) |")
        print("|---|" + "---|" * len(rrs) + "---|")
        for r in results["eval"]:
            cells = []
            for k in rrs:
                x = (r.get("rr_depths") or {}).get(k)
                cells.append("-" if x is None else f"{x['seconds_at_equal_error']:.2f}, {x['speedup']:.2f}x, "
                             f"{x['speedup_equal_spp']:.2f}x, {x['error_at_spp'] * 255:.3f}")
            print(f"| {r['scene']} | " + " | ".join(cells) + f" | {r['speedup']:.2f}x |")
        for k in rrs:
            sp = [r["rr_depths"][k]["speedup"] for r in results["eval"] if k in (r.get("rr_depths") or {})]
            print(f"\nfrom vertex {k}: mean speed-up {np.mean(sp):.2f}x, minimum {np.min(sp):.2f}x")
        print()
    print_variants(results)
    print_evaluate_as(results)
    dens = list(dict.fromkeys(d for r in results["eval"] for d in (r.get("denoisers") or {})))
    for d in dens:
        al = [r for r in results["eval"] if d in (r.get("denoisers") or {})]
        k = al[0]["denoisers"][d].get("seeds_at_spp", 0)
        print(f"The plan denoised by Open Image Denoise, variant {d} (optimizer/rendering/denoise.py VARIANTS; features "
              f"at {a.get('aux_spp', 16)} spp, their render and the denoising timed), measured in the same run against "
              "the same full tracing. Bias: the mean of the denoised plan over its "
              f"{k} seeds at {a['eval_spp']} spp against the reference, the seeds' spread and the reference's noise "
              f"subtracted; at {a['ref_spp']} spp: the denoised converged plan. Noise near the object: the object and "
              "a 2-pixel rim, two seeds, with-object / background (both denoised alike)\n")
        print(f"| scene | plan + {d} CPU s @ equal error | speed-up | speed-up at {top} spp (equal spp) | full + {d}: "
              f"speed-up | error @{a['eval_spp']} spp, plan + {d} / plan / full (/255) | bias @{a['eval_spp']} spp / "
              f"@{a['ref_spp']} spp (/255) | noise near the object / bg, plan | plan + {d} (/255) | features s | "
              "denoise s |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        sd = []
        for r in al:
            x = r["denoisers"][d]
            n0, n1 = r.get("noise_near_object") or {}, x.get("noise_near_object") or {}
            t_eq, low = clamped_seconds(x["curve"], r["full_error_at_spp"], x["seconds_at_equal_error"])
            sp = r["full_seconds_at_spp"] / t_eq
            sd.append(sp)
            f_curve = x.get("full_curve") or _mean_curve(r["rows"], f"full+{d}")
            t_f, f_low = clamped_seconds(f_curve, r["full_error_at_spp"],
                                         r["full_seconds_at_spp"] / x["full_denoised_speedup"])
            fsp = r["full_seconds_at_spp"] / t_f
            print(f"| {r['scene']} | {t_eq:.2f}{' (lowest level)' if low else ''} | {'>= ' if low else ''}{sp:.2f}x | "
                  f"{x['speedup_equal_spp']:.2f}x | {'>= ' if f_low else ''}{fsp:.2f}x | "
                  f"{x['error_at_spp'] * 255:.3f} / {r['noise_at_spp'] * 255:.3f} / {r['full_error_at_spp'] * 255:.3f} | "
                  f"{x['bias_at_spp'] * 255:.3f} / {x['bias_at_ref_spp'] * 255:.3f} | "
                  f"{n0.get('object', float('nan')):.2f} / {n0.get('background', float('nan')):.2f} | "
                  f"{n1.get('object', float('nan')):.2f} / {n1.get('background', float('nan')):.2f} | "
                  f"{x['features_seconds']:.2f} | {x['denoise_seconds']:.2f} |")
        print(f"\nplan + {d}: mean speed-up {np.mean(sd):.2f}x, minimum {np.min(sd):.2f}x (where its cheapest level, "
              f"{min(a['eval_levels'])} spp, is already below the target error, its seconds: a lower bound)\n")
        ob = [r for r in al if r["denoisers"][d].get("object")]
        if ob:
            print(f"On the object's own pixels (coverage >= 0.5 in the with-object render; its starting material, "
                  f"see-through) at {a['eval_spp']} spp, {k} seeds, against the reference (sRGB /255): the bias of the "
                  "seeds' mean (spread and reference noise subtracted) beside one seed's noise, and the detail ratio "
                  "(mean |Laplacian| of the luma against the reference's; 1 = its texture, < 1 smoothed, > 1 noise). "
                  "The reference's own noise adds to its detail: the two references' mean (2x spp) against it, and "
                  "its extrapolation to infinite spp, sqrt(2 d^2 - 1), by which the detail is divided to give the "
                  "detail against the converged render. The plan's own object bias is the estimator's floor (the plan is unbiased over the frame; 3 seeds "
                  "with fireflies leave their spread poorly estimated). Whole-frame bias from the table above\n")
            print(f"| scene | object px | whole-frame bias, plan + {d} | object bias, plan + {d} | object noise, "
                  f"plan + {d} | object bias, plan | object noise, plan | detail, plan + {d} | detail, plan | "
                  f"reference at 2x spp: detail / converged (extrapolated) | detail vs converged, plan + {d} | "
                  f"object bias of plan + {d} below the plan's noise / below its own noise? |")
            print("|---|---|---|---|---|---|---|---|---|---|---|---|")
            for r in ob:
                x = r["denoisers"][d]
                o_d, o_p = x["object"]["denoised"], x["object"]["plan"]
                print(f"| {r['scene']} | {o_d['pixels']} | {x['bias_at_spp'] * 255:.2f} | {o_d['bias'] * 255:.2f} | "
                      f"{o_d['noise'] * 255:.2f} | {o_p['bias'] * 255:.2f} | {o_p['noise'] * 255:.2f} | "
                      f"{o_d['detail']:.2f} | {o_p['detail']:.2f} | "
                      f"{o_d.get('ref_detail_2x', float('nan')):.2f} / {o_d.get('converged', float('nan')):.2f} | "
                      f"{o_d['detail'] / o_d.get('converged', float('nan')):.2f} | "
                      f"{'yes' if o_d['bias'] < o_p['noise'] else 'no'} / "
                      f"{'yes' if o_d['bias'] < o_d['noise'] else 'no'} |")
            print()
    if results["grad"]:
        g = results.get("grad_args", a)
        print(f"(b) Stage 1 gradient, {g['grad_views']} views at {g['grad_resolution']}^2, maps {g['map_resolution']}^2 "
              f"(cosine of the map gradients with full tracing's at {g['ref_grad_spp']} x {g['ref_grad_seeds']} spp, "
              f"mean of {g['reps']} probes per level); equal seconds / equal cosine at full tracing's "
              f"{g['train_spp']} spp\n")
        levels = sorted({int(k) for r in results["grad"] for k in r["curves"].get("plan", {})})
        print("| scene | plan depth | window | vs | cosine plan / full at " + " | ".join(f"{k} spp" for k in levels) +
              " | step s plan / full @" + f"{g['train_spp']} spp | cosine ratio at {g['train_spp']} spp | plan cos in "
              "full's s (spp afforded) | ratio | speed-up at equal cos | loss err plan / full |")
        print("|---|---|---|---|" + "---|" * len(levels) + "---|---|---|---|---|---|")
        for r in results["grad"]:
            for who in ("full", "full-lt"):
                if who not in r:
                    continue
                w, c, pl = r[who], r["curves"], r.get("plan_at_spp", {})
                cells = " | ".join(f"{c['plan'][str(k)][1]:.3f} / {c[who][str(k)][1]:.3f}" if str(k) in c[who] else
                                   f"{c['plan'][str(k)][1]:.3f} / -" for k in levels)
                print(f"| {r['scene']} | {r['max_depth']} | {r['window_share']:.0%} | {who} | {cells} | "
                      f"{pl.get('seconds', float('nan')):.2f} / {w['seconds_at_spp']:.2f} | "
                      f"{w.get('cosine_ratio_equal_spp', float('nan')):.2f} | "
                      f"{w['plan_cosine_at_same_seconds']:.3f} ({w.get('plan_spp_at_same_seconds', float('nan')):.1f}"
                      f"{', clamped' if w.get('clamped') else ''}) | {w['cosine_ratio']:.2f} | {w['speedup']:.2f}x | "
                      f"{pl.get('loss_error', float('nan')):.2e} / {w['loss_error_at_spp']:.2e} |")
        print("\nAt equal spp, pooled over the levels both measured (sum of the plan's mean cosines over sum of full's; "
              "median over the levels of the ratio of least step seconds):")
        for r in results["grad"]:
            c = r["curves"]
            for who in ("full", "full-lt"):
                common = [k for k in c.get(who, {}) if k in c.get("plan", {})]
                if common:
                    cp, cf = sum(c["plan"][k][1] for k in common), sum(c[who][k][1] for k in common)
                    ts = float(np.median([c["plan"][k][0] / c[who][k][0] for k in common]))
                    print(f"- {r['scene']} vs {who}: cosine {cp / cf:.2f} of full's, step seconds {ts:.2f} of full's "
                          f"({', '.join(common)} spp)")
        print_gradient_probes(results["grad"])
        for who in ("full", "full-lt"):
            sp = [r[who]["speedup"] for r in results["grad"] if who in r]
            cr = [r[who]["cosine_ratio"] for r in results["grad"] if who in r]
            ce = [r[who].get("cosine_ratio_equal_spp", float("nan")) for r in results["grad"] if who in r]
            if sp:
                print(f"\nvs {who}: speed-up at equal cosine mean {np.nanmean(sp):.2f}x, minimum {np.nanmin(sp):.2f}x; "
                      f"cosine ratio at equal seconds mean {np.nanmean(cr):.2f}, minimum {np.nanmin(cr):.2f}; "
                      f"at equal spp mean {np.nanmean(ce):.2f}, minimum {np.nanmin(ce):.2f}")

if __name__ == "__main__":
    main()
