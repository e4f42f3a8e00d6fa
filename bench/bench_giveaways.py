"""Give-away measures (detail ratio, tint, shadow share) of today's default against changes of the method, on the
built-in scenes: the detail term (``detail8``: ``--detail-match 8``), the map resolution (``map256``), no gradient
blur (``blur0``), clear glass (``clear``: IOR 1.05, smooth start; ``auto``: clear glass as a start the held-out
views keep or reject per scene, ``--clear-candidate 1.05``), the mean-colour term (``tint4``, ``tint16``:
``--tint-match W``; ``tint16_auto`` with ``--clear-candidate 1.05``), the perceptual term (``lpips``), a lower shared IOR
(``eta1.2``), a lower transmittance start (``today_t0.3``), the "large steps" map update and the grain layer
(``grain``: ``--grain 1``, the ground's texture projected from each texel's best view onto the albedo);
docs/results/giveaways.md.

    python bench/bench_giveaways.py --out /tmp/giveaways --scenes meadow,gravel,split \
        --arms today,detail8,map256,map256_detail8,blur0,clear --eval-spp 512 --docs docs/results
        # optimise (resumable), evaluate, table, sheets

Every optimised arm gets the same Stage 1 iterations (``--iterations``), or the same ``--seconds`` budget; an arm
whose step costs more gets fewer (``--arm-iterations ARM=N``: equal seconds). The machine's load moves absolute
seconds: compare arms within one run of this script; each run's seconds are in the table. The Mean baseline is run
once per scene for the contact sheets. Evaluation: ``camo evaluate`` of all arms of a scene together (the same
jittered views, common random numbers) at ``--eval-spp`` (converged: the render noise must not count against the
material); the give-away measures (``detail_ratio``, ``tint``) are the crop rows' means over views; the shadow share
is the shadow's part of the crop's squared error (:mod:`evaluation.giveaway`'s object / shadow / rest split); the
real LPIPS (AlexNet) of the saved frames when its weights are installed. Prints one Markdown table per scene and arm,
and their means; ``--docs`` also writes the contact sheets (background | arms | Mean). An arm not in :data:`ARMS` is a
run made by other code and filed under ``OUT/runs/SCENE-ARM`` by hand (``pre_fix``: ``today`` run by the checkout
before the warm-start fix of issue 29, ``git worktree add /tmp/pre 8abe702``, then moved there); it is evaluated and
tabled with the others.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from camo_base.tables import read_parquet

SCENES = ("meadow", "gravel", "split", "room", "occluded", "panorama")
#: The default (the ``fast`` preset) has had the coarse level since issue 29's third session (``--coarse-grid 1``);
#: ``today`` is the default of the code that runs, ``coarse0`` the default before (no level). The arms measured before
#: that change keep ``--coarse-grid 0`` so that they mean what their rows in giveaways.md measured.
OLD = ["--coarse-grid", "0"]
#: arm -> extra `camo optimize` flags (the default preset otherwise)
ARMS = {
    "today": [],
    "coarse0": OLD,
    "large_steps": [*OLD, "--map-update", "large_steps", "--grad-blur", "0"],
    "large_steps_t0.3": [*OLD, "--map-update", "large_steps", "--grad-blur", "0", "--init", "transmittance=0.3"],
    "today_t0.3": [*OLD, "--init", "transmittance=0.3"],
    # the perceptual term (optimizer/optimise/perceptual.py): weight 1e-3 makes its gradient about twice the
    # squared error's at a converged meadow run (rms over the body's pixels: 6.1e-3 x W against 2.7e-6)
    "lpips": [*OLD, "--perceptual", "1e-3"],
    # a lower shared index of refraction: less Fresnel reflection of the sky on the transmissive parts, and what is
    # seen through them is displaced less (the glassy tint, point 3 of the issue)
    "eta1.2": [*OLD, "--eta", "1.2"],
    # the detail term (optimizer/optimise/detail.py): the body's pixel-scale texture energy matched to the ground's
    "detail8": [*OLD, "--detail-match", "8"],
    "detail32": [*OLD, "--detail-match", "32"],
    # per-texel map steps (no gradient blur): can fine texels move where the blur held them?
    "blur0": [*OLD, "--grad-blur", "0"],
    # twice the map resolution (a texel is about a pixel at 128 texels and 64 px: see docs/results/giveaways.md)
    "map256": [*OLD, "--map-resolution", "256"],
    "map256_detail8": [*OLD, "--map-resolution", "256", "--detail-match", "8"],
    # clear glass: an IOR near 1 and a smooth start, so the ground behind shows through sharp and barely displaced
    # (texture and colour that are the ground's own; the roughness start search and the glint-safe start are off)
    "clear": [*OLD, "--eta", "1.05", "--init", "roughness=0.2", "--init-search", "off"],
    # clear glass as a candidate start the held-out views choose per scene (optimizer/optimise/startsearch.py):
    # today's start (IOR 1.5, the searched roughness) against IOR 1.05 with roughness 0.2
    "auto": [*OLD, "--clear-candidate", "1.05"],
    # the mean-colour term (optimizer/optimise/tint.py): the body's mean colour per view weighted 1 + W times in
    # Stage 1's squared error (the glassy tint is a low-frequency colour error); alone and with clear glass per scene
    "tint4": [*OLD, "--tint-match", "4"],
    "tint16": [*OLD, "--tint-match", "16"],
    "tint4_auto": [*OLD, "--tint-match", "4", "--clear-candidate", "1.05"],
    "tint16_auto": [*OLD, "--tint-match", "16", "--clear-candidate", "1.05"],
    "tint1_auto": [*OLD, "--tint-match", "1", "--clear-candidate", "1.05"],
    # its local form: the colour error low-passed by a Gaussian of 2 px, each pixel its own neighbourhood's cast
    "tint4_s2": [*OLD, "--tint-match", "4", "--tint-scale", "2"],
    # a coarse level under the albedo and transmittance maps (optimizer/optimise/coarse.py): the body's colour moved as
    # a whole by Adam at its own rate (1: one offset per channel, today's default; 4: 4 x 4 cells over the atlas);
    # alone, with clear glass per scene, and at three times the maps' rate
    "coarse1": ["--coarse-grid", "1"],
    "coarse1_auto": ["--coarse-grid", "1", "--clear-candidate", "1.05"],
    "coarse4_auto": ["--coarse-grid", "4", "--clear-candidate", "1.05"],
    "coarse1_lr3_auto": ["--coarse-grid", "1", "--coarse-lr", "3e-2", "--clear-candidate", "1.05"],
    "coarse1_tint1_auto": ["--coarse-grid", "1", "--tint-match", "1", "--clear-candidate", "1.05"],
    "coarse1_lr3": ["--coarse-grid", "1", "--coarse-lr", "3e-2"],
    # clear glass per scene started rougher (--clear-roughness; 0.2 above): rough glass spreads the sunlight it focuses
    # into its shadow (the caustic specks of coarse1_auto's panorama) and blurs the ground seen through it; 0.5 is
    # the planner's glint-safe roughness
    "coarse1_auto_r35": ["--coarse-grid", "1", "--clear-candidate", "1.05", "--clear-roughness", "0.35"],
    "coarse1_auto_r5": ["--coarse-grid", "1", "--clear-candidate", "1.05", "--clear-roughness", "0.5"],
    # the clear glass's caustic (issue 29, fourth session): at 4 spp it arrives as rare bright samples that the soft
    # clamp of the loss cuts, so Stage 1 sees the lit shadow as dark as the opaque start's and raises the
    # transmittance further; without the clamp it sees the caustic's mean (r5_c0), and rougher glass spreads it (r10)
    "coarse1_auto_r5_c0": ["--coarse-grid", "1", "--clear-candidate", "1.05", "--clear-roughness", "0.5",
                           "--loss-clamp", "0"],
    "coarse1_auto_r10": ["--coarse-grid", "1", "--clear-candidate", "1.05", "--clear-roughness", "1.0"],
    "coarse1_auto_r7": ["--coarse-grid", "1", "--clear-candidate", "1.05", "--clear-roughness", "0.7"],
    # an index of refraction nearer 1: light through the body bends and focuses less (the caustic's bright core)
    "coarse1_auto_r5_eta102": ["--coarse-grid", "1", "--clear-candidate", "1.02", "--clear-roughness", "0.5"],
    # clear glass at IOR 1.02 imposed (not a candidate): what the caustic becomes when the body bends light less
    "clear102_r5": ["--coarse-grid", "1", "--eta", "1.02", "--init", "roughness=0.5", "--init-search", "off"],
    # the displacement kept (issue 29): the fast preset's proximal L1 step (displacement_shrink 0.5) removes every
    # noise-driven move, so the anamorphic term ends at ~0; without it (the paper's 0, SPEC_FIELDS) can the body's
    # shape move where the clear glass's refracted sunlight lands (the caustic streak)?
    "coarse1_auto_r5_keepdisp": ["--coarse-grid", "1", "--clear-candidate", "1.05", "--clear-roughness", "0.5"],
    # its replicate: coarse1_auto_r5 with another training seed (how far two runs of one arm differ)
    "coarse1_auto_r5_seed1": ["--coarse-grid", "1", "--clear-candidate", "1.05", "--clear-roughness", "0.5",
                              "--seed", "1"],
    # the control: the maps' own rate doubled, no level (do faster per-texel steps do what the level does?)
    # against the cast shadow (issue 29, seventh session): the loss domain's pixels outside the object weigh 4x
    # (``--shadow-weight``: the transmittance and the pose are pulled harder towards a lighter shadow), and the same
    # with the transmittance started at 0.95 as given (light through the body where the shadow falls)
    "shadow4": ["--shadow-weight", "4"],
    "shadow4_t95": ["--shadow-weight", "4", "--init", "transmittance=0.95", "--init-search", "off"],
    # the grain layer (optimizer/optimise/grain.py, issue 29): a fixed albedo residual, the ground's texture projected
    # from each texel's best training view minus the warm start's multi-view mean (which leaves the body too smooth)
    "grain": ["--grain", "1"],
    "grain05": ["--grain", "0.5"],
    # the same projected from the targets sharpened (unsharp mask, amount 2, 0.7 px): resampling the target at each
    # texel's projection and the render's pixel box blur the projected grain twice (bench/grain_ceiling.py)
    "grain_s2": ["--grain", "1", "--grain-sharpen", "2"],
    # light through the body where the albedo clips (issue 29): the warm start solves the transmittance per texel with
    # the albedo, between the start's 0.75 and 1 (the paper's bound), or anywhere in [0, 1] (lowered too: a more
    # diffuse, sunlit body where the light through it is darker than the ground)
    "warmt1": ["--warm-transmittance", "1"],
    "warmt01": ["--warm-transmittance", "1", "--warm-transmittance-low", "0"],
    # the floor halfway: a body half as transmissive at most, so its cast shadow stays lighter than an opaque one's
    "warmt05": ["--warm-transmittance", "1", "--warm-transmittance-low", "0.5"],
    # the floor between (issue 29, nineteenth session): the trade-off between the body (lower: more diffuse, in the
    # detail band, less tint) and its cast shadow (higher: more light through the body into it) mapped point by point
    "warmt02": ["--warm-transmittance", "1", "--warm-transmittance-low", "0.2"],
    "warmt035": ["--warm-transmittance", "1", "--warm-transmittance-low", "0.35"],
    "warmt065": ["--warm-transmittance", "1", "--warm-transmittance-low", "0.65"],
    # the same floors at today's starting roughness (the roughness search's 0.5 alone): meadow's floored arms chose 0.7
    "warmt05_r5": ["--warm-transmittance", "1", "--warm-transmittance-low", "0.5", "--roughness-search", "0.5"],
    "warmt065_r5": ["--warm-transmittance", "1", "--warm-transmittance-low", "0.65", "--roughness-search", "0.5"],
    "warmt01_r5": ["--warm-transmittance", "1", "--warm-transmittance-low", "0", "--roughness-search", "0.5"],
    # the other lever on the shadow: warmt01's start, then Stage 1's loss weighs the pixels outside the object 4x
    # (``--shadow-weight``), pulling the transmittance back up where the shadow is too dark
    "warmt01_sw4": ["--warm-transmittance", "1", "--warm-transmittance-low", "0", "--shadow-weight", "4"],
    # [0, 1] lowered only on the texels facing away from the sun: the sun-facing ones, where the sunlight enters the body
    # on its way to the cast shadow, keep at least the start's 0.75 (warmt01's opaque body casts a full dark shadow)
    "warmsun": ["--warm-transmittance", "1", "--warm-transmittance-low", "0", "--warm-transmittance-sun", "facing"],
    # lowered only on the texels whose shadow point on the ground no training view sees (hidden under or behind the body)
    "warmshadow": ["--warm-transmittance", "1", "--warm-transmittance-low", "0", "--warm-transmittance-sun", "shadow"],
    "lr2": [*OLD, "--lr-maps", "2e-2"],
    "lr2_auto": [*OLD, "--lr-maps", "2e-2", "--clear-candidate", "1.05"],
}
#: baseline arms -> their `camo optimize` flags (no Stage 1 flags: nothing is optimised). Transparent (transmittance 1
#: everywhere, smooth) is as much light as any transmittance pattern can let through the body into its shadow: the
#: bound of what the maps can do against the cast shadow at the paper's IOR 1.5 (``transparent``) and at 1.05
#: (``transparent_eta105``: clear glass, ``--clear-candidate``'s IOR; ``transparent_eta105_white`` colourless too)
BASELINE_ARMS = {"transparent": ["--method", "transparent"],
                 "transparent_eta105": ["--method", "transparent", "--eta", "1.05"],
                 # and colourless (albedo 1: the principled BSDF tints what it transmits by the albedo)
                 "transparent_eta105_white": ["--method", "transparent", "--eta", "1.05", "--init", "albedo=1"]}
#: arm -> run spec fields no `camo optimize` flag sets (``"table.field": value``), set in the spec its flags make;
#: such an arm runs as ``camo optimize --spec RUNS/SCENE-ARM.spec.toml``
SPEC_FIELDS = {"coarse1_auto_r5_keepdisp": {"appearance.displacement_shrink": 0.0}}
SIZE = ["--views", "4", "--resolution", "64", "--map-resolution", "128", "--target-vertices", "3000"]


def camo(*args: str) -> None:
    cmd = [sys.executable, "-m", "camo.cli", *args]
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True)


def name_of(scene: str) -> str:
    """The name a scene's runs and evaluations are filed under: a built-in scene's name, a scene pack's file stem
    (``packs/real/cross/sky-cone.toml`` -> ``sky-cone``: the real cross, ``grids/real_cross.toml``)."""
    return Path(scene).stem if scene.endswith(".toml") else scene


def spec_file(args: list[str], fields: dict, dest: Path) -> Path:
    """Write to ``dest`` the run spec ``camo optimize ARGS`` would run, with ``fields`` (``"table.field": value``, a
    field the method records) set, for ``camo optimize --spec dest``; SystemExit naming a field the spec lacks."""
    import tomli_w

    from camo.cli import build_parser
    from camo.optimize_cli import spec_of
    from optimizer.optimise.spec import RunSpec

    d = spec_of(build_parser().parse_args(["optimize", *args])).to_dict()
    for path, value in fields.items():
        table, key = path.split(".")
        if key not in d.get(table, {}):
            raise SystemExit(f"bench_giveaways: the run spec has no field {path}")
        d[table][key] = value
    RunSpec.from_dict(d, where=str(dest)).validate()  # the edited spec is one camo optimize accepts
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(tomli_w.dumps(d), encoding="utf-8")
    return dest


def optimise(out: Path, scene: str, arms, budget: list[str], mean: bool = True,
             iterations: dict[str, int] | None = None) -> None:
    for arm in [*arms, "mean"] if mean else arms:
        run = out / "runs" / f"{name_of(scene)}-{arm}"
        if (run / "config.toml").is_file():
            continue
        if arm == "mean":
            camo("optimize", scene, "--method", "mean", "--out", str(run), *SIZE, "--quiet")
        elif arm in BASELINE_ARMS:
            camo("optimize", scene, *BASELINE_ARMS[arm], "--out", str(run), *SIZE, "--quiet")
        elif arm not in ARMS:
            # an arm made by other code (e.g. ``pre_fix``: today's arm run by an older checkout) is filed there by hand
            raise SystemExit(f"bench_giveaways: no run {run} and no arm {arm!r} to make it")
        else:
            own = ["--iterations", str(iterations[arm])] if iterations and arm in iterations else budget
            args = [scene, "--out", str(run), *SIZE, "--displacement-resolution", "64", *own, *ARMS[arm], "--quiet"]
            if arm in SPEC_FIELDS:
                spec = spec_file(args, SPEC_FIELDS[arm], run.with_name(f"{run.name}.spec.toml"))
                args = ["--spec", str(spec), "--out", str(run), "--quiet"]
            camo("optimize", *args)


def evaluate(out: Path, scene: str, arms, spp: int, views: int, into: str = "eval", mean: bool = True) -> None:
    ev = out / into / name_of(scene)
    if (ev / "metrics.parquet").is_file():
        return
    runs = [str(out / "runs" / f"{name_of(scene)}-{a}") for a in ([*arms, "mean"] if mean else arms)]
    camo("evaluate", *runs, "--out", str(ev), "--spp", str(spp), "--views", str(views),
         "--metrics", "psnr,lpips_proxy,detail_ratio,tint", "--quiet")


def _seconds_per_iteration(run: Path) -> float:
    """Median seconds of a Stage 1 iteration (log.jsonl), NaN for a method without iterations."""
    import json

    secs = [r["seconds"] for r in map(json.loads, (run / "log.jsonl").read_text().splitlines())
            if r.get("stage") == 1 and "seconds" in r] if (run / "log.jsonl").is_file() else []
    return float(sorted(secs)[len(secs) // 2]) if secs else float("nan")  # median: the first one compiles


def _ior(run: Path) -> float:
    """The shared index of refraction a run's result renders with: the clear-glass search's choice
    (``summary.json``'s ``clear_search``), else its spec's ``appearance.eta``; NaN for a method without one."""
    import json
    import tomllib

    summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").is_file() else {}
    if summary.get("clear_search"):
        return float(summary["clear_search"]["chosen_eta"])
    config = tomllib.loads((run / "config.toml").read_text()) if (run / "config.toml").is_file() else {}
    return float(config["appearance"]["eta"]) if config.get("method") in ("ours", "transparent") \
        and "appearance" in config \
        else float("nan")


def real_lpips(renders: Path) -> float:
    """Mean real LPIPS (v0.1, AlexNet, installed weights) of a run's evaluation renders, with against without the
    object, over the whole 64 px frames (the saved PNGs; NaN when the weights are not installed)."""
    import numpy as np
    from PIL import Image

    try:
        from evaluation.metrics.lpips import load_lpips, lpips
        model = load_lpips("alex")
    except Exception:  # noqa: BLE001 - weights missing: the column says NaN
        return float("nan")
    vals = []
    for o in sorted(renders.glob("view_*_obj.png")):
        x = np.asarray(Image.open(o).convert("RGB"), np.float32) / 255
        y = np.asarray(Image.open(o.with_name(o.name.replace("_obj", "_bg"))).convert("RGB"), np.float32) / 255
        vals.append(float(lpips(x, y, model)[0]))
    return float(np.mean(vals)) if vals else float("nan")


def measures(out: Path, scenes, arms):
    """One row per scene and arm (and Mean) evaluated under ``out``: crop PSNR, LPIPS-proxy, real LPIPS of the
    frames, detail ratio, tint (CIELAB ΔE), shadow share, method seconds, seconds per Stage 1 iteration, IOR
    (a pandas DataFrame; what :func:`table` prints)."""
    import pandas as pd

    from evaluation.giveaway import split_eval_dir

    rows = []
    for scene in scenes:
        # eval/SCENE, and eval_*/SCENE for arms added later (same seed: the same cameras and render seeds)
        evals = [d for d in sorted(out.glob(f"eval*/{scene}")) if (d / "metrics.parquet").is_file()]
        if not evals:
            continue
        t = pd.concat([read_parquet(d / "metrics.parquet") for d in evals])
        t = t[t.region == "crop"]
        # the shadow's share of the crop's squared error: the object / shadow / rest split (evaluation.giveaway),
        # recomputed from the saved renders so that evaluations made before the split had columns count too
        split = pd.concat([split_eval_dir(d) for d in evals])
        split = split[split.region == "crop"]
        for arm in [*arms, "mean"]:
            r = t[t.run == f"{scene}-{arm}"]
            if r.empty:
                continue
            sp = split[split.run == f"{scene}-{arm}"]
            parts = sp[["sqerr_object", "sqerr_shadow", "sqerr_rest"]].sum(axis=1).clip(lower=1e-12)
            rows.append({"scene": scene, "arm": arm, "psnr": r.psnr.mean(), "lpips_proxy": r.lpips_proxy.mean(),
                         "shadow": float((sp.sqerr_shadow / parts).mean()),
                         "detail_ratio": r.detail_ratio.mean(), "tint": r.tint.mean(),
                         "lpips": next((real_lpips(d / "renders" / f"{scene}-{arm}") for d in evals
                                        if (d / "renders" / f"{scene}-{arm}").is_dir()), float("nan")),
                         "seconds": float(r.seconds_method.iloc[0]) if len(r) else float("nan"),
                         "s_per_it": _seconds_per_iteration(out / "runs" / f"{scene}-{arm}"),
                         "ior": _ior(out / "runs" / f"{scene}-{arm}")})
    return pd.DataFrame(rows)


def table(out: Path, scenes, arms, df=None) -> str:
    """The give-away table (Markdown) of :func:`measures`' rows (``df``, measured here when None) and each arm's mean
    over the scenes."""
    df = measures(out, scenes, arms) if df is None else df
    lines = ["| scene | arm | crop PSNR↑ | LPIPS-proxy↓ | LPIPS (frame)↓ | detail ratio (1 best) | tint ΔE↓ | shadow share | "
             "method s | s / Stage 1 it | IOR |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in df.itertuples():
        ior = "" if r.ior != r.ior else f"{r.ior:g}"  # NaN: a method without an IOR (Mean)
        lines.append(f"| {r.scene} | {r.arm} | {r.psnr:.2f} | {r.lpips_proxy:.3f} | {r.lpips:.3f} | {r.detail_ratio:.2f} | "
                     f"{r.tint:.2f} | {r.shadow:.2f} | {r.seconds:.0f} | {r.s_per_it:.2f} | {ior} |")
    def mean_row(label: str, arm: str, g) -> str:
        return (f"| **{label}** | {arm} | {g.psnr.mean():.2f} | {g.lpips_proxy.mean():.3f} | {g.lpips.mean():.3f} | "
                f"{g.detail_ratio.mean():.2f} | {g.tint.mean():.2f} | {g.shadow.mean():.2f} | {g.seconds.mean():.0f} | "
                f"{g.s_per_it.mean():.2f} | |")

    base = df[df.arm == "today"]
    for arm, g in df.groupby("arm", sort=False):
        lines.append(mean_row(f"mean of {len(g)}", arm, g))
        # an arm measured on fewer scenes than today's: today's mean on the same scenes beside it (means over
        # different scenes do not compare)
        if arm != "today" and not base.empty and set(g.scene) != set(base.scene):
            same = base[base.scene.isin(set(g.scene))]
            if len(same) == len(g):
                lines.append(mean_row(f"mean of {len(g)}", "today, same scenes", same))
    return "\n".join(lines)


#: the issue's band of the detail ratio (1 = the ground's own texture energy)
DETAIL_BAND = (0.8, 1.25)


def pareto_front(g) -> list[bool]:
    """Per row of ``g`` (one scene's arms: columns ``psnr``, ``lpips_proxy``, ``detail_ratio``, ``tint``): whether no
    other row is at least as good on all four of crop PSNR (higher), LPIPS-proxy (lower), the detail ratio's distance
    from 1 (``|ln ratio|``, lower) and tint (lower) and better on one (the trade-off's non-dominated points).

    >>> import pandas as pd
    >>> pareto_front(pd.DataFrame({"psnr": [33, 32, 31], "lpips_proxy": [.16, .2, .2], "detail_ratio": [.6, 1, 1],
    ...                            "tint": [2, 1.4, 1.5]}))
    [True, True, False]
    """
    import numpy as np

    x = np.c_[-g.psnr.to_numpy(float), g.lpips_proxy.to_numpy(float), np.abs(np.log(g.detail_ratio.to_numpy(float))),
              g.tint.to_numpy(float)]
    return [not any((x[j] <= x[i]).all() and (x[j] < x[i]).any() for j in range(len(x)) if j != i)
            for i in range(len(x))]


def against_base(df, base: str = "today", psnr_tol: float = 0.3, lpips_tol: float = 0.01):
    """Each arm of :func:`measures`' rows (Mean left out) against ``base`` of the same scene and run: the crop PSNR and
    LPIPS-proxy differences, the tint as a share of the base's, whether the detail ratio is in :data:`DETAIL_BAND`,
    whether the arm is on the scene's :func:`pareto_front`, and ``meets``: in the band, tint below the base's, crop PSNR
    at most ``psnr_tol`` dB and LPIPS-proxy at most ``lpips_tol`` above the base's (one run's noise: ~0.1 dB on meadow,
    up to ~0.6 dB and 0.017 on gravel, section "Run-to-run noise"). A scene without the base arm is left out."""
    import pandas as pd

    rows = []
    for scene, g in df[df.arm != "mean"].groupby("scene", sort=False):
        b = g[g.arm == base]
        if b.empty:
            continue
        b = b.iloc[0]
        for r, front in zip(g.itertuples(), pareto_front(g)):
            band = DETAIL_BAND[0] <= r.detail_ratio <= DETAIL_BAND[1]
            d_psnr, d_lp = r.psnr - b.psnr, r.lpips_proxy - b.lpips_proxy
            rows.append({"scene": scene, "arm": r.arm, "psnr": r.psnr, "d_psnr": d_psnr, "d_lpips": d_lp,
                         "detail_ratio": r.detail_ratio, "in_band": band, "tint": r.tint,
                         "tint_share": r.tint / b.tint, "shadow": r.shadow, "pareto": front,
                         "meets": bool(r.arm != base and band and r.tint < b.tint and d_psnr >= -psnr_tol
                                       and d_lp <= lpips_tol)})
    return pd.DataFrame(rows)


def tradeoff_table(df, base: str = "today") -> str:
    """Markdown: :func:`against_base`'s rows (the trade-off's points against ``base`` in the same run)."""
    t = against_base(df, base)
    lines = [f"| scene | arm | crop PSNR | Δ PSNR vs {base} | Δ LPIPS-proxy | detail ratio | tint ΔE (share of {base}'s) "
             "| shadow share | Pareto | meets |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in t.itertuples():
        detail = f"**{r.detail_ratio:.2f}**" if r.in_band else f"{r.detail_ratio:.2f}"
        lines.append(f"| {r.scene} | {r.arm} | {r.psnr:.2f} | {r.d_psnr:+.2f} | {r.d_lpips:+.3f} | {detail} | "
                     f"{r.tint:.2f} ({r.tint_share:.0%}) | {r.shadow:.2f} | {'yes' if r.pareto else 'no'} | "
                     f"{'**yes**' if r.meets else 'no'} |")
    return "\n".join(lines)


def tradeoff_plot(df, dest: Path, base: str = "today", curve=()) -> Path:
    """A small PNG of the trade-off, one row per scene: crop PSNR against the detail ratio (the band shaded) and
    against tint ΔE (below half of ``base``'s shaded); each arm a labelled point (green: on the Pareto front),
    ``base`` a red star, the dashed line ``base``'s PSNR minus 0.3 dB, and the arms of ``curve`` joined in that order
    (e.g. a sweep of one lever)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = against_base(df, base)
    scenes = list(dict.fromkeys(t.scene))
    fig, axes = plt.subplots(len(scenes), 2, figsize=(7.5, 2.6 * len(scenes)), squeeze=False)
    for row, scene in zip(axes, scenes):
        g = t[t.scene == scene]
        b = g[g.arm == base].iloc[0]
        for ax, x, label in ((row[0], "detail_ratio", "detail ratio (band 0.8-1.25)"), (row[1], "tint", "tint ΔE")):
            if x == "detail_ratio":
                ax.axvspan(*DETAIL_BAND, color="0.9")
            else:
                ax.axvspan(0, b.tint / 2, color="0.9")  # the tint halved
            ax.axhline(b.psnr - 0.3, ls="--", lw=0.8, color="0.4")
            line = [g[g.arm == c].iloc[0] for c in curve if (g.arm == c).any()]
            if len(line) > 1:
                ax.plot([getattr(r, x) for r in line], [r.psnr for r in line], "-", lw=0.8, color="0.5")
            for r in g.itertuples():
                ax.plot(getattr(r, x), r.psnr, "*" if r.arm == base else "o", ms=10 if r.arm == base else 5,
                        color="C3" if r.arm == base else ("C2" if r.pareto else "C0"))
                ax.annotate(LABELS.get(r.arm, r.arm), (getattr(r, x), r.psnr), fontsize=6, xytext=(3, 2),
                            textcoords="offset points")
            ax.set_xlabel(label, fontsize=8)
            ax.set_ylabel(f"{scene}: crop PSNR (dB)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.tight_layout()
    dest.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(dest, dpi=90)
    plt.close(fig)
    return dest


def shadow_table(out: Path, scenes, arms) -> str:
    """What the cast shadow costs, per scene and arm (crop rows, mean over views): the shadow's share of the crop's
    pixels, of its squared error and of its real LPIPS (the Shapley split of :mod:`evaluation.giveaway`, AlexNet; NaN
    without the weights), the crop PSNR of the saved 8-bit renders and the crop PSNR the same renders would have if
    the shadow's pixels matched the background (the object's and the rest's error only): the most that a change
    of the object's material, which leaves its shadow as it is, could win."""
    import numpy as np
    import pandas as pd

    from evaluation.giveaway import split_eval_dir

    try:
        from evaluation.metrics.lpips import load_lpips, lpips
        model = load_lpips("alex")
        lpips_fn = lambda x, y: lpips(x, y, model).tolist()  # noqa: E731
    except Exception:  # noqa: BLE001 - weights missing: the LPIPS column says NaN
        lpips_fn = None
    lines = ["| scene | arm | shadow pixels | shadow share of squared error | shadow share of LPIPS | crop PSNR (8 bit) | "
             "crop PSNR, shadow matched |", "|---|---|---|---|---|---|---|"]
    rows = []
    for scene in scenes:
        evals = [d for d in sorted(out.glob(f"eval*/{scene}")) if (d / "metrics.parquet").is_file()]
        for arm in arms:
            d = next((d for d in evals if (d / "renders" / f"{scene}-{arm}").is_dir()), None)
            if d is None:
                continue
            sp = split_eval_dir(d, lpips_fn)
            sp = sp[(sp.region == "crop") & (sp.run == f"{scene}-{arm}")]
            px = sp[["pixels_object", "pixels_shadow", "pixels_rest"]].sum(axis=1)
            mse = sp[["sqerr_object", "sqerr_shadow", "sqerr_rest"]].sum(axis=1)
            lp = sp[["lpips_object", "lpips_shadow", "lpips_rest"]].sum(axis=1)
            r = {"scene": scene, "arm": arm, "px": float((sp.pixels_shadow / px).mean()),
                 "se": float((sp.sqerr_shadow / mse.clip(lower=1e-12)).mean()),
                 "lp": float((sp.lpips_shadow / lp.where(lp > 0)).mean()),
                 "psnr": float((-10 * np.log10(mse.clip(lower=1e-12))).mean()),
                 "psnr_ns": float((-10 * np.log10((mse - sp.sqerr_shadow).clip(lower=1e-12))).mean())}
            rows.append(r)
            lines.append(f"| {scene} | {arm} | {r['px']:.2f} | {r['se']:.2f} | {r['lp']:.2f} | {r['psnr']:.2f} | "
                         f"{r['psnr_ns']:.2f} |")
    df = pd.DataFrame(rows)
    for arm, g in (df.groupby("arm", sort=False) if len(df) else ()):
        lines.append(f"| **mean of {len(g)}** | {arm} | {g.px.mean():.2f} | {g.se.mean():.2f} | {g.lp.mean():.2f} | "
                     f"{g.psnr.mean():.2f} | {g.psnr_ns.mean():.2f} |")
    return "\n".join(lines)


LABELS = {"today": "ours (today)", "shadow4": "ours, shadow x4", "shadow4_t95": "shadow x4, T0=0.95",
          "transparent": "transparent", "transparent_eta105": "transparent 1.05", "transparent_eta105_white": "clear white 1.05",
          "coarse0": "ours, no coarse level", "large_steps": "ours, large steps", "large_steps_t0.3": "large steps, T0=0.3",
          "today_t0.3": "ours, T0=0.3", "lpips": "ours + LPIPS", "eta1.2": "ours, IOR 1.2",
          "detail8": "ours + detail 8", "detail32": "ours + detail 32", "blur0": "ours, no grad blur",
          "map256": "ours, map 256", "map256_detail8": "map 256 + detail 8",
          "clear": "ours, IOR 1.05, R0 0.2", "auto": "ours, clear chosen per scene",
          "tint4": "ours + tint 4", "tint16": "ours + tint 16", "tint4_auto": "tint 4 + clear per scene",
          "tint16_auto": "tint 16 + clear per scene", "tint1_auto": "tint 1 + clear per scene", "tint4_s2": "ours + local tint 4",
          "coarse1": "ours + coarse 1", "coarse1_auto": "coarse 1 + clear per scene",
          "coarse4_auto": "coarse 4 + clear per scene", "coarse1_lr3_auto": "coarse 1 (lr 3e-2) + clear",
          "coarse1_tint1_auto": "coarse 1 + tint 1 + clear",
          "coarse1_auto_r35": "coarse 1 + clear R0 0.35", "coarse1_auto_r5": "coarse 1 + clear R0 0.5", "coarse1_auto_r5_c0": "clear R0 0.5, no loss clamp",
          "coarse1_auto_r10": "coarse 1 + clear R0 1.0", "coarse1_auto_r7": "coarse 1 + clear R0 0.7",
          "coarse1_auto_r5_eta102": "clear IOR 1.02, R0 0.5",
          "coarse1_auto_r5_keepdisp": "clear R0 0.5, disp. kept", "coarse1_auto_r5_seed1": "clear R0 0.5, seed 1", "clear102_r5": "IOR 1.02 imposed, R0 0.5", "coarse1_lr3": "ours + coarse 1 (lr 3e-2)",
          "grain": "ours + grain 1", "grain05": "ours + grain 0.5", "grain_s2": "grain 1, sharpened 2",
          "lr2": "ours, map rate 2e-2", "lr2_auto": "map rate 2e-2 + clear",
          "pre_fix": "ours, warm start before fix",
          "warmt1": "T in [0.75, 1]", "warmt01": "T in [0, 1]", "warmt02": "T in [0.2, 1]", "warmt035": "T in [0.35, 1]", "warmt065": "T in [0.65, 1]", "warmt05_r5": "T in [0.5, 1], R0 0.5",
          "warmt065_r5": "T in [0.65, 1], R0 0.5", "warmt01_r5": "T in [0, 1], R0 0.5",
          "warmt05": "T in [0.5, 1]", "warmt01_sw4": "T in [0, 1], shadow x4",
          "warmsun": "T lowered facing away", "warmshadow": "T lowered unseen shadow",
          "mean": "Mean"}


def sheet_path(docs: Path, section: str, scene: str, sheet_arms: bool) -> Path | None:
    """Where a section's contact sheet of ``scene`` goes: the first table's (section ``table``) always, as
    ``giveaways_SCENE.png``; another section's only when its arms were named (``--sheet-arms``), as
    ``giveaways_SECTION_SCENE.png``; the shadow table has none.

    >>> sheet_path(Path("d"), "table", "meadow", False).name, sheet_path(Path("d"), "caustic", "meadow", True).name
    ('giveaways_meadow.png', 'giveaways_caustic_meadow.png')
    >>> sheet_path(Path("d"), "caustic", "meadow", False) is None, sheet_path(Path("d"), "shadow", "meadow", True)
    (True, None)
    """
    if section == "table":
        return docs / f"giveaways_{scene}.png"
    return docs / f"giveaways_{section}_{scene}.png" if sheet_arms and section != "shadow" else None


def contact_sheet(ev: Path, scene: str, arms, dest: Path, zoom: int = 3) -> Path:
    """One PNG per scene: a row per evaluation view, columns background | each arm | Mean (the converged
    evaluation renders, nearest-neighbour zoomed so single-pixel speckle stays visible). An arm's renders are
    looked up in ``ev`` and then in the other ``eval*/SCENE`` directories beside it (arms evaluated later, same
    seed: the same views)."""
    import numpy as np
    from PIL import Image, ImageDraw

    dirs = [ev, *(d for d in sorted(ev.parent.parent.glob(f"eval*/{scene}")) if d != ev)]
    where = {}
    for a in [*arms, "mean"]:
        found = next((d / "renders" / f"{scene}-{a}" for d in dirs if (d / "renders" / f"{scene}-{a}").is_dir()), None)
        if found is not None:
            where[a] = found
    arms = [a for a in arms if a in where]
    cols = [("background", where[arms[0]], "bg")] + [(LABELS.get(a, a), where[a], "obj")
                                                      for a in [*arms, "mean"] if a in where]
    views = sorted({p.name[:7] for p in where[arms[0]].glob("view_*_obj.png")})
    tiles = [[np.asarray(Image.open(d / f"{v}_{kind}.png").convert("RGB")) for _, d, kind in cols] for v in views]
    h, w = tiles[0][0].shape[:2]
    th, tw, pad, top = h * zoom, w * zoom, 4, 22
    sheet = Image.new("RGB", (len(cols) * (tw + pad) + pad, top + len(views) * (th + pad) + pad), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for c, (label, _, _) in enumerate(cols):
        draw.text((pad + c * (tw + pad) + 4, 5), label, fill=(0, 0, 0))
    for r, row in enumerate(tiles):
        for c, img in enumerate(row):
            tile = Image.fromarray(img).resize((tw, th), Image.NEAREST)
            sheet.paste(tile, (pad + c * (tw + pad), top + pad + r * (th + pad)))
    dest.parent.mkdir(parents=True, exist_ok=True)
    if dest.suffix.lower() in (".jpg", ".jpeg"):
        sheet.save(dest, quality=85, optimize=True)  # JPEG: the sheets of the newer sections (a tenth of the PNG's bytes)
    else:
        sheet.save(dest, optimize=True)
    return dest


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--scenes", default=",".join(SCENES), help="built-in scene names or scene pack files (e.g. "
                    "packs/real/cross/sky-cone.toml: a pair of the real cross), comma-separated")
    ap.add_argument("--arms", default=",".join(ARMS))
    ap.add_argument("--iterations", type=int, default=24, help="Stage 1 iterations of every optimised arm")
    ap.add_argument("--seconds", type=float, help="instead: this time budget for every optimised arm")
    ap.add_argument("--arm-iterations", default="", help="ARM=N,...: Stage 1 iterations of these arms (equal "
                    "seconds for an arm whose iteration costs more, e.g. lpips=20)")
    ap.add_argument("--no-mean", action="store_true", help="do not run the Mean baseline (another run of this "
                    "script does)")
    ap.add_argument("--eval-spp", type=int, default=512)
    ap.add_argument("--eval-views", type=int, default=4)
    ap.add_argument("--eval-dir", default="eval", help="evaluate into OUT/EVAL_DIR/SCENE (arms added later: "
                    "eval_NAME; the table and the contact sheets read every eval*/SCENE)")
    ap.add_argument("--sheet-arms", help="the arms of the contact sheets (comma-separated; default: --arms)")
    ap.add_argument("--shadow-table", action="store_true", help="write the shadow's cost per scene and arm "
                    "(shadow_table; what section 'shadow' writes) between this --section's markers; no sheets")
    ap.add_argument("--sheet-format", choices=("png", "jpg"), default="png", help="the contact sheets' format "
                    "(jpg: quality 85, small)")
    ap.add_argument("--tradeoff", action="store_true", help="also each arm against today in the same run "
                    "(tradeoff_table: Δ PSNR, Δ LPIPS-proxy, detail band, tint share, Pareto front, meets the targets) "
                    "below the table, and with --docs its plot giveaways_SECTION_tradeoff.png")
    ap.add_argument("--curve", help="with --tradeoff: the arms the plot joins by a line, in this order (a sweep)")
    ap.add_argument("--phase", choices=("all", "optimize", "evaluate", "table"), default="all")
    ap.add_argument("--docs", help="also write the contact sheets (giveaways_SCENE.png) and the table (between the "
                    "markers of giveaways.md) here, e.g. docs/results")
    ap.add_argument("--section", default="table", help="the table goes between the markers "
                    "'<!-- bench_giveaways: SECTION -->' and '<!-- /bench_giveaways -->' of giveaways.md; only the "
                    "default section ('table') writes the contact sheets giveaways_SCENE.png, another one with --sheet-arms "
                    "giveaways_SECTION_SCENE.png (another section: e.g. a second "
                    "evaluation of the same runs at a higher --eval-spp in another --out; 'shadow': the shadow's cost "
                    "per scene and arm, shadow_table, instead of the give-away table)")
    a = ap.parse_args(argv)
    out, scenes, arms = Path(a.out), a.scenes.split(","), a.arms.split(",")
    budget = ["--time-budget", str(a.seconds)] if a.seconds else ["--iterations", str(a.iterations)]
    for scene in scenes:  # scene by scene, so that a partial run already gives whole rows
        if a.phase in ("all", "optimize"):
            own = dict((k, int(v)) for k, v in (p.split("=") for p in a.arm_iterations.split(",") if p))
            optimise(out, scene, arms, budget, mean=not a.no_mean, iterations=own)
        if a.phase in ("all", "evaluate"):
            evaluate(out, scene, arms, a.eval_spp, a.eval_views, a.eval_dir, mean=not a.no_mean)
    if a.phase in ("all", "evaluate", "table"):
        names = [name_of(s) for s in scenes]
        shadow = a.section == "shadow" or a.shadow_table
        df = None if shadow else measures(out, names, arms)
        text = shadow_table(out, names, arms) if shadow else table(out, names, arms, df)
        if a.tradeoff and not shadow:
            text += "\n\n" + tradeoff_table(df)
        print(text)
        if a.docs:
            docs = Path(a.docs)
            if a.tradeoff and not shadow:
                print(tradeoff_plot(df, docs / f"giveaways_{a.section}_tradeoff.png",
                                    curve=a.curve.split(",") if a.curve else ()))
            for scene in names if not shadow else []:
                dest = sheet_path(docs, a.section, scene, bool(a.sheet_arms))
                if dest is not None:
                    dest = dest.with_suffix("." + a.sheet_format)
                    print(contact_sheet(out / "eval" / scene, scene,
                                        a.sheet_arms.split(",") if a.sheet_arms else arms, dest))
            doc = docs / "giveaways.md"
            start, end = f"<!-- bench_giveaways: {a.section} -->", "<!-- /bench_giveaways -->"
            body = doc.read_text(encoding="utf-8") if doc.is_file() else f"{start}\n{end}\n"
            if start not in body:
                raise SystemExit(f"{doc}: no '{start}' marker")
            i = body.index(start) + len(start)
            j = body.index(end, i)
            doc.write_text(body[:i] + "\n" + text + "\n" + body[j:], encoding="utf-8")  # the table between the markers
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
