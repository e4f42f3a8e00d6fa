"""bench/grid_figures.py on a hand-made grid output: crops, montages and the Stage 2 table's values."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image
from camo_base.tables import write_parquet


def test_crop_box_is_square_inside_and_around_the_mask(bench_module):
    gf = bench_module("grid_figures")
    mask = np.zeros((96, 96), bool)
    mask[80:90, 85:95] = True  # near the corner: the box is shifted inside
    x0, y0, x1, y1 = gf.crop_box(mask, pad=0.35, min_side=40)
    assert (x1 - x0, y1 - y0) == (40, 40) and x1 <= 96 and y1 <= 96
    assert x0 <= 85 and y0 <= 80 and x1 >= 95 and y1 >= 90
    assert gf.crop_box(np.zeros((8, 8), bool)) == (0, 0, 8, 8)


def make_cell(write_eval_renders, grid: Path, key: str, ablation: str, object_value: int,
              psnr: float) -> pd.DataFrame:
    cell = grid / "cells" / key
    name = f"gravel__ours{'' if ablation == 'none' else '-wo-' + ablation}__s0"
    bg = np.full((32, 32, 3), 100, np.uint8)
    bg[0, :8] = 200  # 8 of 1024 pixels: the 99.5th luminance percentile is exactly the 200 level
    img = bg.copy()
    img[10:20, 10:20] = object_value
    mask = np.zeros((32, 32), np.uint8)
    mask[10:20, 10:20] = 255
    write_eval_renders(cell / "eval" / name, bg, img, mask)
    (cell / "cell.json").write_text(json.dumps({"key": key, "name": name, "scene_label": "gravel", "method": "ours",
                                                "ablation": ablation}))
    (cell / "DONE").write_text("")
    run = cell / "run" / name
    run.mkdir(parents=True)
    log = [{"iteration": 1, "stage": 1, "seconds": 1.0}]
    if ablation == "none":
        log += [{"iteration": i, "stage": 2, "seconds": 1.0, "seconds_total": 2.5} for i in (1, 2)]
    (run / "log.jsonl").write_text("\n".join(json.dumps(r) for r in log) + "\n")
    return pd.DataFrame({"run": [name] * 2, "region": ["crop"] * 2, "psnr": [psnr, psnr + 2], "ssim": [0.5, 0.5],
                         "lpips_proxy": [0.3, 0.3], "sifid_proxy": [0.01, 0.01]})


def test_stage2_table_and_figures(tmp_path, bench_module, write_eval_renders):
    gf = bench_module("grid_figures")
    grid = tmp_path / "grid"
    m = pd.concat([make_cell(write_eval_renders, grid, "a" * 16, "none", 150, 30.0),  # no pixel above 200: sparkle 0 %
                   make_cell(write_eval_renders, grid, "b" * 16, "inpainting", 255, 20.0)])  # all above: 100 %
    write_parquet(m, grid / "metrics.parquet")
    runs = gf.load_runs(grid)
    assert set(runs) == {("gravel", "ours", "none"), ("gravel", "ours", "inpainting")}
    table = gf.stage2_table(grid, runs)
    assert "| gravel | Stage 1 only | 21.00 | 0.5000 | 0.3000 | 0.0100 | 100.00 | 0.0 |" in table
    assert "| gravel | Stage 1 + 2 | 31.00 | 0.5000 | 0.3000 | 0.0100 | 0.00 | 5.0 |" in table
    assert "Scenes (of 1) where Stage 1 + 2 is better than Stage 1 only: PSNR 1, SSIM 0, LPIPS-proxy 0, SIFID-proxy 0, sparkle % 1; the same figures (Stage 1's iterate kept) in 0." in table
    gf.montage(runs, "gravel", [("Stage 1 only", ("ours", "inpainting")), ("Stage 1 + 2", ("ours", "none"))], [0, 1, 7],
               tmp_path / "f.png", 40)
    im = np.asarray(Image.open(tmp_path / "f.png"))
    assert im.shape == (18 + 2 * 40, 3 * 40, 3)  # view 7 does not exist: two rows


def test_stage2_table_shows_lpips_and_the_give_away_measures_when_computed(tmp_path, bench_module,
                                                                          write_eval_renders):
    gf = bench_module("grid_figures")
    grid = tmp_path / "grid"
    a = make_cell(write_eval_renders, grid, "a" * 16, "none", 150, 30.0)
    b = make_cell(write_eval_renders, grid, "b" * 16, "inpainting", 255, 20.0)
    a = a.assign(lpips=[0.20, 0.30], detail_ratio=[1.5, 1.7], tint=[2.0, 4.0])  # Stage 1 + 2: detail 1.6, 0.6 off
    b = b.assign(lpips=[0.30, 0.30], detail_ratio=[0.7, 0.7], tint=[1.0, 1.0])  # Stage 1 only: 0.7, 0.3 off
    write_parquet(pd.concat([a, b]), grid / "metrics.parquet")
    table = gf.stage2_table(grid, gf.load_runs(grid))
    assert table.startswith("| scene | variant | LPIPS↓ | PSNR↑ | SSIM↑ | LPIPS-proxy↓ | SIFID-proxy↓ | Detail→1 | "
                            "Tint↓ | sparkle % | Stage 2 s |")
    assert "| gravel | Stage 1 only | 0.3000 | 21.00 | 0.5000 | 0.3000 | 0.0100 | 0.70 | 1.00 | 100.00 | 0.0 |" in table
    assert "| gravel | Stage 1 + 2 | 0.2500 | 31.00 | 0.5000 | 0.3000 | 0.0100 | 1.60 | 3.00 | 0.00 | 5.0 |" in table
    # the detail ratio is best at 1: Stage 1 only's 0.70 beats 1.60
    assert ("Stage 1 + 2 is better than Stage 1 only: LPIPS 1, PSNR 1, SSIM 0, LPIPS-proxy 0, SIFID-proxy 0, "
            "Detail 0, Tint 0, sparkle % 1;") in table


def test_per_scene_table_means_over_views_and_bolds_the_best_lpips(tmp_path, bench_module):
    gf = bench_module("grid_figures")
    rows = []
    for run, method, abl, lp, ps in (("s__ours", "ours", "none", (0.1, 0.3), (30, 32)),
                                     ("s__ours-wo", "ours", "inpainting", (0.25, 0.25), (29, 29)),
                                     ("s__mean", "mean", "none", (0.4, 0.5), (25, 26))):
        for v in (0, 1):
            for region in ("crop", "full"):
                rows.append({"run": run, "scene": "real-s", "method": method, "ablation": abl, "view": v,
                             "region": region, "lpips": lp[v] + (region == "full"), "psnr": float(ps[v]),
                             "detail_ratio": 1.5, "tint": 2.0})
    (tmp_path / "g").mkdir()
    write_parquet(pd.DataFrame(rows), tmp_path / "g" / "metrics.parquet")
    md = gf.per_scene_table(tmp_path / "g")
    assert "| scene | Mean [6] | w/o Inpainting | Ours |" in md  # Table II order
    assert "| real-s | 0.450 / 25.50 / 1.50 / 2.0 | 0.250 / 29.00 / 1.50 / 2.0 | **0.200 / 31.00 / 1.50 / 2.0** |" in md
