"""Seconds per Stage-2 inpaint call, per backend; prints a Markdown table.

    python bench/bench_inpaint.py [--repeat 3] [--large] [--no-diffusers] [--sdxl-path DIR --controlnet-path DIR]

``patch`` runs on tinted scikit-image textures (grass) with a square hole and
an object-like blob mask. ``diffusers`` runs the tiny randomly initialised
SDXL ControlNet inpainting pipeline (same classes as the real one, built into
a temporary folder; measures the pipeline overhead, not SDXL's cost), or real
weights if ``--sdxl-path``/``--controlnet-path`` are given.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from optimizer.optimise.inpaint import get_inpainter  # noqa: E402


def texture(size: int) -> np.ndarray:
    import skimage.data

    g = skimage.data.grass()
    reps = -(-size // g.shape[0])
    g = np.pad(g, [(0, (reps - 1) * g.shape[0]), (0, (reps - 1) * g.shape[1])], mode="symmetric")
    g = g[:size, :size].astype(np.float32) / 255.0
    return np.clip(g[..., None] * np.array([0.6, 1.0, 0.5], np.float32), 0, 1).astype(np.float32)


def square(size: int, side: int) -> np.ndarray:
    m = np.zeros((size, size), bool)
    a = (size - side) // 2
    m[a : a + side, a : a + side] = True
    return m


def blob(size: int, frac: float) -> np.ndarray:
    """An irregular object silhouette covering about ``frac`` of the image."""
    yy, xx = np.mgrid[:size, :size].astype(np.float32) / size
    ang = np.arctan2(yy - 0.55, xx - 0.5)
    rad = np.sqrt(frac / np.pi) * (1.0 + 0.25 * np.sin(3 * ang) + 0.1 * np.cos(7 * ang))
    return np.hypot(yy - 0.55, xx - 0.5) < rad


def time_call(inp, img, mask, bg, depth, strength, repeat: int) -> float:
    inp.inpaint(img, mask, bg, depth, strength, 0)  # warm-up (imports, caches)
    ts = []
    for i in range(repeat):
        t0 = time.perf_counter()
        inp.inpaint(img, mask, bg, depth, strength, i)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-diffusers", action="store_true")
    ap.add_argument("--sdxl-path")
    ap.add_argument("--controlnet-path")
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--large", action="store_true", help="also 512^2 and 800^2 (the paper's render size)")
    args = ap.parse_args(argv)

    rows = []
    patch = get_inpainter("patch")
    for size, name, mask in [
        (128, "square 24x24", square(128, 24)),
        (128, "blob ~10%", blob(128, 0.10)),
        (256, "square 40x40", square(256, 40)),
        (256, "blob ~10%", blob(256, 0.10)),
        (256, "blob ~25%", blob(256, 0.25)),
    ] + ([(512, "blob ~10%", blob(512, 0.10)), (800, "blob ~10%", blob(800, 0.10))] if args.large else []):
        bg = texture(size)
        img = bg.copy()
        img[mask] = 0.5
        depth = np.full((size, size), 5.0, np.float32)
        s = time_call(patch, img, mask, bg, depth, 1.0, args.repeat)
        rows.append(("patch", f"{size}x{size}", name, int(mask.sum()), "-", s))

    if not args.no_diffusers:
        try:
            import torch

            if args.sdxl_path:
                label = "diffusers (given weights)"
                inp = get_inpainter("diffusers", sdxl_path=args.sdxl_path, controlnet_path=args.controlnet_path,
                                    num_inference_steps=args.steps)
                cases = [(512, None)]
            else:
                from optimizer.optimise.inpainting._tiny import build_tiny_sdxl_controlnet_inpaint

                label = "diffusers (tiny random SDXL+ControlNet)"
                tmp = tempfile.mkdtemp(prefix="bench_inpaint_")
                sdxl, cn = build_tiny_sdxl_controlnet_inpaint(tmp)
                inp = None
                cases = [(64, 64), (128, 128)]
            for size, res in cases:
                if res is not None:
                    inp = get_inpainter("diffusers", sdxl_path=str(sdxl), controlnet_path=str(cn),
                                        resolution=res, num_inference_steps=args.steps)
                bg = texture(size)
                mask = blob(size, 0.10)
                img = bg.copy()
                img[mask] = 0.5
                depth = np.full((size, size), 5.0, np.float32)
                s = time_call(inp, img, mask, bg, depth, 1.0, args.repeat)
                rows.append((label, f"{size}x{size}", "blob ~10%", int(mask.sum()), f"{args.steps} steps, {inp.device}", s))
            del torch
        except Exception as exc:  # noqa: BLE001 - the bench reports and goes on
            rows.append(("diffusers", "-", "-", 0, f"skipped: {' '.join(str(exc).split())[:80]}", float("nan")))

    print(f"Stage-2 inpainting, seconds per call (median of {args.repeat}); "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs visible, "
          f"torch threads {_torch_threads()}\n")
    print("| backend | image | mask | mask px | notes | s / call |")
    print("|---|---|---|---:|---|---:|")
    for b, size, name, px, notes, s in rows:
        print(f"| {b} | {size} | {name} | {px} | {notes} | {s:.3f} |")
    return 0


def _torch_threads() -> str:
    if "torch" not in sys.modules:
        return "-"
    return str(sys.modules["torch"].get_num_threads())


if __name__ == "__main__":
    raise SystemExit(main())
