"""Data and figures of the report's "Where the object gives itself away" section (:mod:`evaluation.report`
writes the section): per scene and method, the crop's squared error and LPIPS split into object / cast shadow /
rest (the columns of :mod:`evaluation.giveaway`), and a figure of the LPIPS spatial map beside each render.

Table values (crop region): the mean over a run's views, then over the runs of a label (the report's
aggregation). Shares are of the summed parts (``sqerr_*``: of the MSE; ``lpips_*``: Shapley parts of LPIPS).
The figure recomputes LPIPS's spatial map (:func:`evaluation.metrics.lpips_map`) from the saved 8-bit renders,
so it needs the installed LPIPS weights; without them the section says so and shows the squared-error split only.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from evaluation.evaldir import SPLIT_PARTS

#: Views per method in the heat-map figure (the first ones of the evaluation: the same views for every method).
FIGURE_VIEWS = 2


def _pct(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{100 * v + 0.0:.0f}%".replace("-0%", "0%")


def split_table(df, scene: str) -> list[dict[str, Any]]:
    """Per label of ``scene`` (crop region): pixels, squared-error and LPIPS parts (means as in the report)."""
    cols = [f"{w}_{p}" for w in ("pixels", "sqerr", "lpips") for p in SPLIT_PARTS] + ["lpips", "psnr"]
    d = df.loc[(df["region"] == "crop") & (df["scene"] == scene)]
    cols = [c for c in cols if c in d.columns]
    if d.empty or d[[f"sqerr_{p}" for p in SPLIT_PARTS if f"sqerr_{p}" in d.columns]].isna().all().all():
        return []
    t = d.groupby(["label", "run"], sort=False)[cols].mean().groupby(level="label", sort=False).mean()
    order = d.drop_duplicates("label").set_index("label")["_order"]
    rows = []
    for lab in sorted(t.index, key=lambda x: order[x]):
        r = t.loc[lab]
        px = sum(float(r.get(f"pixels_{p}", math.nan)) for p in SPLIT_PARTS)
        se = sum(float(r.get(f"sqerr_{p}", math.nan)) for p in SPLIT_PARTS)
        lp = sum(float(r.get(f"lpips_{p}", math.nan)) for p in SPLIT_PARTS)
        row = {"label": lab, "lpips": float(r.get("lpips", math.nan)), "mse": se}
        for p in SPLIT_PARTS:
            row[f"px_{p}"] = float(r[f"pixels_{p}"]) / px if px > 0 else math.nan
            row[f"se_{p}"] = float(r[f"sqerr_{p}"]) / se if se > 0 else math.nan
            row[f"lp_{p}"] = float(r.get(f"lpips_{p}", math.nan))
            row[f"lpshare_{p}"] = row[f"lp_{p}"] / lp if math.isfinite(lp) and lp > 0 else math.nan
        rows.append(row)
    return rows


def _load8(path: Path) -> np.ndarray | None:
    """A saved render as the metrics saw it (8-bit values), or None when unreadable."""
    from camo_base.errors import CamoError
    from camo_base.imaging import load_png

    try:
        return np.round(load_png(path) * 255.0).astype(np.uint8)
    except CamoError:
        return None


def split_cells(rows: list[dict[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """Header and text cells of a scene's give-away table (rows of :func:`split_table`)."""
    has_lpips = any(math.isfinite(r["lpips"]) for r in rows)
    header = ["Model", "pixels: object / shadow / rest", "sq. error: object / shadow / rest"]
    if has_lpips:
        header += ["LPIPS", "LPIPS: object / shadow / rest", "LPIPS shares"]
    out = []
    for r in rows:
        cells = [r["label"], " / ".join(_pct(r[f"px_{p}"]) for p in SPLIT_PARTS),
                 " / ".join(_pct(r[f"se_{p}"]) for p in SPLIT_PARTS)]
        if has_lpips:
            cells += ["—" if not math.isfinite(r["lpips"]) else f"{r['lpips']:.4f}",
                      " / ".join("—" if not math.isfinite(r[f"lp_{p}"]) else f"{r[f'lp_{p}']:.4f}".replace("-0.0000", "0.0000")
                                 for p in SPLIT_PARTS),
                      " / ".join(_pct(r[f"lpshare_{p}"]) for p in SPLIT_PARTS)]
        out.append(cells)
    return header, out


NOTE = ("Where the object gives itself away (object crop): its pixels split into the object (mask + 1-px ring), "
        "its cast shadow (darker with the object, outside it: 3x3-averaged luma darkening above max(3 sigma, 2/255), "
        "sigma the render noise, estimated from the pixels the object brightens) and the rest; per part its share of the pixels, of the squared "
        "error (PSNR's MSE) and of LPIPS (Shapley parts: the LPIPS each part adds, averaged over the orders of "
        "adding them; they sum to the crop's LPIPS). Columns `pixels_*`, `sqerr_*`, `lpips_*` of metrics.parquet; "
        "definitions in evaluation/giveaway.py.")


def heatmap_figure(df, eval_dirs: Sequence[str | Path], out: Path, scene: str) -> Path | None:
    """PNG: per label (rows) and for the first :data:`FIGURE_VIEWS` views, the crop with the object | its LPIPS
    spatial map (shared colour scale; white contour: the object, cyan: the cast shadow). None without weights or
    renders; a crop smaller than LPIPS takes (``MIN_SIZE["lpips"]``, a tiny evaluation) is left out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from camo_base import atomic
    from camo_base.errors import CamoError
    from evaluation.evaldir import renders_json
    from evaluation.giveaway import object_region, shadow_mask
    from evaluation.metrics import MIN_SIZE, apply_crop, load_lpips, lpips_map

    try:
        model = load_lpips("alex")
    except CamoError:
        return None
    d = df.loc[(df["region"] == "crop") & (df["scene"] == scene) & (df["mask_pixels"] > 0)]
    if d.empty:
        return None
    renders: dict[tuple[str, str, int], dict[str, Path]] = {}
    for ed in {str(x) for x in d["_eval_dir"]}:
        for e in renders_json(ed):
            try:
                renders[(ed, str(e["run"]), int(e["view"]))] = {k: Path(ed) / str(e[k]) for k in
                                                               ("image", "background", "mask") if e.get(k)}
            except (KeyError, TypeError, ValueError):
                continue
    runs = sorted(d.drop_duplicates(["_eval_dir", "run"]).to_dict("records"), key=lambda r: r["_order"])
    seen, panels = set(), []
    for r in runs:
        if r["label"] in seen:
            continue
        views = sorted(int(v) for v in d.loc[(d["run"] == r["run"]) & (d["_eval_dir"] == r["_eval_dir"]), "view"])
        row = []
        for v in views[:FIGURE_VIEWS]:
            files = renders.get((r["_eval_dir"], r["run"], v), {})
            if not all(k in files for k in ("image", "background", "mask")):
                continue
            img, bg, m = (_load8(files[k]) for k in ("image", "background", "mask"))
            if img is None or bg is None or m is None:
                continue
            mask = (m if m.ndim == 2 else m[..., 0]) >= 128
            shadow, _ = shadow_mask(img, bg, mask)
            rr = d.loc[(d["run"] == r["run"]) & (d["_eval_dir"] == r["_eval_dir"]) & (d["view"] == v)].iloc[0]
            box = (int(rr["region_y0"]), int(rr["region_x0"]), int(rr["region_height"]))
            a, b, mk, sh = (apply_crop(x, box) for x in (img, bg, mask, shadow))
            if min(a.shape[:2]) < MIN_SIZE["lpips"]:  # (the report must not fail on what it only illustrates)
                continue
            lmap = lpips_map(a, b, model)[0].numpy()
            row.append((v, a, lmap, object_region(mk), sh, float(rr.get("lpips", math.nan))))
        if row:
            seen.add(r["label"])
            panels.append((r["label"], row))
    if not panels:
        return None
    vmax = float(np.percentile(np.concatenate([p[2].ravel() for _, row in panels for p in row]), 99.5)) or 1.0
    ncol = 2 * max(len(row) for _, row in panels)
    fig, axes = plt.subplots(len(panels), ncol, figsize=(1.8 * ncol, 1.9 * len(panels) + 0.5), dpi=100,
                             squeeze=False)
    im = None
    for i, (label, row) in enumerate(panels):
        for j in range(ncol):
            axes[i][j].set_axis_off()
        for k, (v, a, lmap, obj, sh, value) in enumerate(row):
            ax_img, ax_map = axes[i][2 * k], axes[i][2 * k + 1]
            ax_img.imshow(a, interpolation="nearest")
            ax_img.set_title(f"{label}, view {v}" if k == 0 else f"view {v}", fontsize=7)
            im = ax_map.imshow(lmap, cmap="inferno", vmin=0.0, vmax=vmax, interpolation="nearest")
            for mask, colour in ((obj, "white"), (sh, "cyan")):
                if mask.any() and not mask.all():
                    ax_map.contour(mask.astype(float), levels=[0.5], colors=colour, linewidths=0.7)
            ax_map.set_title("LPIPS map" + ("" if not math.isfinite(value) else f" ({value:.3f})"), fontsize=7)
    fig.suptitle(f"{scene}: object crop | LPIPS spatial map (AlexNet; white = object, cyan = cast shadow)",
                 fontsize=8)
    fig.tight_layout(rect=(0, 0, 0.94, 0.97))
    if im is not None:
        cax = fig.add_axes((0.95, 0.1, 0.012, 0.8))
        fig.colorbar(im, cax=cax).ax.tick_params(labelsize=6)
    path = out / "giveaway" / f"{re.sub(r'[^A-Za-z0-9._-]+', '_', scene).strip('_') or 'scene'}.png"
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
