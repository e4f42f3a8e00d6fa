"""Picture sheet of a ``bench/bench_convergence.py`` run: per scene a background row, then one row per variant.

Reads the ``final_<scene>_<variant>.png`` files the bench writes (background row over with-object row, the
final snapshot on the bench's jittered novel views) and stacks them with a label column, upscaled for viewing:

    python bench/convergence_pictures.py bench_out/convergence --scenes meadow,room,split,pack_meadow_vase \
        --variants fast,paper,mean --out docs/results/convergence_pictures.jpg

A scene given as ``pack:ENV:OBJECT`` to the bench is named ``pack_ENV_OBJECT`` in the file names.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw


def rows_of(path: Path, views: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(background row, with-object row) of one ``final_*.png``, each ``(h, W, 3)`` uint8; with ``views``, only the
    first ``views`` square views of each row."""
    a = np.asarray(Image.open(path).convert("RGB"))
    h = a.shape[0] // 2
    w = a.shape[1] if views is None else min(a.shape[1], views * h)
    return a[:h, :w], a[h:2 * h, :w]


def sheet(out_dir: Path, scenes: list[str], variants: list[str], scale: int = 2, label_w: int = 180,
          views: int | None = None) -> Image.Image:
    rows: list[tuple[str, np.ndarray]] = []
    for scene in scenes:
        files = {v: out_dir / f"final_{scene}_{v}.png" for v in variants}
        missing = [str(p) for p in files.values() if not p.is_file()]
        if missing:
            raise SystemExit(f"convergence_pictures: missing {missing[0]} (run bench/bench_convergence.py first)")
        rows.append((f"{scene}\nbackground", rows_of(files[variants[0]], views)[0]))
        rows += [(f"{scene}\n{v}", rows_of(files[v], views)[1]) for v in variants]
    width = max(r.shape[1] for _, r in rows) * scale
    tiles = []
    for label, img in rows:
        big = np.asarray(Image.fromarray(img).resize((img.shape[1] * scale, img.shape[0] * scale), Image.NEAREST))
        tile = Image.new("RGB", (label_w + width, big.shape[0]), "white")
        tile.paste(Image.fromarray(big), (label_w, 0))
        ImageDraw.Draw(tile).multiline_text((8, big.shape[0] // 2 - 14), label.replace("_", " "), fill="black")
        tiles.append(tile)
    out = Image.new("RGB", (label_w + width, sum(t.height for t in tiles)), "white")
    y = 0
    for t in tiles:
        out.paste(t, (0, y))
        y += t.height
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench_out", type=Path)
    ap.add_argument("--scenes", default="meadow,room,split")
    ap.add_argument("--variants", default="fast,paper,mean")
    ap.add_argument("--scale", type=int, default=2)
    ap.add_argument("--views", type=int, help="only the first N views of each row (default: all)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    img = sheet(args.bench_out, [s.replace(":", "_") for s in args.scenes.split(",")], args.variants.split(","),
                args.scale, views=args.views)
    tmp = args.out.with_name(args.out.name + ".tmp" + args.out.suffix)
    img.save(tmp, quality=90)
    tmp.replace(args.out)
    print(f"wrote {args.out} ({img.width}x{img.height})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
