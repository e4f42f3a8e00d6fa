"""Evaluation quality vs cost: how far each metric is from a high-spp reference, and what it costs.

Run: ``python bench/bench_eval_tradeoff.py [RUN_DIR] [--spp 4,16,64,256] [--resolutions 64,128] [--ref-spp 1024]
[--views 4] [--out DIR]``. Without RUN_DIR a small run directory is made first (``camo optimize gravel``, a few
iterations at 32 px).

For each resolution, the run is evaluated exactly as ``camo evaluate`` does it (jittered novel views, the
planner's evaluation path tracer, background and with-object renders with common random numbers, 8-bit sRGB,
``full`` frame and GANmouflage ``crop``) at every spp in ``--spp`` and once at ``--ref-spp`` with an
independent sampler seed. Reported per (resolution, spp, metric): the metric's mean over the views, its mean
absolute deviation from the reference (per view, then averaged), and the seconds spent rendering (background +
with-object + mask, all views) and computing that metric (all views, both regions). Prints a Markdown table
and saves ``eval_tradeoff.png`` (time vs relative deviation, log-log) and ``eval_tradeoff.csv`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation.evaluate import REGIONS, srgb8  # noqa: E402

DEFAULT_METRICS = "psnr,ssim,lpips_proxy,sifid_proxy"


def make_run(root: Path) -> Path:
    from camo.cli import main

    out = root / "bench_run"
    if not (out / "config.toml").is_file():
        rc = main(["optimize", "gravel", "--out", str(out), "--iterations", "4", "--views", "4", "--resolution", "32",
                   "--map-resolution", "64", "--displacement-resolution", "32", "--target-vertices", "1500",
                   "--spp", "2", "--target-spp", "16", "--quiet"])
        if rc != 0:
            raise SystemExit(rc)
    return out


def regions_of(mask: np.ndarray):
    from evaluation.metrics import object_crop_box

    out = {"full": (0, 0, mask.shape[0], mask.shape[1])}
    if mask.any():
        y0, x0, side = object_crop_box(mask)
        out["crop"] = (y0, x0, side, side)
    return out


def score(obj: np.ndarray, bg: np.ndarray, masks: np.ndarray, names: list[str], weights: dict, repeats: int = 1):
    """``{(metric, region): [value per view]}`` and ``{metric: seconds}`` (each call timed best of ``repeats``)
    for linear renders ``(V, H, W, 3)``."""
    from evaluation.metrics import compute_metrics

    vals: dict[tuple[str, str], list[float]] = {(m, r): [] for m in names for r in REGIONS}
    secs = {m: 0.0 for m in names}
    for v in range(len(obj)):
        o8, b8 = srgb8(obj[v]), srgb8(bg[v])
        for region, (y0, x0, h, w) in regions_of(masks[v]).items():
            a, b = o8[y0:y0 + h, x0:x0 + w], b8[y0:y0 + h, x0:x0 + w]
            for m in names:
                best = float("inf")
                for _ in range(max(1, repeats)):
                    t = time.perf_counter()
                    value = float(compute_metrics(a, b, [m], weights)[m])
                    best = min(best, time.perf_counter() - t)
                vals[(m, region)].append(value)
                secs[m] += best
    return vals, secs


def render(run, assets, env, cams, plan, spp: int, seed: int):
    """Background, with-object image and mask through evaluation.views (fresh renderer: no cache)."""
    from evaluation.views import ViewRenderer, object_mesh_of

    r = ViewRenderer(spp, seed)
    t = time.perf_counter()
    bg = r.background(run.pack, env, cams, plan.integrator)
    objr = r.with_object(env, lambda: object_mesh_of(run, assets), cams, plan.integrator)
    return bg.image, objr.image, objr.mask, time.perf_counter() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", nargs="?", help="a run directory (default: make a small one)")
    ap.add_argument("--spp", default="4,16,64,256")
    ap.add_argument("--resolutions", default="64,128")
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--metrics", default=DEFAULT_METRICS)
    ap.add_argument("--out", help="folder for the plot and CSV (default: a folder in the temp dir)")
    ap.add_argument("--threads", type=int)
    ap.add_argument("--repeats", type=int, default=3, help="time each metric call best of this many")
    args = ap.parse_args(argv)

    from optimizer import backend
    from optimizer.scenes.environments import get_environment
    from evaluation.evaluate import parse_metrics
    from evaluation.views import evaluation_cameras, evaluation_plan, load_result, load_run

    out = Path(args.out or Path(tempfile.gettempdir()) / "camo_bench_eval_tradeoff")
    out.mkdir(parents=True, exist_ok=True)
    run_dir = Path(args.run_dir) if args.run_dir else make_run(out)
    names = parse_metrics(args.metrics)
    spps = [int(s) for s in args.spp.split(",")]
    resolutions = [int(s) for s in args.resolutions.split(",")]
    info = backend.init(threads=args.threads)
    run = load_run(run_dir)
    assets = load_result(run)
    env = get_environment(run.pack.environment)
    plan = evaluation_plan(run.pack, env)
    weights: dict = {}
    import torch

    rows = []
    for res in resolutions:
        cams = evaluation_cameras(run.pack, args.views, 0.25, args.seed, (res, res)).cams
        bg, obj, mask, t_ref = render(run, assets, env, cams, plan, args.ref_spp, args.seed + 1)
        ref, _ = score(obj, bg, mask, names, weights)
        print(f"# {res} px: reference {args.ref_spp} spp rendered in {t_ref:.1f} s", file=sys.stderr)
        for spp in spps:
            bg, obj, mask_s, t_render = render(run, assets, env, cams, plan, spp, args.seed)
            # the crop comes from the reference mask so both score the same pixels (masks are ray-cast: equal)
            vals, secs = score(obj, bg, mask, names, weights, args.repeats)
            for m in names:
                row = {"resolution": res, "spp": spp, "metric": m, "seconds_render": t_render,
                       "seconds_metric": secs[m], "mask_equal": bool(np.array_equal(mask, mask_s))}
                for region in REGIONS:
                    v, r = np.asarray(vals[(m, region)]), np.asarray(ref[(m, region)])
                    row[f"{region}_value"] = float(v.mean()) if v.size else float("nan")
                    row[f"{region}_ref"] = float(r.mean()) if r.size else float("nan")
                    row[f"{region}_dev"] = float(np.abs(v - r).mean()) if v.size else float("nan")
                rows.append(row)

    lines = [f"Run `{run_dir}` ({run.scene}, {run.method}, ablation {run.ablation_label}); {args.views} jittered "
             f"views; integrator {plan.integrator}; reference {args.ref_spp} spp (independent seed); backend "
             f"{info.variant}, {info.threads} threads, torch {torch.get_num_threads()} threads. |Δ| = mean over "
             "views of |metric - reference|; seconds for all views (render: background + with-object + mask; "
             f"metric: both regions, each call best of {args.repeats}).", "",
             "| px | spp | metric | full | full |Δ| | crop | crop |Δ| | ref (crop) | s render | s metric |",
             "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        f = "{:.2f}" if r["metric"] == "psnr" else "{:.4f}"
        lines.append(f"| {r['resolution']} | {r['spp']} | {r['metric']} | {f.format(r['full_value'])} | "
                     f"{f.format(r['full_dev'])} | {f.format(r['crop_value'])} | {f.format(r['crop_dev'])} | "
                     f"{f.format(r['crop_ref'])} | {r['seconds_render']:.2f} | {r['seconds_metric']:.3f} |")
    table = "\n".join(lines)
    print(table)

    import pandas as pd

    pd.DataFrame(rows).to_csv(out / "eval_tradeoff.csv", index=False)
    (out / "eval_tradeoff.md").write_text(table + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    markers = ["o", "s", "^", "D"]
    for mi_, m in enumerate(names):
        for ri, res in enumerate(resolutions):
            rs = [r for r in rows if r["metric"] == m and r["resolution"] == res]
            x = [r["seconds_render"] + r["seconds_metric"] for r in rs]
            y = [max(r["crop_dev"] / max(abs(r["crop_ref"]), 1e-12), 1e-6) for r in rs]
            ax.loglog(x, y, marker=markers[ri % len(markers)], color=f"C{mi_}", label=f"{m} @ {res} px")
            for xi, yi, r in zip(x, y, rs):
                ax.annotate(str(r["spp"]), (xi, yi), fontsize=6, xytext=(2, 2), textcoords="offset points")
    ax.set_xlabel(f"seconds for {args.views} views (render + metric)")
    ax.set_ylabel("|metric - reference| / |reference| (crop)")
    ax.set_title("evaluation spp: time vs deviation from the reference")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "eval_tradeoff.png")
    print(f"\nwrote {out / 'eval_tradeoff.png'}, {out / 'eval_tradeoff.csv'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
