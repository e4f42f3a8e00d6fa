"""Does noise give the object away? The with-object render's noise around the object against the background
render's noise in the same pixels, per scene, without and with noise matching (:mod:`optimizer.rendering.noise`).

For every scene (built-in, optionally real packs), the scene's object at its starting material (the built-in
scenes start transmissive: the hard case) is rendered as ``camo evaluate`` renders it (the evaluation plan, the
region the object can change, the rest from the background render of the same seed), at ``--spp``, with two
independent seeds. Noise = RMS of the difference of the two 8-bit sRGB renders over sqrt 2, over the object and a
2-pixel rim; the background's over the same pixels. "Fireflies": pixels of that set whose two renders differ by more
than 20/255, per 1000. Both measured without noise matching and with it, side by side in one run; the extra samples
and the with-object render's seconds state what matching costs.

    python bench/bench_noise.py [--scenes meadow,room] [--views 2] [--resolution 64] [--spp 64]

Prints a Markdown table (ratios near 1 mean the object's surroundings are no noisier than the background).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def bench_scene(name: str, args) -> dict:
    import dataclasses

    from evaluation.views import ViewRenderer, evaluation_cameras, evaluation_plan
    from optimizer.rendering.noise import fireflies, noise_rms
    from optimizer.rendering.placement import prepare_object, static_object_fn
    from optimizer.rendering.region import dilate_px
    from optimizer.scenes.builtin_scenes import resolve_scene
    from optimizer.scenes.environments import get_environment

    pack = resolve_scene(name)
    pack.cameras = dataclasses.replace(pack.cameras, views=args.views)
    pack.render = dataclasses.replace(pack.render, resolution=(args.resolution, args.resolution))
    env = get_environment(pack.environment)
    cams = evaluation_cameras(pack, args.views, seed=0).cams
    mesh_fn = static_object_fn(pack, prepare_object(pack, target_vertices=args.target_vertices))
    plan = evaluation_plan(pack, env, cams, args.spp, 0)
    integ = plan.integrator
    threshold = plan.region_threshold if plan.region_search else None
    out = {"scene": name, "max_depth": plan.max_depth, "transmittance": float(pack.material.transmittance),
           "roughness": float(pack.material.roughness)}
    renders = {}
    settings = [(m, "", 1) for m in (False, True)]
    if args.denoise:
        settings += [(m, args.denoise, 1) for m in (False, True)]
        settings += [(True, args.denoise, k) for k in args.object_spp if k != 1]
        if args.auto:  # what the evaluation plan would choose (evaluation.views.object_spp_pilot), on its own seeds
            from evaluation.views import object_spp_pilot

            plan.denoise = args.denoise
            pilot = object_spp_pilot(pack, env, cams, plan, args.spp, 0, True, mesh_fn)
            out["pilot"] = {k: v for k, v in pilot.items() if k != "why"}
            settings.append((True, args.denoise, pilot["factor"]))
            settings = list(dict.fromkeys(settings))
    for matched, denoise, k in settings:
        rs = []
        for seed in (1, 2):
            r = ViewRenderer(args.spp, seed, noise_match=matched)
            bg = r.background(pack, env, cams, integ, denoise)
            t = time.perf_counter()
            o = r.with_object(env, mesh_fn, cams, integ, bg, threshold, object_spp=k)
            rs.append((bg.image, o, time.perf_counter() - t, bg.seconds))
        renders[(matched, denoise, k)] = rs
    (b0, o0, _, _), (b1, o1, _, _) = renders[(False, "", 1)]
    near = np.stack([dilate_px(m, 2) for m in o0.mask])
    for (matched, denoise, k), rs in renders.items():
        (b0, o0, s0, bs0), (b1, o1, s1, bs1) = rs
        bg_noise = noise_rms(b0, b1, near)
        key = ("matched" if matched else "plain") + (f"+{denoise}" if denoise else "") + (f"+x{k}" if k > 1 else "")
        out[key] = {"object_noise": noise_rms(o0.image, o1.image, near), "background_noise": bg_noise,
                    "ratio": noise_rms(o0.image, o1.image, near) / max(bg_noise, 1e-9),
                    "fireflies": fireflies(o0.image, o1.image, near), "bg_fireflies": fireflies(b0, b1, near),
                    "seconds": (s0 + s1) / 2, "background_seconds": (bs0 + bs1) / 2,
                    "extra_samples_share": float(np.mean([o.noise.extra_samples for o in (o0, o1)]))
                    if o0.noise is not None else 0.0,
                    "max_factor": int(max(o.noise.factor.max() for o in (o0, o1))) if o0.noise is not None else 1}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="", help="comma list (default: the six built-in scenes)")
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--target-vertices", type=int, default=8000)
    ap.add_argument("--denoise", default="", help="also both renders denoised by this denoiser (optimizer/rendering/"
                    "denoise.py VARIANTS, e.g. oidn-raw), without and with noise matching")
    ap.add_argument("--object-spp", default="1", help="with --denoise: also matched and denoised with the object and "
                    "its rim at these factors of the spp (comma list of integers >= 1, e.g. 2,4)")
    ap.add_argument("--auto", action="store_true", help="with --denoise: also the factor the evaluation's pilot "
                    "chooses (evaluation.views.object_spp_pilot; its own seeds, timed)")
    args = ap.parse_args()
    try:
        args.object_spp = [int(x) for x in args.object_spp.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--object-spp: integers >= 1, not {args.object_spp!r}")
    if any(k < 1 for k in args.object_spp):
        ap.error(f"--object-spp: integers >= 1, not {args.object_spp}")
    if (args.auto or args.object_spp != [1]) and not args.denoise:
        ap.error("--object-spp / --auto need --denoise VARIANT")

    from optimizer import backend
    from optimizer.scenes import builtin_scenes

    info = backend.init()
    names = args.scenes.split(",") if args.scenes else list(builtin_scenes.names())
    t0 = time.perf_counter()
    rows = []
    for n in names:
        rows.append(bench_scene(n, args))
        print(f"{n}: noise ratio {rows[-1]['plain']['ratio']:.2f} -> {rows[-1]['matched']['ratio']:.2f}", flush=True)
    print(f"\nbackend {info.variant}, {info.threads} threads; {args.views} views at {args.resolution}^2, {args.spp} spp; "
          f"{time.perf_counter() - t0:.0f} s in all\n")
    print("| scene | start T / roughness | depth | bg noise (/255) | object noise plain -> matched (/255) | ratio plain "
          "-> matched | fireflies /1000 plain -> matched (bg) | extra samples | with-object s plain -> matched |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        p, m = r["plain"], r["matched"]
        print(f"| {r['scene']} | {r['transmittance']:.2f} / {r['roughness']:.2f} | {r['max_depth']} | "
              f"{p['background_noise']:.2f} | {p['object_noise']:.2f} -> {m['object_noise']:.2f} | "
              f"{p['ratio']:.2f} -> {m['ratio']:.2f} | {p['fireflies']:.1f} -> {m['fireflies']:.1f} "
              f"({p['bg_fireflies']:.1f}) | +{m['extra_samples_share']:.0%} (max {m['max_factor']}x) | "
              f"{p['seconds']:.2f} -> {m['seconds']:.2f} |")
    if args.denoise:
        print_denoised(rows, args.denoise)
        print_object_spp(rows, args.denoise)


def print_object_spp(rows: list[dict], denoise: str) -> None:
    """Matched and denoised, the object and its rim at more spp: noise ratio and what it costs."""
    cols = sorted({int(k.rsplit("+x", 1)[1]) for r in rows for k in r if k.startswith(f"matched+{denoise}+x")})
    if not cols and not any("pilot" in r for r in rows):
        return
    print(f"\nMatched and {denoise}, the object and a 3-pixel rim at k x the spp (ratio = object / background noise "
          "after the denoiser; extra samples as a share of a frame; with-object seconds)\n")
    head = ["k = 1", *[f"k = {k}" for k in cols]]
    print("| scene | " + " | ".join(head) + " | pilot: r -> k (r at k), s |")
    print("|---|" + "---|" * (len(head) + 1))
    for r in rows:
        cells = []
        for k in [1, *cols]:
            x = r.get(f"matched+{denoise}" + (f"+x{k}" if k > 1 else ""))
            cells.append("-" if x is None else f"{x['ratio']:.2f}; +{x['extra_samples_share']:.0%}; {x['seconds']:.2f} s")
        p = r.get("pilot")
        pc = "-" if p is None else (f"{p['ratio']:.2f} -> x{p['factor']} ({p['ratio_at_factor']:.2f} at "
                                   f"x{p['verified_factor']}), {p['seconds']:.1f} s")
        print(f"| {r['scene']} | " + " | ".join(cells) + f" | {pc} |")


def print_denoised(rows: list[dict], denoise: str) -> None:
    """The noise table with the denoiser: background noise (denoised alike) and the object's, per setting."""
    keys = ("plain", "matched", f"plain+{denoise}", f"matched+{denoise}")
    print(f"\nWith the denoiser {denoise} on both renders (noise (/255) object / background, ratio; fireflies /1000 "
          "object (background))\n")
    print("| scene | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for r in rows:
        cells = [f"{r[k]['object_noise']:.2f} / {r[k]['background_noise']:.2f} = {r[k]['ratio']:.2f}; "
                 f"{r[k]['fireflies']:.1f} ({r[k]['bg_fireflies']:.1f})" for k in keys]
        print(f"| {r['scene']} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
