"""Does a low-resolution panorama flatter camouflage? The built-in `panorama` scene at 1024, 512 and 256 wide.

The real HDRIs of `data_manifests/pmndrs_hdris.toml` are 512 x 256 (0.70 degrees per texel): at the demo size
(96 px over a 30 degree field of view, 0.31 degrees per pixel) their backdrop is blurred over about two pixels,
and the ground projected from them as well. This takes the built-in plaza panorama (1024 x 512, rendered
offline), box-downsamples it to 512 x 256 and 256 x 128, writes one pack per size (the built-in scene's object,
placement, ground and start), runs `ours`, `mean` and `transparent` on each at the demo size of
`grids/real.toml`, and prints per size: how sharp the backdrop is (mean gradient magnitude of the evaluation
backgrounds' luminance, sRGB; and their PSNR against the 1024 backgrounds) and the evaluation metrics.

    python bench/panorama_blur.py --out /tmp/blur            # writes packs + grid, runs it (~10 min, 1 worker)
    python bench/panorama_blur.py --out /tmp/blur --no-run   # only the analysis of an earlier run
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SIZES = (1024, 512, 256)
METHODS = ("ours", "mean", "transparent")


def setup(out: Path) -> Path:
    from optimizer import backend
    from optimizer.scenes.data.registry import write_exr_float32
    from optimizer.scenes.environments import builtin_panorama
    from camo_base.imaging import load_exr

    backend.init()
    pano = load_exr(builtin_panorama())
    out.mkdir(parents=True, exist_ok=True)
    img = pano
    for size in SIZES:
        while img.shape[1] > size:
            h, w = img.shape[:2]
            img = img.reshape(h // 2, 2, w // 2, 2, 3).mean((1, 3))  # box filter: energy kept, no ringing
        (out / f"plaza_{size}.exr").write_bytes(write_exr_float32(img))
        (out / f"plaza_{size}.toml").write_text(f'''name = "plaza-{size}"
# the built-in `panorama` scene with its plaza panorama at {size} x {size // 2}
[object]
primitive = "utility_box"
size = 1.0
rotation = [0.0, 0.0, 40.0]
[environment]
panorama = "plaza_{size}.exr"
capture_height = 1.6
ground = true
ground_extent = 5.0
[material]
roughness = 0.5
''')
    grid = (REPO / "grids" / "real.toml").read_text()
    body = grid[grid.index("[optimize]"):]
    scenes = ", ".join(f'"plaza_{s}.toml"' for s in SIZES)
    methods = ", ".join(f'"{m}"' for m in METHODS)
    (out / "blur.toml").write_text(f'name = "blur"\nscenes = [{scenes}]\nmethods = [{methods}]\nseeds = [0]\n\n{body}')
    return out / "blur.toml"


def sharpness(png: Path) -> float:
    from PIL import Image

    y = np.asarray(Image.open(png).convert("L"), np.float64) / 255.0
    gx, gy = np.diff(y, axis=1)[:-1], np.diff(y, axis=0)[:, :-1]
    return float(np.mean(np.hypot(gx, gy)))


def analyse(out: Path) -> None:
    import pandas as pd
    from PIL import Image

    rows = []
    bgs: dict[tuple[int, int], np.ndarray] = {}
    sharp: dict[int, list[float]] = {s: [] for s in SIZES}
    for metrics in sorted(out.glob("grid*/cells/*/eval/*/metrics.csv")):  # grid/, and e.g. grid_seeds/
        df = pd.read_csv(metrics)
        rows.append(df)
        run = metrics.parent.name
        size = int(run.split("__")[0].split("_")[1])
        if sharp[size]:
            continue
        for png in sorted((metrics.parent / "renders").glob("*/view_*_bg.png")):
            sharp[size].append(sharpness(png))
            bgs[(size, int(png.stem.split("_")[1]))] = np.asarray(Image.open(png).convert("RGB"), np.float64) / 255
    if not rows:
        raise SystemExit(f"no evaluations under {out}/grid*")
    df = pd.concat(rows)
    df["size"] = df["run"].str.extract(r"plaza_(\d+)").astype(int)
    df["opt_seed"] = df["run"].str.extract(r"__s(\d+)$").astype(int)  # the run's seed (column `seed` is evaluation's)
    print("backdrop (evaluation backgrounds, 8 novel views): mean |grad L| (sRGB) and PSNR vs the 1024 backdrop")
    for s in SIZES:
        if not sharp[s]:
            continue
        psnr = [10 * np.log10(1 / max(np.mean((bgs[(s, v)] - bgs[(1024, v)]) ** 2), 1e-12)) for (sz, v) in bgs if sz == s]
        p = "-" if s == 1024 else f"{np.mean(psnr):.2f} dB"
        print(f"  {s:5d} x {s // 2:<4d}  sharpness {np.mean(sharp[s]):.4f}   vs 1024: {p}")
    cols = ["psnr", "ssim", "lpips_proxy", "sifid_proxy"]
    per_run = df.groupby(["region", "method", "size", "opt_seed"])[cols].mean().reset_index()
    table = per_run.groupby(["region", "method", "size"])[cols].agg(["mean", "std", "count"]).reset_index()
    for region in ("crop", "full"):
        print(f"\n{region} (mean over views, then seeds; +- std over seeds): method  size  seeds  " + "  ".join(cols))
        sub = table[table.region == region].sort_values(["method", "size"], ascending=[True, False])
        for _, r in sub.iterrows():
            n = int(r[(cols[0], "count")])
            vals = "  ".join(f"{r[(c, 'mean')]:.4f}" + (f" +- {r[(c, 'std')]:.4f}" if n > 1 else "") for c in cols)
            print(f"  {r[('method', '')]:12s} {int(r[('size', '')]):5d}  {n}  {vals}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--no-run", action="store_true")
    args = ap.parse_args()
    if not args.no_run:
        grid = setup(args.out)
        subprocess.run([sys.executable, "-m", "camo.cli", "grid", "run", str(grid), "--out", str(args.out / "grid"),
                        "--workers", str(args.workers)], check=True, cwd=REPO)
    analyse(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
