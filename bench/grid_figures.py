"""Figures and the Stage 2 table from a `camo grid run` output (e.g. ``grids/all_scenes.toml``).

* ``stage2_<scene>.png``: the paper's Fig. 14 comparison per scene -- background | Stage 1 only (the
  ``inpainting`` ablation) | Stage 1 + 2, on evaluation (novel, jittered) views, cropped around the object.
* ``methods_<scene>.png``: one column per method (and ablation) on one scene.
* ``per_scene.md``: per scene and method, LPIPS / PSNR / detail ratio / tint on the object crop (those computed).
* ``stage2.md``: per scene, Stage 1 only vs Stage 1 + 2 on the object crop (LPIPS and the give-away measures
  detail ratio and tint when the grid computed them, PSNR, SSIM, LPIPS-proxy, SIFID-proxy; mean over the
  evaluation views) and the share of object pixels brighter than the brightest
  0.5 % of the background ("sparkle %": isolated specular highlights), plus the Stage 2 seconds.

    python bench/grid_figures.py GRID_OUT --out figures [--views 0,2,5] [--methods-scene gravel]

Images are the evaluation's 8-bit sRGB renders (``eval/*/renders/``); nothing is re-rendered.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image, ImageDraw
from camo_base.tables import read_parquet

METHOD_ORDER = ["transparent", "mean", "random", "greedy", "diffusion2d", "ganmouflage", "ours"]
REC709 = np.array([0.2126, 0.7152, 0.0722])


def load_runs(grid: Path) -> dict[tuple[str, str, str], tuple[dict, Path, list[dict]]]:
    """(scene label, method, ablation) -> (cell, evaluation folder, renders.json records)."""
    runs = {}
    for cell_json in sorted(grid.glob("cells/*/cell.json")):
        cell = json.loads(cell_json.read_text())
        ev = next((cell_json.parent / "eval").glob("*/renders.json"), None)
        if ev is not None and (cell_json.parent / "DONE").exists():
            runs[(cell["scene_label"], cell["method"], cell["ablation"])] = (cell, ev.parent, json.loads(ev.read_text()))
    if not runs:
        raise SystemExit(f"grid_figures: no finished, evaluated cells under {grid}/cells")
    return runs


def crop_box(mask: np.ndarray, pad: float = 0.35, min_side: int = 40) -> tuple[int, int, int, int]:
    """A square around the object's mask (PIL box), at least ``min_side`` px, kept inside the image."""
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return 0, 0, mask.shape[1], mask.shape[0]
    cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
    side = int(min(max(min_side, (1 + 2 * pad) * max(np.ptp(ys), np.ptp(xs))), min(mask.shape)))
    y0 = int(np.clip(cy - side / 2, 0, mask.shape[0] - side))
    x0 = int(np.clip(cx - side / 2, 0, mask.shape[1] - side))
    return x0, y0, x0 + side, y0 + side


def read(evdir: Path, rec: dict, key: str, mode: str = "RGB") -> Image.Image:
    return Image.open(evdir / rec[key]).convert(mode)


def montage(runs, scene: str, columns: list[tuple[str, tuple[str, str]]], views: list[int], path: Path,
            size: int) -> None:
    """Rows = views, columns = background then ``columns`` (label, (method, ablation)); crops from the first."""
    _, ref_dir, ref = runs[(scene, *columns[0][1])]
    views = [v for v in views if v < len(ref)]
    labels = ["background"] + [c[0] for c in columns]
    canvas = Image.new("RGB", (size * len(labels), 18 + size * len(views)), "white")
    draw = ImageDraw.Draw(canvas)
    for i, lab in enumerate(labels):
        draw.text((i * size + 4, 3), lab, fill="black")
    for r, v in enumerate(views):
        box = crop_box(np.asarray(read(ref_dir, ref[v], "mask", "L")) > 127)
        tiles = [read(ref_dir, ref[v], "background").crop(box)]
        for _, key in columns:
            _, evdir, recs = runs[(scene, *key)]
            tiles.append(read(evdir, recs[v], "image").crop(box))
        for i, im in enumerate(tiles):
            canvas.paste(im.resize((size, size), Image.NEAREST), (i * size, 18 + r * size))
    canvas.save(path, optimize=True)
    print(f"wrote {path}")


def sparkle_share(evdir: Path, recs: list[dict]) -> float:
    """Mean over views of the share of object pixels brighter than the background's 99.5th luminance percentile."""
    out = []
    for rec in recs:
        bg = np.asarray(read(evdir, rec, "background"), np.float64) / 255 @ REC709
        im = np.asarray(read(evdir, rec, "image"), np.float64) / 255 @ REC709
        mask = np.asarray(read(evdir, rec, "mask", "L")) > 127
        if mask.any():
            out.append(float((im[mask] > np.quantile(bg, 0.995)).mean()))
    return float(np.mean(out)) if out else float("nan")


def file_stem(scene: str) -> str:
    """A file-name-safe form of a scene name (built-in name, ``data:`` reference or pack path)."""
    name = Path(scene).stem if scene.endswith(".toml") else scene
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "scene"


#: Stage 2 table columns: (metrics.parquet column, header, decimals, direction: +1 higher is better, -1 lower, 0 best
#: at 1). LPIPS and the give-away measures are shown when the grid computed them (``[evaluate] metrics``).
STAGE2_METRICS = (("lpips", "LPIPS↓", 4, -1), ("psnr", "PSNR↑", 2, 1), ("ssim", "SSIM↑", 4, 1),
                  ("lpips_proxy", "LPIPS-proxy↓", 4, -1), ("sifid_proxy", "SIFID-proxy↓", 4, -1),
                  ("detail_ratio", "Detail→1", 2, 0), ("tint", "Tint↓", 2, -1))
OPTIONAL = {"lpips", "detail_ratio", "tint"}


def _better(a: float, b: float, direction: int) -> bool:
    """Whether ``a`` is better than ``b`` (direction 0: closer to 1)."""
    return a > b if direction > 0 else a < b if direction < 0 else abs(a - 1) < abs(b - 1)


def stage2_table(grid: Path, runs) -> str:
    metrics = read_parquet(grid / "metrics.parquet")
    metrics = metrics[metrics["region"] == "crop"]
    cols = [c for c in STAGE2_METRICS if c[0] not in OPTIONAL or (c[0] in metrics and metrics[c[0]].notna().any())]
    cols += [("sparkle", "sparkle %", 2, -1)]
    rows = []
    for (scene, method, ablation), (cell, evdir, recs) in sorted(runs.items()):
        if method != "ours" or ablation not in ("none", "inpainting"):
            continue
        m = metrics[metrics["run"] == cell["name"]]
        log_path = next((grid / "cells" / cell["key"] / "run").glob("*/log.jsonl"))
        stage2 = [r for r in map(json.loads, log_path.read_text().splitlines()) if r.get("stage") == 2]
        values = {c[0]: float(m[c[0]].mean()) for c in cols[:-1]}
        values["sparkle"] = 100 * sparkle_share(evdir, recs)
        rows.append((scene, "Stage 1 only" if ablation == "inpainting" else "Stage 1 + 2", values,
                     sum(r.get("seconds_total", r["seconds"]) for r in stage2)))
    rows.sort(key=lambda r: (r[0], r[1] != "Stage 1 only"))
    head = ["scene", "variant"] + [c[1] for c in cols] + ["Stage 2 s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, variant, values, seconds in rows:
        cells = [f"{values[c[0]]:.{c[2]}f}" for c in cols]
        lines.append(f"| {scene} | {variant} | " + " | ".join(cells) + f" | {seconds:.1f} |")
    by = {}
    for r in rows:
        by.setdefault(r[0], {})[r[1]] = r[2]
    both = [v for v in by.values() if len(v) == 2]
    if both:
        wins = [sum(_better(v["Stage 1 + 2"][c[0]], v["Stage 1 only"][c[0]], c[3]) for v in both) for c in cols]
        same = sum(all(v["Stage 1 + 2"][c[0]] == v["Stage 1 only"][c[0]] for c in cols) for v in both)
        lines += ["", f"Scenes (of {len(both)}) where Stage 1 + 2 is better than Stage 1 only: "
                      + ", ".join(f"{c[1].rstrip('↑↓').replace('→1', '')} {w}" for c, w in zip(cols, wins))
                      + f"; the same figures (Stage 1's iterate kept) in {same}."]
    return "\n".join(lines) + "\n"


#: Per-scene table cells: (column, decimals), shown when computed; the first shown is the one whose best is bold.
PER_SCENE = (("lpips", 3), ("psnr", 2), ("detail_ratio", 2), ("tint", 1))


def per_scene_table(grid: Path) -> str:
    """Per scene (rows) and method label (columns, Table II order): ``LPIPS / PSNR / detail ratio / tint`` on the
    object crop, each the mean over a run's views then over the label's runs (the report's per-scene values); bold:
    the best LPIPS of the scene (PSNR when no LPIPS was computed)."""
    from evaluation.report import label_order, method_label

    m = read_parquet(grid / "metrics.parquet")
    m = m[m["region"] == "crop"].copy()
    cols = [(c, d) for c, d in PER_SCENE if c in m.columns and m[c].notna().any()]
    if not cols:
        raise SystemExit(f"grid_figures: {grid}/metrics.parquet has none of {', '.join(c for c, _ in PER_SCENE)}")
    m["label"] = [method_label(a, b) for a, b in zip(m["method"], m["ablation"])]
    order = {lab: label_order(a, b) for lab, a, b in zip(m["label"], m["method"], m["ablation"])}
    names = [c for c, _ in cols]
    t = m.groupby(["scene", "label", "run"])[names].mean().groupby(level=["scene", "label"]).mean()
    labels = sorted(t.index.get_level_values("label").unique(), key=lambda lab: order[lab])
    key, sign = cols[0][0], (1 if cols[0][0] == "psnr" else -1)
    head = ["scene"] + labels
    lines = [" / ".join({"lpips": "LPIPS↓", "psnr": "PSNR↑", "detail_ratio": "detail ratio→1", "tint": "tint↓"}[c]
                        for c in names), "", "| " + " | ".join(head) + " |", "|---|" + "---:|" * len(labels)]
    for scene in sorted(t.index.get_level_values("scene").unique()):
        sub = t.xs(scene, level="scene")
        best = max((sign * sub.loc[lab, key] for lab in sub.index if pd.notna(sub.loc[lab, key])), default=None)
        cells = []
        for lab in labels:
            if lab not in sub.index:
                cells.append("—")
                continue
            text = " / ".join(f"{sub.loc[lab, c]:.{d}f}" for c, d in cols)
            cells.append(f"**{text}**" if best is not None and sign * sub.loc[lab, key] == best else text)
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("grid_out", type=Path)
    ap.add_argument("--out", type=Path, default=Path("figures"))
    ap.add_argument("--views", default="0,2,5", help="evaluation views in the Stage 2 figures")
    ap.add_argument("--methods-scene", default=None, help="scene of the per-method figure (default: the first)")
    args = ap.parse_args()
    runs = load_runs(args.grid_out)
    args.out.mkdir(parents=True, exist_ok=True)
    views = [int(v) for v in args.views.split(",")]
    scenes = sorted({k[0] for k in runs})
    for scene in scenes:
        if (scene, "ours", "inpainting") in runs and (scene, "ours", "none") in runs:
            montage(runs, scene, [("Stage 1 only", ("ours", "inpainting")), ("Stage 1 + 2", ("ours", "none"))], views,
                    args.out / f"stage2_{file_stem(scene)}.png", 160)
    scene = args.methods_scene or scenes[0]
    keys = sorted((k for k in runs if k[0] == scene),
                  key=lambda k: (METHOD_ORDER.index(k[1]) if k[1] in METHOD_ORDER else 99, k[2] == "none", k[2]))
    if keys:
        cols = [(m if a == "none" else f"{m} w/o {a}", (m, a)) for _, m, a in keys]
        montage(runs, scene, cols, views[:2], args.out / f"methods_{file_stem(scene)}.png", 128)
    table = stage2_table(args.grid_out, runs)
    (args.out / "stage2.md").write_text(table)
    print(table)
    scenes_md = per_scene_table(args.grid_out)
    (args.out / "per_scene.md").write_text(scenes_md)
    print(scenes_md)


if __name__ == "__main__":
    main()
