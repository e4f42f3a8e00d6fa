"""How far the weight-free metrics agree with the real LPIPS: Kendall's tau and Spearman's rho per scene and pooled,
and the method pairs where a proxy and LPIPS disagree about which method hides better; plus where the object gives
itself away (object / shadow / rest) per scene and method. Writes ``docs/results/metric_agreement.md``.

    camo grid run grids/real_cross_quick.toml --out grid_real_cross_quick --workers 1   # all 64 real pairs, cheaply
    camo grid run grids/all_scenes.toml --out grid_all --workers 2
    python bench/metric_agreement.py --grid real_cross_quick=grid_real_cross_quick --grid built-in=grid_all \\
        --out docs/results/metric_agreement.md --figure 'built-in:meadow=what the pictures show'

(``grids/real_cross.toml``, the same 64 pairs at the shipped settings, is read the same way when it has been run.)
Reads the evaluation directories of the grids' finished cells (``cells/*/eval/*``; an unfinished grid gives what
has finished, and the page says how many cells and how many scenes with every method that is); the object / shadow / rest columns are recomputed from
their saved renders with this checkout's ``evaluation/giveaway.py``. Rows: the object crop (GANmouflage protocol). Every
metric is oriented as a distance (lower = hides better): PSNR and SSIM enter negated, so a positive correlation
means agreement with LPIPS. Per scene, the correlations run over that scene's crop rows (every method's views);
"pooled" runs over every row of the grid, and "methods pooled" over the per-run means (one point per scene and
method). A disagreement is a pair of methods in one scene whose mean over the views LPIPS orders one way and the
metric the other (ties count as agreement).
"""

from __future__ import annotations

import argparse
import datetime
import math
import shlex
import sys
from itertools import combinations
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: The metrics set against LPIPS, with their display names; oriented as distances (sign).
OTHERS = (("lpips_proxy", "LPIPS-proxy", 1.0), ("ssim", "SSIM", -1.0), ("psnr", "PSNR", -1.0),
          ("sifid_proxy", "SIFID-proxy", 1.0))
PROXIES = ("lpips_proxy", "sifid_proxy")


def eval_dirs(grid: Path) -> list[Path]:
    return sorted(p.parent for p in grid.glob("cells/*/eval/*/metrics.parquet"))


def resplit(df, dirs: list[Path]):
    """Recompute the object / shadow / rest columns from the saved renders with this checkout's
    evaluation/giveaway.py (so cells evaluated by an older version agree with the current definition)."""
    import pandas as pd

    from evaluation.giveaway import split_eval_dir
    from evaluation.evaldir import SPLIT_COLUMNS
    from evaluation.metrics import load_lpips, lpips

    model = load_lpips("alex")
    fn = lambda x, y: lpips(x, y, model).tolist()  # noqa: E731
    parts = []
    for d in dirs:
        s = split_eval_dir(d, fn)
        s["_eval_dir"] = str(d.resolve())
        parts.append(s)
    new = pd.concat(parts, ignore_index=True)
    df = df.drop(columns=[c for c in SPLIT_COLUMNS if c in df.columns])
    return df.merge(new, on=["_eval_dir", "run", "view", "region"], how="left")


def coverage(grid: Path) -> tuple[int, int, int]:
    """Of a grid folder's scenes (``cells/*/cell.json``, grouped by the scene as the grid wrote it): how many have
    every one of their cells evaluated, how many at least one, and how many there are. A scene ranks methods only
    when all its methods finished, so this is the coverage the page states (a stopped grid: the finished prefix)."""
    import json

    done: dict[str, list[bool]] = {}
    for cj in grid.glob("cells/*/cell.json"):
        cell = json.loads(cj.read_text(encoding="utf-8"))
        finished = any(cj.parent.glob("eval/*/metrics.parquet"))
        done.setdefault(cell["scene_label"], []).append(finished)
    return (sum(all(v) for v in done.values()), sum(any(v) for v in done.values()), len(done))


def load(grid: Path):
    from evaluation.report import load_metrics

    dirs = eval_dirs(grid)
    if not dirs:
        raise SystemExit(f"{grid}: no finished cells (cells/*/eval/*/metrics.parquet)")
    df = resplit(load_metrics(dirs), dirs)
    df = df.loc[(df["region"] == "crop") & (df["mask_pixels"] > 0) & df["lpips"].notna()]
    if df.empty:
        raise SystemExit(f"{grid}: no crop rows with LPIPS (were the cells evaluated with --metrics lpips,...?)")
    return df, len(dirs), len(list(grid.glob("cells/*/cell.json")))


def corr(a: np.ndarray, b: np.ndarray) -> tuple[float, float, int]:
    from scipy.stats import kendalltau, spearmanr

    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return math.nan, math.nan, int(len(a))
    return float(kendalltau(a, b).statistic), float(spearmanr(a, b).statistic), int(len(a))


def paired_z(views, a: str, b: str, metric: str) -> float:
    """|mean / standard error| of the per-view difference of two methods (the same views): how clearly the two
    differ on this metric beyond the view-to-view spread (NaN with fewer than 2 shared views)."""
    va, vb = views.loc[a][metric], views.loc[b][metric]
    shared = va.index.intersection(vb.index)
    d = (va.loc[shared] - vb.loc[shared]).to_numpy(float)
    d = d[np.isfinite(d)]
    if len(d) < 2:
        return math.nan
    se = float(d.std(ddof=1)) / math.sqrt(len(d))
    return math.inf if se == 0 else abs(float(d.mean())) / se


#: A difference counts as clear beyond this many standard errors of the paired per-view difference.
CLEAR_Z = 2.0


def fmt(tau: float, rho: float) -> str:
    return "—" if not math.isfinite(tau) else f"{tau:+.2f} / {rho:+.2f}"


def agreement(df, name: str) -> tuple[list[str], list[dict]]:
    """Markdown lines of one grid's correlation table, and its disagreements."""
    header = "| scene | rows | " + " | ".join(f"{n} τ / ρ" for _, n, _ in OTHERS) + " |"
    lines = [header, "|" + "---|" * (2 + len(OTHERS))]
    per_run = df.groupby(["scene", "label", "run"], sort=True)[["lpips", *(m for m, _, _ in OTHERS)]].mean()
    per_label = per_run.groupby(level=["scene", "label"]).mean()
    dis = []
    scenes = sorted(df["scene"].unique())
    summary = {m: [] for m, _, _ in OTHERS}
    for scene in scenes:
        d = df.loc[df["scene"] == scene]
        cells = []
        for m, _, sign in OTHERS:
            tau, rho, n = corr(d["lpips"].to_numpy(float), sign * d[m].to_numpy(float))
            summary[m].append(tau)
            cells.append(fmt(tau, rho))
        lines.append(f"| {scene} | {len(d)} | " + " | ".join(cells) + " |")
        t = per_label.xs(scene, level="scene")
        views = d.groupby(["label", "view"])[["lpips", *(m for m, _, _ in OTHERS)]].mean()
        for a, b in combinations(sorted(t.index), 2):
            dl = float(t.loc[a, "lpips"] - t.loc[b, "lpips"])
            for m, mname, sign in OTHERS:
                dm = sign * float(t.loc[a, m] - t.loc[b, m])
                if dl * dm < 0:
                    better_l, better_m = (a, b) if dl < 0 else (b, a)
                    dis.append({"grid": name, "scene": scene, "metric": m, "name": mname, "lpips_says": better_l,
                                "metric_says": better_m, "lpips": (float(t.loc[better_l, "lpips"]),
                                                                   float(t.loc[better_m, "lpips"])),
                                "value": (float(t.loc[better_l, m]), float(t.loc[better_m, m])),
                                "z": (paired_z(views, a, b, "lpips"), paired_z(views, a, b, m))})
    pooled = [corr(df["lpips"].to_numpy(float), s * df[m].to_numpy(float)) for m, _, s in OTHERS]
    lines.append(f"| **pooled (every view)** | {len(df)} | " + " | ".join(fmt(t, r) for t, r, _ in pooled) + " |")
    runs = per_run.reset_index()
    pooled_runs = [corr(runs["lpips"].to_numpy(float), s * runs[m].to_numpy(float)) for m, _, s in OTHERS]
    lines.append(f"| **methods pooled (per-run means)** | {len(runs)} | "
                 + " | ".join(fmt(t, r) for t, r, _ in pooled_runs) + " |")
    med = [np.nanmedian(summary[m]) if np.isfinite(summary[m]).any() else math.nan for m, _, _ in OTHERS]
    lines.append("| median τ over scenes | | " + " | ".join("—" if not math.isfinite(v) else f"{v:+.2f}"
                                                       for v in med) + " |")
    return lines, dis


def pair_counts(df, dis: list[dict]) -> list[str]:
    per_label = df.groupby(["scene", "label", "run"])["lpips"].mean().groupby(level=["scene", "label"]).mean()
    pairs = sum(math.comb(len(per_label.xs(s, level="scene")), 2) for s in df["scene"].unique())
    out = []
    for m, name, _ in OTHERS:
        k = [x for x in dis if x["metric"] == m]
        clear = sum(1 for x in k if min(x["z"]) >= CLEAR_Z)
        out.append(f"{name} {len(k)} of {pairs} ({clear} clear on both)")
    return out


def _v(m: str, v: float) -> str:
    return f"{v:.2f}" if m == "psnr" else f"{v:.5f}" if m == "sifid_proxy" else f"{v:.4f}"


def _z(v: float) -> str:
    return "—" if not math.isfinite(v) else ("∞" if math.isinf(v) else f"{v:.1f}")


def giveaway_rows(df) -> list[str]:
    """Per scene and method (crop, means): shares of squared error and LPIPS in object / shadow / rest."""
    from evaluation.giveaway_report import split_table

    lines = ["| scene | method | LPIPS | shadow px | sq. error: object / shadow / rest | LPIPS: object / shadow / rest |",
             "|---|---|---:|---:|---:|---:|"]
    for scene in sorted(df["scene"].unique()):
        for r in split_table(df, scene):
            pct = lambda v: "—" if not math.isfinite(v) else f"{100 * v + 0.0:.0f}%".replace("-0%", "0%")  # noqa: E731
            lines.append(f"| {scene} | {r['label']} | {r['lpips']:.3f} | {pct(r['px_shadow'])} | "
                         + " / ".join(pct(r[f"se_{p}"]) for p in ("object", "shadow", "rest")) + " | "
                         + " / ".join(pct(r[f"lpshare_{p}"]) for p in ("object", "shadow", "rest")) + " |")
    return lines


def _scenes(grid: Path) -> str:
    full, some, total = coverage(grid)
    return f"{full} of {total} scenes with every method" + (f", {some - full} partly" if some > full else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", action="append", required=True, metavar="NAME=DIR", help="a camo grid output folder")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "metric_agreement.md")
    ap.add_argument("--figure", action="append", default=[], metavar="NAME:SCENE[=TEXT]",
                    help="write the LPIPS heat-map figure of this grid's scene next to --out; TEXT (what the "
                         "pictures show: which metric agrees with the eye) is printed under it")
    ap.add_argument("--giveaway-scenes", type=int, default=12, help="scenes per grid in the give-away table")
    ap.add_argument("--about", action="append", default=[], metavar="NAME=TEXT",
                    help="a sentence under grid NAME's heading (which grid file, which subset of what it stands for)")
    args = ap.parse_args(argv)
    about = dict(a.partition("=")[::2] for a in args.about)
    command = "python bench/metric_agreement.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    from evaluation.giveaway_report import heatmap_figure

    grids = {}
    for g in args.grid:
        name, _, d = g.partition("=")
        grids[name] = (Path(d), *load(Path(d)))
    md = ["# Do the weight-free metrics agree with LPIPS? (issue 31)", "",
          f"Generated on {datetime.date.today().isoformat()} by", "", "```bash", command, "```", "", "from "
          + ", ".join(f"`{n}` ({done} of {total} cells finished; {_scenes(d)})" for n, (d, _, done, total)
                      in grids.items())
          + ". Object crop; LPIPS = LPIPS v0.1 AlexNet on the installed weights (docs/evaluation.md). "
          "Each metric is oriented as a distance (PSNR and SSIM negated): +1 = the same order as LPIPS. "
          "τ = Kendall's tau-b, ρ = Spearman's rho; per scene over that scene's crop rows (every method's "
          "views), pooled over every row, and over the per-run means.", ""]
    all_dis = []
    for name, (d, df, done, total) in grids.items():
        lines, dis = agreement(df, name)
        all_dis += dis
        md += [f"## {name}: {df['scene'].nunique()} scenes, methods: "
               + ", ".join(sorted(df['label'].unique())), "", *([about[name], ""] if name in about else []),
               *lines, "",
               "Method pairs (one scene, two methods' means over the views) ordered differently from LPIPS: "
               + "; ".join(pair_counts(df, dis)) + ".", ""]
        pd_ = [x for x in dis if x["metric"] in PROXIES]
        if pd_:
            md += [f"Where a proxy and LPIPS disagree about which method hides better ({name}); z = |mean| / "
                   "standard error of the two methods' per-view difference (the same views), for LPIPS and for the "
                   f"proxy; **bold** rows: both differences clear (z >= {CLEAR_Z:g}), the rest are within the "
                   "view-to-view spread of at least one of the two:", "",
                   "| scene | proxy | LPIPS says | proxy says | LPIPS (A / B) | proxy (A / B) | z LPIPS / proxy |",
                   "|---|---|---|---|---:|---:|---:|"]
            for x in pd_:
                cells = [x["scene"], x["name"], x["lpips_says"], x["metric_says"],
                         f"{x['lpips'][0]:.4f} / {x['lpips'][1]:.4f}",
                         f"{_v(x['metric'], x['value'][0])} / {_v(x['metric'], x['value'][1])}",
                         f"{_z(x['z'][0])} / {_z(x['z'][1])}"]
                if min(x["z"]) >= CLEAR_Z:
                    cells = [f"**{c}**" for c in cells]
                md.append("| " + " | ".join(cells) + " |")
            md.append("")
        md += [f"### Where the object gives itself away ({name})", "",
               "Shares of the crop's squared error and LPIPS (Shapley parts) in the object (mask + 1-px ring), its "
               "cast shadow and the rest; `shadow px` = the shadow's share of the crop's pixels "
               "(evaluation/giveaway.py).", ""]
        scenes = sorted(df["scene"].unique())
        shown = {spec.partition("=")[0].partition(":")[2] for spec in args.figure
                 if spec.partition(":")[0] == name}  # the scenes with a figure are always in the table
        keep = [s for i, s in enumerate(scenes) if i < args.giveaway_scenes or s in shown]
        md += [*giveaway_rows(df.loc[df["scene"].isin(keep)]), ""]
        if len(keep) < len(scenes):
            md += [f"{len(keep)} of the {len(scenes)} scenes: the first {args.giveaway_scenes} by name and those with "
                   "a figure below (`--giveaway-scenes N` for more; the grid's own report, `report/report.html` in its "
                   "output folder, has every scene's).", ""]
    for spec in args.figure:
        spec, _, caption = spec.partition("=")
        name, _, scene = spec.partition(":")
        if name not in grids:
            raise SystemExit(f"--figure {spec}: no --grid named {name!r}")
        d, df_all, _, _ = grids[name]
        from evaluation.report import load_metrics

        full = load_metrics(eval_dirs(d))
        path = heatmap_figure(full, [], args.out.parent / "_fig", scene)
        if path is not None:
            target = args.out.parent / f"giveaway_{name}_{Path(scene).name}.png"
            path.replace(target)
            md += [f"![{scene}: object crop and LPIPS spatial map per method]({target.name})", "",
                   *([f"**{name}, {scene}.** {caption}", ""] if caption else [])]
    fig_dir = args.out.parent / "_fig"
    if fig_dir.exists():
        import shutil

        shutil.rmtree(fig_dir)
    args.out.write_text("\n".join(md).rstrip() + "\n", encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
