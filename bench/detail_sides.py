"""The detail ratio's two sides per run: which one moves with the samples (render noise) and which stays (texture).

The detail ratio (``evaluation/metrics/detail_ratio.py``) is the object's mean |Laplacian| of luma over the
background's, inside the mask's interior. A ratio can be high because the body has speckle or because a smooth
ground's render noise is missing from it -- and low because the ground is still noisy. Evaluating the same runs at
two spp and printing both sides tells them apart: a side that falls with more samples was noise.

    python bench/detail_sides.py /tmp/giveaways_real/eval/sky-duck /tmp/giveaways_real2048/eval/sky-duck \\
        --runs sky-duck-today,sky-duck-mean

Reads each evaluation folder's ``renders.json`` and its saved 8-bit sRGB PNGs (object, background, mask; nothing is
re-rendered), averages over the views, and prints one markdown row per (folder, run): the two sides in 8-bit steps
(1/255) and the ratio made from them (within a few hundredths of ``camo evaluate``'s, which reads the float renders).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from evaluation.metrics.detail_ratio import EPS, detail_energies


def _srgb(path: Path) -> np.ndarray:
    """8-bit sRGB PNG -> ``(H, W, 3)`` float32 in [0, 1]."""
    return np.asarray(Image.open(path).convert("RGB"), np.float32) / 255.0


def sides(eval_dir: Path, runs: set[str] | None = None) -> dict[str, tuple[float, float, int]]:
    """run -> (object side, background side, views), sides in 1/255 averaged over the run's views."""
    index = eval_dir / "renders.json"
    if not index.is_file():
        raise SystemExit(f"detail_sides: {eval_dir} has no renders.json (not a `camo evaluate` output)")
    per_run: dict[str, list[tuple[float, float]]] = {}
    for rec in json.loads(index.read_text()):
        if runs is not None and rec["run"] not in runs:
            continue
        mask = np.asarray(Image.open(eval_dir / rec["mask"]).convert("L")) > 127
        ex, ey = detail_energies(_srgb(eval_dir / rec["image"]), _srgb(eval_dir / rec["background"]), mask)
        if torch.isfinite(ex).all():
            per_run.setdefault(rec["run"], []).append((float(ex) * 255.0, float(ey) * 255.0))
    return {run: (float(np.mean([v[0] for v in vals])), float(np.mean([v[1] for v in vals])), len(vals))
            for run, vals in per_run.items()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("evals", nargs="+", type=Path, help="`camo evaluate` output folders (e.g. the same runs at 512 and 2048 spp)")
    ap.add_argument("--runs", default="", help="comma-separated run names to keep (default: every run)")
    args = ap.parse_args(argv)
    keep = {r for r in args.runs.split(",") if r} or None
    print("| evaluation | run | views | object side (1/255) | background side (1/255) | ratio |")
    print("|---|---|---|---|---|---|")
    for d in args.evals:
        for run, (ex, ey, n) in sorted(sides(d, keep).items()):
            ratio = (EPS * 255.0 + ex) / (EPS * 255.0 + ey)
            print(f"| {d} | {run} | {n} | {ex:.1f} | {ey:.1f} | {ratio:.2f} |")


if __name__ == "__main__":
    main()
