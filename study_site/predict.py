"""The simulated observer on the stimuli participants see (``camo study build-stimuli``, ``camo study predict``).

The observer (:mod:`evaluation.observer`) searches every stimulus of a set exactly as the site shows it: the image
file served to participants (the WebP when the set has one, else the PNG; object at its drawn, off-centre place),
at the site's display size, with the site's time limit, and its click scored against the set's mask. A rendered
set's object-free render of the same framing (``backgrounds/``, :func:`study_site.stimuli.background_path`)
gives the observer the background statistics of each region (its knowledge of the scene's ground), and, with
``--observer surfaces=geometry``, that render's surface normals (``backgrounds/*_normals.npz``,
:func:`study_site.stimuli.surface_path`) its surfaces -- floor, walls -- on which a place's surround is taken; sets
without a background (``--copy``) use the image's own statistics, sets without normals (built before them;
``camo study surfaces`` adds them) the colour grounds only. The predictions are what ``camo study power --predicted``
and the report's predicted Table I (``camo report EVAL_DIR --stimuli STIMULI_DIR``) read; the centred evaluation
renders are never used for them.

Display size: the site shows an image at ``DISPLAY_HEIGHT_SHARE`` (72 %) of the viewport's height, capped at
``DISPLAY_MAX_WIDTH_SHARE`` (94 %) of its width (:mod:`study_site.config`). On the reference viewport of
:data:`VIEWPORT_CSS` (1280 x 800 CSS px, the simulated participants' window) a square image is 576 px high; the
observer takes that height as :data:`REFERENCE_DEG` (16 deg, ``ObserverConfig.display_deg``: ~60 cm from a laptop
screen) and scales other aspect ratios by the height the site would give them.

Files written next to ``manifest.json`` (server-side only, like it; atomically)::

    predicted.parquet, predicted.csv   one row per stimulus: manifest identity (id, run, scene, method, ablation,
                                       condition, view, practice, placement) + the observer's p_found, p_miss,
                                       p_timeout, times, object_evidence, display_deg, n
    predicted_trials.parquet           one row per simulated trial: id, scene, method (condition label), view,
                                       practice, trial, found, timed_out, rt_s, time_limit_s
    predicted_config.json              observer settings, trials per stimulus, seed, the manifest's creation time
    predicted_power/                   power.md, power.csv, power_needed.csv, power.png of the formal stimuli
                                       (:func:`study_site.power.write_predicted_power`, run by the CLI after the
                                       predictions; absent with fewer than two methods)
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from camo_base import atomic, seeds
from camo_base.errors import CamoError
from camo_base.tables import read_parquet, write_parquet

#: The simulated participants' window (CSS px) and the visual angle of the image height the site gives a square
#: image in it (576 px at the default 72 %).
VIEWPORT_CSS = (1280, 800)
REFERENCE_DEG = 16.0


def display_deg(width: int, height: int, site_config: dict[str, Any] | None = None) -> float:
    """Visual degrees of the displayed image's height, as the site lays out a ``width`` x ``height`` image on the
    reference viewport (see the module docstring)."""
    from study_site.config import DEFAULTS

    cfg = {**DEFAULTS, **(site_config or {})}
    vw, vh = VIEWPORT_CSS
    shown_h = min(cfg["DISPLAY_HEIGHT_SHARE"] * vh, cfg["DISPLAY_MAX_WIDTH_SHARE"] * vw * height / width)
    return REFERENCE_DEG * shown_h / (DEFAULTS["DISPLAY_HEIGHT_SHARE"] * vh)


def predict_stimulus_set(stim_dir: str | Path, n: int = 200, seed: int = 0, config=None,
                         time_limit_s: float | None = None, progress: bool = False,
                         log: Callable[[str], None] | None = None):
    """Run the observer on every stimulus of the set in ``stim_dir`` (``n`` simulated trials each) and write the
    predicted* files of the module docstring (the power curve: :func:`study_site.power.write_predicted_power`). Returns ``(per stimulus, per trial)`` DataFrames.

    ``config``: an :class:`evaluation.observer.ObserverConfig` (its ``display_deg`` is the reference for a square
    image; ``time_limit_s`` defaults to the site's). Seeds: stream ``observer`` of :mod:`camo_base.seeds`, per
    stimulus index in the manifest."""
    import dataclasses

    import pandas as pd

    from evaluation.observer import ObserverConfig, make_cells, predict_stimulus
    from study_site.config import DEFAULTS
    from study_site.stimuli import StimulusSet, _load_rgb, background_path, load_normals, surface_path

    say = log or (lambda s: print(s, file=sys.stderr))
    if not 1 <= n <= 100_000:
        raise CamoError(f"observer trials must be 1-100000, not {n}")
    sset = StimulusSet(stim_dir)
    base = config or ObserverConfig()
    limit = float(time_limit_s if time_limit_s is not None else DEFAULTS["TRIAL_TIME_LIMIT_S"])
    base = dataclasses.replace(base, time_limit_s=limit)
    base.validate()
    rows, trials = [], []
    n_bg = n_surf = 0
    t0 = time.perf_counter()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(sset.stimuli), desc="observer", unit="stimulus", file=sys.stderr, leave=False)
    for k, s in enumerate(sset.stimuli):
        webp = sset.image_path(s, ".webp")  # what the site serves first (study_site.stimuli.image_names)
        img = _load_rgb(webp if webp.is_file() else sset.image_path(s))
        mask = sset.mask(s)
        if mask.shape != img.shape[:2]:
            raise CamoError(f"{sset.mask_path(s)}: mask size differs from its image")
        deg = display_deg(img.shape[1], img.shape[0]) * base.display_deg / REFERENCE_DEG
        cfg = dataclasses.replace(base, display_deg=deg)
        bgp = background_path(sset.root, s.scene, s.view)
        bg = _load_rgb(bgp) if bgp.is_file() and not s.practice else None
        if bg is not None and bg.shape != img.shape:
            bg = None  # a background of another size is not this framing's
        use = bg is not None and cfg.surround == "ground" and cfg.surfaces == "geometry"
        normals = load_normals(surface_path(sset.root, s.scene, s.view), img.shape[:2]) if use else None
        cells = make_cells(img, cfg, background=bg, normals=normals)
        p = predict_stimulus(img, mask, n, seeds.seed("observer", seed, stimulus=k), cfg, cells=cells)
        n_bg += bg is not None
        n_surf += normals is not None
        ident = {"id": s.id, "run": s.run, "scene": s.scene, "object": s.object, "method": s.method,
                 "ablation": s.ablation or "", "condition": s.condition, "view": str(s.view), "practice": s.practice,
                 "width": s.width, "height": s.height, "centroid_x": s.centroid_x, "centroid_y": s.centroid_y,
                 "area_share": s.area_share}
        rows.append({**ident, "n": n, "display_deg": deg, **p.summary()})
        r = p.result
        trials.append(pd.DataFrame({"id": s.id, "scene": s.scene, "method": s.condition, "view": str(s.view),
                                    "practice": s.practice, "trial": np.arange(n), "found": r.found,
                                    "timed_out": r.timed_out, "rt_s": r.rt_s, "time_limit_s": limit}))
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    views = pd.DataFrame(rows)
    per_trial = pd.concat(trials, ignore_index=True)
    root = sset.root
    with atomic.atomic_path(root / "predicted.parquet") as tmp:
        write_parquet(views, tmp)
    with atomic.atomic_path(root / "predicted.csv") as tmp:
        views.to_csv(tmp, index=False)
    with atomic.atomic_path(root / "predicted_trials.parquet") as tmp:
        write_parquet(per_trial, tmp)
    atomic.write_json(root / "predicted_config.json", {
        "observer": base.to_dict(), "reference_display_deg": base.display_deg, "viewport_css": list(VIEWPORT_CSS),
        "trials_per_stimulus": n, "seed": seed, "stimuli_with_background": n_bg,
        "stimuli_with_surfaces": n_surf, "manifest_created": sset.data.get("created"),
        "seconds": round(time.perf_counter() - t0, 1)})
    say(f"observer: {len(views)} stimuli x {n} simulated trials in {time.perf_counter() - t0:.1f} s "
        f"({n_bg} with their object-free background's statistics, {n_surf} with its surfaces' normals used)")
    return views, per_trial


def read_predicted(stim_dir: str | Path):
    """``(per stimulus, per trial, config)`` of a stimulus set's predictions; CamoError when it has none."""
    import pandas as pd

    d = Path(stim_dir)
    p, q = d / "predicted.parquet", d / "predicted_trials.parquet"
    if not p.is_file() or not q.is_file():
        hint = (" (an evaluation directory: the observer runs on the stimuli people see; build them with `camo study "
                "build-stimuli EVAL_DIR --out STIMULI_DIR`)" if (d / "renders.json").is_file() else
                " (run `camo study predict STIMULI_DIR`, or build it with `camo study build-stimuli`)")
        raise CamoError(f"{d}: no observer predictions{hint}")
    try:
        views, trials = read_parquet(p), read_parquet(q)
        cfg = json.loads((d / "predicted_config.json").read_text(encoding="utf-8")) \
            if (d / "predicted_config.json").is_file() else {}
    except Exception as exc:  # pyarrow raises several types for a corrupt file
        raise CamoError(f"{d}: cannot read the predictions "
                        f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    return views, trials, cfg
