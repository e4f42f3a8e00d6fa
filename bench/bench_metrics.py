"""Throughput and agreement of our image metrics against the reference libraries.

Run: ``python bench/bench_metrics.py [--n 32] [--size 256] [--repeats 3]``. Prints a Markdown table: for each
metric, ours vs the reference on the same image pairs (natural crops of scikit-image's sample images with noise,
blur and colour distortions): mean value, max |difference| per image, seconds for the whole batch (best of
``--repeats``) and the speed-up. References: scikit-image (SSIM, PSNR, looping over images as its API needs)
and piq (HaarPSI, batched) when importable. Ours runs with torch's default thread count and with 1 thread.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
import time
import types
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation.metrics import haarpsi, lpips_proxy, psnr, sifid_proxy, ssim  # noqa: E402


def make_pairs(n: int, size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` pairs ``(n, size, size, 3)`` float64 sRGB in [0, 1]: crops and their distorted versions."""
    from scipy import ndimage
    from skimage import data

    sources = [data.astronaut(), data.chelsea(), data.coffee(), data.rocket()]
    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for i in range(n):
        src = sources[i % len(sources)]
        y0 = rng.integers(0, src.shape[0] - size + 1)
        x0 = rng.integers(0, src.shape[1] - size + 1)
        x = src[y0 : y0 + size, x0 : x0 + size].astype(np.float64) / 255.0
        kind = i % 3
        if kind == 0:
            y = x + rng.normal(0, 0.03 + 0.05 * rng.random(), x.shape)
        elif kind == 1:
            y = ndimage.gaussian_filter(x, sigma=(0.5 + 2 * rng.random(),) * 2 + (0,))
        else:
            y = x * rng.uniform(0.8, 1.2, 3) + rng.normal(0, 0.01, x.shape)
        xs.append(x)
        ys.append(np.clip(y, 0, 1))
    return np.stack(xs), np.stack(ys)


def best_time(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def load_piq_haarpsi() -> Optional[Callable]:
    """piq's haarpsi without ``import piq`` (whose __init__ needs torchvision); None if piq is absent."""
    spec = importlib.util.find_spec("piq")
    if spec is None:
        return None
    if "piq" not in sys.modules:
        stub = types.ModuleType("piq")
        stub.__path__ = list(spec.submodule_search_locations)
        sys.modules["piq"] = stub
    try:
        return importlib.import_module("piq.haarpsi").haarpsi
    except Exception:  # a broken optional install only removes a row
        return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    xs, ys = make_pairs(args.n, args.size)
    x32 = torch.from_numpy(xs).permute(0, 3, 1, 2).float().contiguous()
    y32 = torch.from_numpy(ys).permute(0, 3, 1, 2).float().contiguous()
    xs32, ys32 = xs.astype(np.float32), ys.astype(np.float32)
    threads = torch.get_num_threads()

    def sk_ssim() -> np.ndarray:
        return np.array([
            structural_similarity(a, b, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                  use_sample_covariance=False, data_range=1.0)
            for a, b in zip(xs32, ys32)
        ])

    def sk_psnr() -> np.ndarray:
        return np.array([peak_signal_noise_ratio(a, b, data_range=1.0) for a, b in zip(xs32, ys32)])

    rows = []

    def compare(name: str, ours: Callable[[], torch.Tensor], ref: Optional[Callable[[], object]], ref_name: str):
        with torch.no_grad():
            ours()  # warm-up (kernel selection, allocations)
            t_ours, v_ours = best_time(ours, args.repeats)
            torch.set_num_threads(1)
            t_ours1, _ = best_time(ours, args.repeats)
            torch.set_num_threads(threads)
            v_ours = np.asarray(v_ours, dtype=np.float64).reshape(-1)
            if ref is None:
                rows.append((name, v_ours.mean(), None, None, t_ours, t_ours1, None, ref_name))
                return
            ref()
            t_ref, v_ref = best_time(ref, args.repeats)
        v_ref = np.asarray(v_ref, dtype=np.float64).reshape(-1)
        rows.append((name, v_ours.mean(), v_ref.mean(), np.abs(v_ours - v_ref).max(), t_ours, t_ours1, t_ref,
                     ref_name))

    compare("SSIM", lambda: ssim(x32, y32), sk_ssim, "skimage structural_similarity")
    compare("PSNR", lambda: psnr(x32, y32), sk_psnr, "skimage peak_signal_noise_ratio")
    piq_h = load_piq_haarpsi()
    piq_ref = (lambda: piq_h(x32, y32, reduction="none")) if piq_h else None
    piq_name = "piq haarpsi" if piq_h else "piq not installed"
    compare("HaarPSI (authors' YIQ)", lambda: haarpsi(x32, y32), piq_ref, piq_name)
    compare("HaarPSI (yiq='piq')", lambda: haarpsi(x32, y32, yiq="piq"), piq_ref, piq_name)
    compare("lpips_proxy (1-HaarPSI)", lambda: lpips_proxy(x32, y32), None, "-")
    compare("sifid_proxy", lambda: sifid_proxy(x32, y32), None, "-")

    print(f"{args.n} image pairs {args.size}x{args.size}, float32, CPU, torch {torch.__version__} "
          f"({threads} threads by default); seconds for the whole batch, best of {args.repeats}\n")
    print("| metric | ours (mean) | reference (mean) | max abs diff | ours s | ours s (1 thread) | reference s "
          "| speed-up | reference |")
    print("|---|---|---|---|---|---|---|---|---|")

    def f(v: Optional[float], fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    for name, vo, vr, diff, to, to1, tr, rn in rows:
        speed = f"{tr / to:.1f}x ({tr / to1:.1f}x)" if tr else "-"
        print(f"| {name} | {vo:.6f} | {f(vr, '.6f')} | {f(diff, '.2e')} | {to:.3f} | {to1:.3f} | {f(tr, '.3f')} "
              f"| {speed} | {rn} |")


if __name__ == "__main__":
    main()
