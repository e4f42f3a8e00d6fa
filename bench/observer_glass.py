"""Why the observer misses room's glass chairs: the figures of docs/results/observer.md, "Room's Transparent cell".

Two measurements on stimulus sets with their object-free backgrounds (``camo study build-stimuli``), neither a
change of the model:

``--outline SET ...``: per stimulus, the pixels the cast-shadow texture test reads as ground in shadow
(:func:`evaluation.observer.cast_shadow_map` > 0.5) on the object and off it, and the **sharpness of their
outline**: the scale-normalised gradient magnitude ``s |grad G_s * r|`` of the light ratio against the object-free
view at the same place (``r = ln(background / image)`` of linear luminance, so the ground's own texture cancels) at
``s1`` = 0.7 px (the derivative floor of the observer's features) over the same at ``s2`` = the finest centre
scale (``centre_sigmas_deg[0]`` x ``feature_px_per_deg`` = 2.4 px), read on the rim of those regions (within 3 px
of their boundary) on the edge's own line (the ``s2`` gradient at least 0.15, a 14 % light step, and within 10 % of
its largest value over 5 x 5 px: :func:`edge_ridge`). For an ideal step the ratio is 1
whatever the scale (a one-pixel step sampled on the grid: 0.82); for an edge blurred over much more than ``s2`` -- a
penumbra -- it is ``s1 / s2`` = 0.29 (the blur-scale logic of Elder & Zucker 1998, IEEE PAMI 20, and Lindeberg
1998, IJCV 30). Median over the rim pixels, ``-`` where fewer than 6; ``--by-scene``: per scene and method, the
range and median of the stimuli's medians; ``--regions``: per connected region in shadow (at least 20 px), its own
rim's sharpness, pooled per scene into regions mostly on the object (> 70 % of their pixels), mixed, and off it.

``--probe SET --stimuli METHOD:VIEW,...``: for the named stimuli, the object's largest discriminability D, object
evidence O and verification V, and the share of 100 simulated trials (seed 0) that find it, under (a) the default
observer, (b) no shadow discount at all (``cast_shadow=none,shadow_shape=none,shadow_discount=0``: an upper bound,
it lifts every real shadow too), (c) the default with a surround that keeps to the floor -- the grounds split where
the object-free view has an edge (colour means of two half-windows 0.5 deg apart differing by more than
``--edge`` (1.3, chosen by eye on room's views: a probe, not a rule) in units of the sides' spread), and (d) (b)
and (c) together.

Usage: python bench/observer_glass.py --outline STIM_DIR ... | --probe STIM_DIR --stimuli transparent:0,...
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np


def _load(sset, s):
    from study_site.stimuli import _load_rgb, background_path

    webp = sset.image_path(s, ".webp")
    img = _load_rgb(webp if webp.is_file() else sset.image_path(s))
    return img, sset.mask(s).astype(bool), _load_rgb(background_path(sset.root, s.scene, s.view))


#: The fine scale of the outline's sharpness (Gaussian sigma, px): the derivative floor of the observer's features.
FINE_PX = 0.7


def scale_gradient(x: np.ndarray, s: float) -> np.ndarray:
    """``s |grad G_s * x|``: the scale-normalised gradient magnitude of a 2-D map at Gaussian scale ``s`` (px). For
    a step of height ``A`` its peak is ``A / sqrt(2 pi)`` at every scale; for a linear ramp of width ``w`` >> ``s``
    it is ``s A / w`` (Lindeberg 1998), so the ratio of two scales is 1 for a step and ``s1 / s2`` for a blur.
    Sampled, a one-pixel step reads 0.82 at ``s1`` = 0.7 px against 2.4 px (the finer kernel is undersampled;
    tests/test_bench_observer_glass.py)."""
    from scipy import ndimage

    gx = ndimage.gaussian_filter(x, s, order=(0, 1), mode="nearest")
    gy = ndimage.gaussian_filter(x, s, order=(1, 0), mode="nearest")
    return s * np.hypot(gx, gy)


def edge_ridge(g2: np.ndarray) -> np.ndarray:
    """Where the coarse gradient ``g2`` is an edge: at least 0.15 (a 14 % light step) and within 10 % of its largest
    value over the 5 x 5 px around (the edge's own line, not the 2-3 px beside it where the fine scale reads ~0)."""
    from scipy import ndimage

    return (g2 > 0.15) & (g2 >= 0.9 * ndimage.maximum_filter(g2, size=5, mode="nearest"))


def outline_table(dirs: list[Path], by_scene: bool = False) -> str:
    from scipy import ndimage

    from evaluation import observer as ob
    from study_site.stimuli import StimulusSet

    cfg = ob.ObserverConfig()
    s1, s2 = FINE_PX, cfg.centre_sigmas_deg[0] * cfg.feature_px_per_deg
    grad = scale_gradient

    out = ["| scene | method | view | in shadow by the texture test (px): on object / off | outline sharpness "
           "on object (rim px) | off object (rim px) |", "|---|---|---|---|---|---|"]
    per: dict[tuple[str, str], tuple[list, list]] = {}
    for d in dirs:
        sset = StimulusSet(d)
        for s in [s for s in sset.stimuli if not s.practice]:
            img, mask, bg = _load(sset, s)
            if img.shape[0] != round(cfg.display_deg * cfg.feature_px_per_deg):
                raise SystemExit(f"{d}: {img.shape[0]} px stimuli are not on the feature grid")
            li, lb = ob._log_image(img), ob._log_image(bg)
            cast = ob.cast_shadow_map(li, lb, s2, cfg)
            r = (lb[..., 0] - li[..., 0]) / ob.LOG_UNITS
            g1, g2 = grad(r, s1), grad(r, s2)
            reg = cast > 0.5
            rim = ndimage.binary_dilation(reg, iterations=3) & ~ndimage.binary_erosion(reg, iterations=3)
            strong = rim & edge_ridge(g2)
            on = strong & ndimage.binary_dilation(mask, iterations=1)
            off = strong & ~ndimage.binary_dilation(mask, iterations=3)
            q = lambda m: f"{np.median(g1[m] / g2[m]):.2f} ({int(m.sum())})" if m.sum() > 5 else "-"  # noqa: E731
            for lst, m in zip(per.setdefault((s.scene, s.method), ([], [])), (on, off)):
                if m.sum() > 5:
                    lst.append(float(np.median(g1[m] / g2[m])))
            out.append(f"| {s.scene} | {s.method} | {s.view} | {int((reg & mask).sum())} / {int((reg & ~mask).sum())} "
                       f"| {q(on)} | {q(off)} |")
    if by_scene:  # per scene and method: the stimuli's medians, their range and median
        rng = lambda v: f"{min(v):.2f}-{max(v):.2f} ({np.median(v):.2f}, {len(v)})" if v else "-"  # noqa: E731
        out = ["| scene | method | outline sharpness on the object: range (median, stimuli) | off the object "
               "(cast shadows) | stimuli off the object above 0.5 |", "|---|---|---|---|---|"]
        for (sc, me), (a, b) in per.items():
            out.append(f"| {sc} | {me} | {rng(a)} | {rng(b)} | {sum(x > 0.5 for x in b)} |")
    return "\n".join(out)


def region_table(dirs: list[Path], min_px: int = 20) -> str:
    """Per connected region of ground in shadow by the texture test (map > 0.5, at least ``min_px`` px): its share
    on the object and the median sharpness of its own rim (as :func:`outline_table`); pooled per scene into the
    regions mostly on the object (> 50 % of their pixels) and mostly off it."""
    from scipy import ndimage

    from evaluation import observer as ob
    from study_site.stimuli import StimulusSet

    cfg = ob.ObserverConfig()
    s2 = cfg.centre_sigmas_deg[0] * cfg.feature_px_per_deg
    out = ["| scene | regions mostly on the object: n, sharpness range (median) | mixed (30-70 % on it): n "
           "| mostly off it: n, sharpness range (median), above 0.5 |", "|---|---|---|---|"]
    for d in dirs:
        sset = StimulusSet(d)
        on_v, off_v, mixed = [], [], 0
        for s in [s for s in sset.stimuli if not s.practice]:
            img, mask, bg = _load(sset, s)
            li, lb = ob._log_image(img), ob._log_image(bg)
            r = (lb[..., 0] - li[..., 0]) / ob.LOG_UNITS
            ratio = scale_gradient(r, FINE_PX) / np.maximum(scale_gradient(r, s2), 1e-9)
            strong = edge_ridge(scale_gradient(r, s2))
            lab, n = ndimage.label(ob.cast_shadow_map(li, lb, s2, cfg) > 0.5)
            for k in range(1, n + 1):
                reg = lab == k
                if reg.sum() < min_px:
                    continue
                rim = ndimage.binary_dilation(reg, iterations=3) & ~ndimage.binary_erosion(reg, iterations=3) & strong
                if rim.sum() < 6:
                    continue
                share, v = float(mask[reg].mean()), float(np.median(ratio[rim]))
                if share > 0.7:
                    on_v.append(v)
                elif share < 0.3:
                    off_v.append(v)
                else:
                    mixed += 1
        rng = lambda v: f"{len(v)}, {min(v):.2f}-{max(v):.2f} ({np.median(v):.2f})" if v else "0"  # noqa: E731
        out.append(f"| {sset.stimuli[0].scene} | {rng(on_v)} | {mixed} | {rng(off_v)}, "
                   f"{sum(x > 0.5 for x in off_v)} |")
    return "\n".join(out)


def edge_segments(lab: np.ndarray, sky: np.ndarray, cfg, edge: float) -> np.ndarray:
    """The probe's grounds: connected places of the object-free view not on an edge (see the module docstring);
    pieces under ``SEGMENT_MIN_SHARE`` of the frame and the edges join the nearest piece; the sky its own."""
    from scipy import ndimage

    from evaluation import observer as ob

    s = ob.SEGMENT_SIGMA_DEG * cfg.feature_px_per_deg
    f = np.moveaxis(lab.astype(np.float64), -1, 0)
    mu = np.stack([ndimage.gaussian_filter(c, s, mode="nearest") for c in f])
    m2 = np.stack([ndimage.gaussian_filter(c * c, s, mode="nearest") for c in f])
    var = np.maximum(m2 - mu * mu, 0).sum(0) + 3 * cfg.internal_noise ** 2
    dmax = np.zeros(sky.shape)
    for dy, dx in [(0, 1), (1, 0), (1, 1), (1, -1)]:
        n = math.hypot(dy, dx)
        oy, ox = dy / n * s, dx / n * s
        a = ndimage.shift(mu, (0, oy, ox), order=1, mode="nearest")
        b = ndimage.shift(mu, (0, -oy, -ox), order=1, mode="nearest")
        va = ndimage.shift(var, (oy, ox), order=1, mode="nearest")
        vb = ndimage.shift(var, (-oy, -ox), order=1, mode="nearest")
        dmax = np.maximum(dmax, np.sqrt(((a - b) ** 2).sum(0) / (0.5 * (va + vb))))
    lab_, _ = ndimage.label((dmax < edge) & ~sky)
    sizes = np.bincount(lab_.ravel())
    sizes[0] = 0
    big = np.where(sizes >= ob.SEGMENT_MIN_SHARE * dmax.size)[0]
    keep = np.where(np.isin(lab_, big), lab_, 0)
    idx = ndimage.distance_transform_edt(keep == 0, return_distances=False, return_indices=True)
    _, full = np.unique(keep[idx[0], idx[1]], return_inverse=True)
    full = full.reshape(dmax.shape)
    return np.where(sky, full.max() + 1, full) if sky.any() else full


def probe_table(d: Path, wanted: list[str], edge: float) -> str:
    from evaluation import observer as ob
    from study_site.stimuli import StimulusSet

    sset = StimulusSet(d)
    none = dict(cast_shadow="none", shadow_shape="none", shadow_discount=0.0)
    out = ["| stimulus | (a) default: D / O / V, found | (b) no shadow discount | (c) floor-only surround "
           "| (d) both |", "|---|---|---|---|---|"]
    for s in [s for s in sset.stimuli if not s.practice and f"{s.method}:{s.view}" in wanted]:
        img, mask, bg = _load(sset, s)
        lab_bg = ob.srgb_to_lab(bg)
        sky = ob.sky_map(ob._log_image(bg))
        cells = []
        for kw, split in [({}, False), (none, False), ({}, True), (none, True)]:
            cfg = dataclasses.replace(ob.ObserverConfig(), **kw)
            seg = edge_segments(lab_bg, sky, cfg, edge) if split else None
            m = ob.evidence_maps(img, cfg, bg, segments=seg)
            c = ob.make_cells(img, cfg, maps=m, background=bg)
            r = ob.simulate_search(img, 100, 0, cfg, mask=mask, cells=c)
            cells.append(f"{m.d[mask].max():.1f} / {m.obj[mask].max():.1f} / {m.verify[mask].max():.1f}, "
                         f"{100 * r.found.mean():.0f} %")
        out.append(f"| {s.scene} {s.method} view {s.view} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--outline", nargs="+", type=Path, default=[], help="stimulus sets: the outline table")
    ap.add_argument("--by-scene", action="store_true", help="--outline: one row per scene and method")
    ap.add_argument("--regions", action="store_true", help="--outline: per connected region in shadow, per scene")
    ap.add_argument("--probe", type=Path, help="a stimulus set: the probe table")
    ap.add_argument("--stimuli", default="transparent:0,transparent:1,transparent:3",
                    help="METHOD:VIEW,... of --probe")
    ap.add_argument("--edge", type=float, default=1.3, help="the probe's edge d' (chosen by eye on room)")
    a = ap.parse_args(argv)
    if not a.outline and not a.probe:
        ap.error("give --outline and/or --probe")
    for d in a.outline + ([a.probe] if a.probe else []):
        if not (d / "manifest.json").is_file():
            ap.error(f"{d}: not a stimulus set (no manifest.json)")
    if a.outline:
        print(region_table(a.outline) if a.regions else outline_table(a.outline, a.by_scene))
    if a.probe:
        print(probe_table(a.probe, a.stimuli.split(","), a.edge))


if __name__ == "__main__":
    main()
