"""What Stage 1 sees of a clear body's caustic: the cast shadow's mean luminance at a few spp, as the loss sees it
(linear, and through the ``fast`` preset's soft clamp), against the converged render (issue 29, giveaways.md).

A transmissive body lets sunlight through to its shadow, and a path tracer reaches that light only when a ground
bounce happens to pass through the body to the sun: at Stage 1's 4 spp it arrives as a few very bright samples. The
loss's soft clamp (``--loss-clamp``, :func:`optimizer.optimise.loss.soft_clamp`, white point ``FACTOR`` x the
background's 99th percentile) cuts those samples, so the loss sees the lit shadow darker than it converges to.

    python bench/caustic_bias.py --ref /tmp/gw29s9/g/eval/meadow --low EVAL_4SPP EVAL_16SPP \\
        --run meadow-coarse1_auto_r5 --shadow-run meadow-today

``--ref``: a ``camo evaluate`` directory at a converged spp holding both runs; ``--low``: evaluations of the same
runs at a few spp with the same seed (the same views and cameras). The shadow is where the opaque run's converged
render is below ``--dark`` x the background's luminance, outside that run's object mask. Prints a Markdown table:
per view and spp, the shadow's mean luminance (Rec. 709, linear) of the background, of the clear run as rendered
(linear mean), soft-clamped as Stage 1's loss sees it, and its 99th percentile.

``--compare RUN2 ...``: does another clear run put the light in the same place? Per view, each run's share of shadow
pixels brighter than the background's 99th percentile (outside the object), the overlap of those bright pixels
(intersection over union) and the Pearson correlation of the two runs' shadow luminance, at ``--ref``'s spp (RUN2
looked up in ``--ref`` and in the other ``eval*/SCENE`` beside it, as is ``--run``: the same views).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

from camo_base.imaging import REC709_LUMA
from optimizer.optimise.loss import soft_clamp_np, white_point


def luminance(img: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear RGB ``(..., 3)``."""
    return np.asarray(img, np.float64) @ np.asarray(REC709_LUMA, np.float64)


def shadow_mask(bg: np.ndarray, opaque: np.ndarray, object_mask: np.ndarray, dark: float) -> np.ndarray:
    """Pixels where ``opaque`` (linear ``(H, W, 3)``) is below ``dark`` x the background's luminance, outside the
    object's ``(H, W)`` boolean mask: its cast shadow.

    >>> bg = np.ones((2, 2, 3)); op = bg.copy(); op[0, 0] = 0.1; op[1, 1] = 0.1
    >>> shadow_mask(bg, op, np.array([[False, False], [False, True]]), 0.6).tolist()
    [[True, False], [False, False]]
    """
    return (luminance(opaque) < dark * luminance(bg)) & ~object_mask


def compare_shadows(a: np.ndarray, b: np.ndarray, bright: float) -> dict[str, float]:
    """Two runs' shadow luminances ``a``, ``b`` (the same pixels, 1-D) against the threshold ``bright``: the share of
    each above it, the intersection over union of those pixels, and the Pearson correlation of ``a`` and ``b``.

    >>> r = compare_shadows(np.array([0., 1, 1, 0]), np.array([0., 1, 0, 1]), 0.5)
    >>> r["bright_a"], r["bright_b"], round(r["iou"], 3), round(r["corr"], 3)
    (0.5, 0.5, 0.333, 0.0)
    """
    ba, bb = a > bright, b > bright
    union = int((ba | bb).sum())
    return {"bright_a": float(ba.mean()), "bright_b": float(bb.mean()),
            "iou": float((ba & bb).sum() / union) if union else float("nan"), "corr": float(np.corrcoef(a, b)[0, 1])}


def _renders_of(ref: Path, run: str) -> Path:
    """The evaluation directory holding ``run``'s renders: ``ref`` or another ``eval*/SCENE`` beside it."""
    for d in [ref, *sorted(ref.parent.parent.glob(f"eval*/{ref.name}"))]:
        if (d / "renders" / run).is_dir():
            return d
    raise SystemExit(f"{ref}: no renders of {run} here or in eval*/{ref.name} beside it")


def _load(d: Path, run: str, view: int, kind: str) -> np.ndarray:
    return np.load(d / "renders" / run / f"view_{view:02d}_{kind}.npy")


def _spp(d: Path) -> int:
    import tomllib

    return int(tomllib.loads((d / "eval_config.toml").read_text())["evaluate"]["spp"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ref", required=True, help="converged camo evaluate directory with both runs")
    ap.add_argument("--low", nargs="+", default=[], help="the same runs evaluated at a few spp (same seed)")
    ap.add_argument("--run", required=True, help="the clear run's name (its renders/ subdirectory)")
    ap.add_argument("--shadow-run", required=True, help="the opaque run whose shadow is the region")
    ap.add_argument("--loss-clamp", type=float, default=8.0, help="the soft clamp's factor (fast preset: 8)")
    ap.add_argument("--dark", type=float, default=0.6)
    ap.add_argument("--compare", nargs="+", default=[], help="other clear runs: where their shadow's light lands "
                    "against --run's (module doc)")
    a = ap.parse_args(argv)
    ref = Path(a.ref)
    run_ref = _renders_of(ref, a.run)  # (the opaque run's evaluation, or another one beside it: the same views)
    views = sorted({int(p.name[5:7]) for p in (run_ref / "renders" / a.run).glob("view_*_obj.npy")})
    if not views:
        raise SystemExit(f"{ref / 'renders' / a.run}: no view_*_obj.npy renders")
    print("| view | spp | shadow px | background | opaque run | clear run, linear | clear run, soft-clamped (loss) | "
          "clear run p99 |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for v in views:
        bg = _load(ref, a.shadow_run, v, "bg")
        mask = np.asarray(Image.open(ref / "renders" / a.shadow_run / f"view_{v:02d}_mask.png").convert("L")) > 127
        sh = shadow_mask(bg, _load(ref, a.shadow_run, v, "obj"), mask, a.dark)
        opaque = luminance(_load(ref, a.shadow_run, v, "obj"))[sh].mean()
        for d in [run_ref, *map(Path, a.low)]:
            b, x = _load(d, a.run, v, "bg"), _load(d, a.run, v, "obj")
            w = white_point(b[None], sh[None], a.loss_clamp)
            r = {"view": v, "spp": _spp(d), "px": int(sh.sum()), "bg": luminance(b)[sh].mean(), "opaque": opaque,
                 "linear": luminance(x)[sh].mean(), "clamped": luminance(soft_clamp_np(x, w))[sh].mean(),
                 "p99": float(np.percentile(luminance(x)[sh], 99))}
            rows.append(r)
            print(f"| {v} | {r['spp']} | {r['px']} | {r['bg']:.3f} | {r['opaque']:.3f} | {r['linear']:.3f} | "
                  f"{r['clamped']:.3f} | {r['p99']:.3f} |")
    for spp in sorted({r["spp"] for r in rows}):
        g = [r for r in rows if r["spp"] == spp]
        m = {k: float(np.mean([r[k] for r in g])) for k in ("bg", "opaque", "linear", "clamped", "p99")}
        print(f"| **mean** | {spp} | | {m['bg']:.3f} | {m['opaque']:.3f} | {m['linear']:.3f} | {m['clamped']:.3f} | "
              f"{m['p99']:.3f} |")
    if a.compare:
        print(f"\n| view | run | bright px, {a.run} | bright px, run | bright px overlap (IoU) | correlation |")
        print("|---|---|---|---|---|---|")
    for other in a.compare:
        od = _renders_of(ref, other)
        got = []
        for v in views:
            bg = _load(ref, a.shadow_run, v, "bg")
            mask = np.asarray(Image.open(ref / "renders" / a.shadow_run / f"view_{v:02d}_mask.png").convert("L")) > 127
            sh = shadow_mask(bg, _load(ref, a.shadow_run, v, "obj"), mask, a.dark)
            bright = float(np.percentile(luminance(bg)[~mask], 99))
            r = compare_shadows(luminance(_load(run_ref, a.run, v, "obj"))[sh], luminance(_load(od, other, v, "obj"))[sh],
                                bright)
            got.append(r)
            print(f"| {v} | {other} | {r['bright_a']:.2f} | {r['bright_b']:.2f} | {r['iou']:.2f} | {r['corr']:.3f} |")
        m = {k: float(np.mean([r[k] for r in got])) for k in got[0]}
        print(f"| **mean** | {other} | {m['bright_a']:.2f} | {m['bright_b']:.2f} | {m['iou']:.2f} | {m['corr']:.3f} |")
    print(json.dumps({"run": a.run, "shadow_run": a.shadow_run, "loss_clamp": a.loss_clamp}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
