"""Fake evaluation directories for tests and benchmarks (random images, rectangular masks)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def make_fake_eval_dir(
    root: str | Path,
    scenes: tuple[str, ...] = ("scene_a", "scene_b"),
    methods: tuple[str, ...] = ("method_x", "method_y"),
    views: int = 2,
    size: tuple[int, int] = (160, 120),
    seed: int = 0,
) -> list[dict]:
    """Write ``root/renders.json`` and PNGs as `camo evaluate` would; return the entries.

    Each entry gets a random RGB image and a rectangular object mask; the rectangle
    (``x0, y0, x1, y1``, half-open, image pixels) is stored in the entry as ``rect``
    so a test knows where the object is. ``size`` is ``(width, height)``.
    """
    from PIL import Image

    rng = np.random.default_rng(seed)
    root = Path(root)
    w, h = size
    entries = []
    for si, scene in enumerate(scenes):
        for method in methods:
            run = f"{scene}__{method}"
            d = root / "renders" / run
            d.mkdir(parents=True, exist_ok=True)
            for v in range(views):
                img = _smooth_noise(rng, w, h)
                bw, bh = max(4, w // 4), max(4, h // 4)
                x0 = int(rng.integers(1, w - bw - 1))
                y0 = int(rng.integers(1, h - bh - 1))
                patch = _smooth_noise(rng, bw, bh).astype(np.int16)
                region = img[y0 : y0 + bh, x0 : x0 + bw].astype(np.int16)
                img[y0 : y0 + bh, x0 : x0 + bw] = np.clip((3 * region + patch) // 4, 0, 255).astype(np.uint8)
                mask = np.zeros((h, w), np.uint8)
                mask[y0 : y0 + bh, x0 : x0 + bw] = 255
                stem = f"view_{v:02d}"
                Image.fromarray(img).save(d / f"{stem}_obj.png")
                Image.fromarray(img).save(d / f"{stem}_bg.png")
                Image.fromarray(mask).save(d / f"{stem}_mask.png")
                entries.append(
                    {
                        "run": run,
                        "scene": scene,
                        "object": f"object_{si}",
                        "method": method,
                        "ablation": "",
                        "view": v,
                        "image": f"renders/{run}/{stem}_obj.png",
                        "background": f"renders/{run}/{stem}_bg.png",
                        "mask": f"renders/{run}/{stem}_mask.png",
                        "depth": None,
                        "rect": [x0, y0, x0 + bw, y0 + bh],
                    }
                )
    (root / "renders.json").write_text(json.dumps(entries, indent=1))
    return entries


def _smooth_noise(rng, w: int, h: int) -> np.ndarray:
    """Low-frequency random RGB texture (``(h, w, 3)`` uint8) with a little pixel noise."""
    from PIL import Image

    gh, gw = max(2, h // 40), max(2, w // 40)
    lum = rng.uniform(70, 190, (gh, gw, 1))
    tint = rng.normal(0, 1, 3) * 18 + rng.normal(0, 1, (gh, gw, 3)) * 10  # muted, mostly shared hue
    coarse = np.clip(lum + tint, 0, 255).astype(np.uint8)
    smooth = np.asarray(Image.fromarray(coarse).resize((w, h), Image.BICUBIC), dtype=np.int16)
    noise = rng.integers(-10, 11, (h, w, 1), dtype=np.int16)
    return np.clip(smooth + noise, 0, 255).astype(np.uint8)


def mask_rects(stimuli_dir: str | Path) -> dict[str, tuple[int, int, int, int]]:
    """``{stimulus id: (x0, y0, x1, y1)}`` bounding boxes of the masks of a built stimulus set."""
    from .stimuli import StimulusSet

    ss = StimulusSet(stimuli_dir)
    out = {}
    for st in ss.stimuli:
        m = ss.mask(st)
        ys, xs = np.nonzero(m)
        out[st.id] = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
    return out
