"""Where an optimised object's bright specks come from: surface glints or multi-bounce sun paths.

Two reports (the numbers in ``docs/results/README.md``, "Where the sparkle comes from"):

* ``RUN_DIR ...``: renders each run's ``scene.xml`` from its training cameras with Mitsuba's ``path``
  integrator at every ``--depths`` value and counts the pixels brighter than ``--threshold`` (linear
  radiance), split into the object (first hit of the ray through the pixel centre) and everything else. Depth 2 is direct light
  only: bright object pixels there are reflections of the light source itself; what appears at larger
  depths went through or off the object first (refraction, caustics on the ground).
* ``--eval EVAL_DIR``: per run of a ``camo evaluate`` folder, on its 8-bit renders, "sparkle %" (object
  pixels brighter than the background's 99.5th luminance percentile; ``grid_figures.py``'s measure) and
  "glint px" (object pixels brighter than twice that percentile in linear luminance, summed over views).

    python bench/glint_sources.py RUN_DIR [RUN_DIR ...] [--spp 256] [--depths 2,3,4,6] [--threshold 0.2]
    python bench/glint_sources.py --eval EVAL_DIR
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from grid_figures import REC709, read, sparkle_share  # noqa: E402


def glint_pixels(evdir: Path, recs: list[dict], factor: float = 2.0) -> tuple[int, int]:
    """(object pixels brighter than ``factor`` x the background's 99.5th percentile, object pixels), linear Y."""
    n = total = 0
    for rec in recs:
        bg = (np.asarray(read(evdir, rec, "background"), np.float64) / 255) ** 2.2 @ REC709
        im = (np.asarray(read(evdir, rec, "image"), np.float64) / 255) ** 2.2 @ REC709
        mask = np.asarray(read(evdir, rec, "mask", "L")) > 127
        n += int((im[mask] > factor * np.quantile(bg, 0.995)).sum())
        total += int(mask.sum())
    return n, total


def eval_report(evdir: Path) -> None:
    recs = json.loads((evdir / "renders.json").read_text())
    print(f"{'run':42s} {'sparkle %':>9s} {'glint px':>14s}")
    for run in sorted({r["run"] for r in recs}):
        mine = [r for r in recs if r["run"] == run]
        n, total = glint_pixels(evdir, mine)
        print(f"{run:42s} {100 * sparkle_share(evdir, mine):9.2f} {n:6d} / {total:6d}")


def object_mask(scene, sensor, obj) -> np.ndarray:
    """(H, W) bool: the first hit of the ray through each pixel centre is ``obj``."""
    import drjit as dr
    import mitsuba as mi

    w, h = sensor.film().crop_size()
    i = dr.arange(mi.UInt32, w * h)
    pos = mi.Point2f((mi.Float(i % w) + 0.5) / w, (mi.Float(i // w) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    return np.asarray(si.is_valid() & (si.shape == mi.ShapePtr(obj)), dtype=bool).reshape(h, w)


def depth_report(run: Path, depths: list[int], spp: int, threshold: float) -> None:
    from optimizer import backend

    backend.init()
    import mitsuba as mi

    scene = mi.load_file(str(run / "scene.xml"))
    obj = next((s for s in scene.shapes() if s.id() == "object"), None)
    if obj is None:
        raise SystemExit(f"glint_sources: {run}/scene.xml has no shape with id 'object'")
    is_obj = np.stack([object_mask(scene, s, obj) for s in scene.sensors()])
    print(f"{run}: {len(scene.sensors())} views, {spp} spp, pixels brighter than {threshold:g} (linear)")
    print(f"{'max_depth':>9s} {'object':>7s} {'other':>7s}")
    for depth in depths:
        integrator = mi.load_dict({"type": "path", "max_depth": depth})
        y = np.stack([np.array(mi.render(scene, sensor=s, integrator=integrator, spp=spp, seed=i)) @ REC709
                      for i, s in enumerate(scene.sensors())])
        bright = y > threshold
        print(f"{depth:9d} {int((bright & is_obj).sum()):7d} {int((bright & ~is_obj).sum()):7d}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", type=Path, metavar="RUN_DIR", help="output of `camo optimize`")
    ap.add_argument("--eval", type=Path, metavar="EVAL_DIR", help="output of `camo evaluate`")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--depths", default="2,3,4,6", help="comma list of path max_depth values")
    ap.add_argument("--threshold", type=float, default=0.2, help="linear radiance a bright pixel exceeds")
    args = ap.parse_args(argv)
    if not args.runs and args.eval is None:
        ap.error("give RUN_DIRs, --eval EVAL_DIR, or both")
    for run in args.runs:
        if not (run / "scene.xml").is_file():
            ap.error(f"no scene.xml in {run} (not a `camo optimize` output?)")
    if args.eval is not None and not (args.eval / "renders.json").is_file():
        ap.error(f"no renders.json in {args.eval} (not a `camo evaluate` output?)")
    try:
        depths = [int(d) for d in args.depths.split(",")]
    except ValueError:
        ap.error(f"--depths must be a comma list of integers, got {args.depths!r}")
    for run in args.runs:
        depth_report(run, depths, args.spp, args.threshold)
    if args.eval is not None:
        eval_report(args.eval)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
