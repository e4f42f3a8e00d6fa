"""``camo evaluate``: the automatic benchmark (paper Sec. IV-D, Table II) of run directories, external assets and
2D image triplets (:mod:`evaluation.inputs`), mixed in one evaluation.

For each run directory or asset: rebuild its scene, render jittered novel views (:mod:`evaluation.views`) with and
without the object at evaluation quality; for triplets take the given images. Score every view in two regions --
the ``full`` frame and the GANmouflage object ``crop`` (:func:`evaluation.metrics.object_crop_box` of the
visible-object mask) -- with the image metrics of :mod:`evaluation.metrics`, comparing the with-object image to the
background image, and time each metric, the evaluation render and (from the run directory or the user) the method.

Images enter the metrics exactly as the saved PNGs hold them: linear radiance -> sRGB
(``camo_base.imaging.linear_to_srgb``, tone-clipped) -> 8 bit. So every score can be recomputed from the PNGs
(or from the linear ``.npy`` renders through the same two steps).

Output (EVAL_DIR, every file written atomically; see CONTRIBUTING.md)::

    metrics.parquet, metrics.csv   one row per run x view x region, columns :data:`COLUMNS` (metrics, and where
                                   the object gives itself away: object / shadow / rest, :mod:`evaluation.giveaway`)
    renders.json                   [{run, scene, object, method, ablation, view, image, background, mask, depth}]
    renders/<run>/view_XX_{obj,bg}.png  (sRGB 8 bit), view_XX_mask.png (0/255),
                  view_XX_{obj,bg}.npy (linear float32), view_XX_depth.npy (background depth, scene units)
    eval_config.toml               resolved settings, seed, cameras, integrator, skipped metrics, versions
    report.md, report.html, grids/ (evaluation.report)

Bad input (a missing run directory, a folder without config.toml, an unknown metric, ``--views 0``,
``--jitter 0``, weights that do not load, ...) raises CamoError before anything is written.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from camo_base.errors import CamoError, SettingError, literal

from camo_base.tables import write_parquet
from evaluation.evaldir import (COLUMNS, IMAGE_ENCODING, KEY_COLUMNS, METHOD_SECONDS_COLUMNS,  # noqa: F401 (re-exported)
                                METRIC_COLUMNS, METRIC_SECONDS_COLUMNS, REGIONS, SECONDS_COLUMNS, SHA_COLUMNS,
                                SPLIT_COLUMNS, VARIANT_COLUMNS, hardware, hardware_text, read_eval_config,
                                renders_json, write_renders)
from evaluation.inputs import Entry, InputSpec, resolve
from evaluation.settings import EvalSettings, parse_metrics  # noqa: F401 (re-exported)
from evaluation.views import (EvalCameras, ViewRenderer, chosen_setting, evaluation_cameras, evaluation_plan,
                              render_seed)



# --------------------------------------------------------------------------------------------------------------
# metric selection and weights
# --------------------------------------------------------------------------------------------------------------


def weights_of(settings: EvalSettings) -> dict[str, str]:
    """The weights entries of ``settings.weights`` (``{metric: path}``): each metric's ``Metric.from_path`` turns
    its path into entries (:mod:`evaluation.metrics.registry`); CamoError (one line) for an unknown metric, a
    metric that takes no weights, or a path that does not hold them."""
    from evaluation.metrics import METRICS

    weights: dict[str, str] = {}
    for name, path in (settings.weights or {}).items():
        if name not in METRICS:
            raise SettingError.of("weights", f" {name}=...: unknown metric; known: {', '.join(METRICS)}")
        if METRICS[name].from_path is None:
            takes = ", ".join(n for n, m in METRICS.items() if m.from_path is not None)
            raise SettingError.of("weights", f" {name}=...: {name} takes no weights (metrics that do: {takes})")
        weights.update(METRICS[name].from_path(str(path)))
    return weights


def given_learned(weights: dict[str, str]) -> list[str]:
    """The learned metrics whose weights the user gave explicitly (their ``Metric.weights_key`` is set by a
    --*-weights option, :func:`weights_of`); they must load."""
    from evaluation.metrics import METRICS

    return [n for n, m in METRICS.items() if m.needs_weights and m.weights_key and m.weights_key in weights]


def select_metrics(requested: Sequence[str] | None, weights: dict[str, str]) -> tuple[list[str], dict[str, str]]:
    """The metrics to compute and ``{skipped metric: why}``.

    Without ``requested``: the weight-free defaults plus each learned metric whose weights are given or found
    locally. A learned metric that is asked for by name, or whose weights were given, but cannot run is an
    error, not a skip.
    """
    from evaluation.metrics import LEARNED, METRICS, WEIGHT_FREE, metric_unavailable

    skipped: dict[str, str] = {}
    for name in given_learned(weights):
        why = metric_unavailable(name, weights)
        if why is not None:
            raise CamoError(f"{name} weights given but unusable: {why}")
    if requested is None:
        names = list(WEIGHT_FREE)
        for name in LEARNED:
            why = metric_unavailable(name, weights)
            if why is None:
                names.append(name)
            else:
                skipped[name] = why
    else:
        names = list(requested)
        for name in names:
            if name not in METRICS:
                raise CamoError(f"unknown metric {name!r}; known: {', '.join(METRICS)}")
            why = metric_unavailable(name, weights)
            if why is not None:
                raise SettingError.of("metrics", f" {name}: {why}")
        for name in METRICS:
            if name not in names:
                skipped[name] = "not requested (metrics)"
    return names, skipped


def check_metrics_load(names: Sequence[str], weights: dict[str, str]) -> None:
    """Load every learned metric once on a dummy pair, so weights that do not load fail before any output."""
    from evaluation.metrics import METRICS, compute_metrics

    learned = [n for n in METRICS if METRICS[n].needs_weights and (n in names or n in given_learned(weights))]
    if learned:
        rng = np.random.default_rng(0)
        a = rng.random((64, 64, 3)).astype(np.float32)
        compute_metrics(a, a[::-1].copy(), learned, weights)


# --------------------------------------------------------------------------------------------------------------
# one run
# --------------------------------------------------------------------------------------------------------------


def srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear radiance -> the 8-bit sRGB values of the saved PNG (what the metrics compare)."""
    from camo_base.imaging import linear_to_srgb, to_uint8

    return to_uint8(linear_to_srgb(linear))


def _empty_metric_fields() -> dict[str, Any]:
    out: dict[str, Any] = {m: math.nan for m in (*METRIC_COLUMNS, *METRIC_SECONDS_COLUMNS, *SPLIT_COLUMNS)}
    out.update({c: "" for c in (*VARIANT_COLUMNS, *SHA_COLUMNS)})
    return out


def _giveaway(a: np.ndarray, b: np.ndarray, m: np.ndarray, shadow: np.ndarray, names: Sequence[str],
              weights: dict[str, str]) -> dict[str, Any]:
    """The region's object / shadow / rest split (:mod:`evaluation.giveaway`), its LPIPS part with the network of
    the ``lpips`` metric when that metric is computed."""
    from evaluation.giveaway import split_region

    lpips_fn = None
    if "lpips" in names:
        from evaluation.metrics import load_lpips, lpips
        from evaluation.metrics.lpips import lpips_files

        model = load_lpips(*lpips_files("lpips", weights))
        lpips_fn = lambda x, y: lpips(x, y, model).tolist()  # noqa: E731
    return split_region(a, b, m, shadow, lpips_fn)


def score_view(obj8: np.ndarray, bg8: np.ndarray, mask: np.ndarray, names: Sequence[str],
               weights: dict[str, str]) -> list[dict[str, Any]]:
    """The ``full`` and ``crop`` score rows (region box, mask pixels, metrics, the object / shadow / rest split,
    seconds) of one view."""
    from evaluation.giveaway import shadow_mask
    from evaluation.metrics import apply_crop, compute_metrics, object_crop_box

    h, w = mask.shape
    shadow, tau = shadow_mask(obj8, bg8, mask)  # on the full frame: the noise estimate sees the most pixels
    rows = []
    for region in REGIONS:
        row: dict[str, Any] = {"region": region, **_empty_metric_fields()}
        if region == "full":
            box = (0, 0, h, w)
            a, b, m, sh = obj8, bg8, mask, shadow
        elif mask.any():
            y0, x0, side = object_crop_box(mask)
            box = (y0, x0, side, side)
            a, b, m, sh = (apply_crop(x, (y0, x0, side)) for x in (obj8, bg8, mask, shadow))
        else:  # the object is not visible in this view: no crop, no crop scores
            box, a = (0, 0, 0, 0), None
            m = mask[:0, :0]
        row.update(region_y0=box[0], region_x0=box[1], region_height=box[2], region_width=box[3],
                   mask_pixels=int(m.sum()))
        t = time.perf_counter()
        if a is not None:
            for name in names:  # one call per metric so that each one's seconds are known
                t_m = time.perf_counter()
                row.update(compute_metrics(a, b, [name], weights, mask=m))
                row[f"seconds_{name}"] = time.perf_counter() - t_m
            row.update(_giveaway(a, b, m, sh, names, weights), shadow_threshold=tau)
        row["seconds_metrics"] = time.perf_counter() - t
        rows.append(row)
    return rows


def view_stem(v: int) -> str:
    return f"view_{v:02d}"


def write_view_files(out: Path, run: str, v: int, obj: np.ndarray, bg: np.ndarray, mask: np.ndarray,
                     depth: np.ndarray | None, obj8: np.ndarray | None = None,
                     bg8: np.ndarray | None = None) -> dict[str, str]:
    """``renders/<run>/view_XX_*``; returns the renders.json paths (relative to ``out``). ``obj8`` / ``bg8``: the
    8-bit sRGB images when they are given (triplets) rather than encoded from the linear ``obj`` / ``bg``; no
    ``depth`` file (and key) when ``depth`` is None."""
    from camo_base import atomic
    from camo_base.imaging import save_png

    rel = Path("renders") / run
    stem = view_stem(v)
    save_png(out / rel / f"{stem}_obj.png", srgb8(obj) if obj8 is None else obj8)
    save_png(out / rel / f"{stem}_bg.png", srgb8(bg) if bg8 is None else bg8)
    save_png(out / rel / f"{stem}_mask.png", mask.astype(bool))
    arrays = [("obj", obj), ("bg", bg)] + ([("depth", depth)] if depth is not None else [])
    for suffix, arr in arrays:
        with atomic.atomic_path(out / rel / f"{stem}_{suffix}.npy") as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, np.asarray(arr, dtype=np.float32))
    paths = {"image": (rel / f"{stem}_obj.png").as_posix(), "background": (rel / f"{stem}_bg.png").as_posix(),
             "mask": (rel / f"{stem}_mask.png").as_posix()}
    if depth is not None:
        paths["depth"] = (rel / f"{stem}_depth.npy").as_posix()
    return paths


# --------------------------------------------------------------------------------------------------------------
# the whole evaluation
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Job:
    entry: Entry
    env: Any = None
    cams: EvalCameras | None = None
    plan: Any = None


def as_specs(inputs: Sequence[str | Path | InputSpec]) -> list[InputSpec]:
    """Plain paths are run directories; :class:`evaluation.inputs.InputSpec` objects are taken as they are."""
    return [i if isinstance(i, InputSpec) else InputSpec("run", str(i)) for i in inputs]


def _prepare(inputs: Sequence[str | Path | InputSpec], settings: EvalSettings) -> list[_Job]:
    """Resolve the inputs and their cameras (no rendering: bad input fails before anything is written)."""
    from optimizer.scenes.environments import get_environment

    jobs = []
    for e in resolve(as_specs(inputs)):
        if e.kind == "triplets":
            jobs.append(_Job(e))
            continue
        res = (settings.resolution, settings.resolution) if settings.resolution else tuple(e.pack.render.resolution)
        cams = evaluation_cameras(e.pack, settings.views, settings.jitter, settings.seed, res)
        env = get_environment(e.pack.environment)
        jobs.append(_Job(e, env, cams))
    return jobs


def _plan_jobs(jobs: list[_Job], settings: EvalSettings, say: Callable[[str], None]) -> None:
    """The evaluation plan of every scene (one pilot per scene and camera set, shared by its inputs:
    :func:`evaluation.views.evaluation_plan`)."""
    plans: dict[tuple, Any] = {}
    for j in jobs:
        if j.cams is None:
            continue
        key = (json.dumps(dataclasses.asdict(j.entry.pack.environment), sort_keys=True, default=str), j.cams.key())
        if key not in plans:
            plans[key] = evaluation_plan(j.entry.pack, j.env, j.cams.cams, settings.spp, settings.seed,
                                         settings.planner, denoise=settings.denoise,
                                         noise_match=settings.noise_match, setting=settings.setting,
                                         sampler=settings.sampler)
            p = plans[key]
            if p.measured:
                say(f"plan for {j.entry.scene}: max_depth {p.max_depth}, Russian roulette from {p.rr_depth}, "
                    f"denoiser {p.denoise or 'off'}" + (f" (object x{p.object_spp} spp)" if p.denoise else "")
                    + f", pilot {p.pilot['seconds']:.1f} s")
                if settings.setting:
                    say(f"evaluation setting for {j.entry.scene}: {p.pilot['setting']['why']}")
        j.plan = plans[key]


def _check_sizes(jobs: list[_Job], names: Sequence[str]) -> None:
    from evaluation.metrics import MIN_SIZE

    need = max(MIN_SIZE.get(n, 1) for n in names)
    worst = max(names, key=lambda n: MIN_SIZE.get(n, 1))
    for j in jobs:
        if j.cams is not None:
            w, h = j.cams.cams[0].width, j.cams.cams[0].height
            fix, names = "raise {0} or drop it from {1}", ("resolution", "metrics")
        else:
            h, w = j.entry.triplets.mask.shape[1:]
            fix, names = "drop it from {0}", ("metrics",)
        if min(w, h) < need:
            raise SettingError(f"{literal(j.entry.name)}: {w}x{h} px is too small for metric {worst} (needs >= {need} "
                               f"px); {fix}", *names)


def evaluate(inputs: Sequence[str | Path | InputSpec], out: str | Path, settings: EvalSettings | None = None,
             log: Callable[[str], None] | None = None):
    """Evaluate run directories, assets and image triplets (:mod:`evaluation.inputs`) into ``out``; returns the
    metrics table (pandas DataFrame). Plain paths in ``inputs`` are run directories."""
    import pandas as pd

    from camo_base import atomic
    from optimizer import backend

    settings = settings or EvalSettings()
    say = log or ((lambda s: print(s, file=sys.stderr)) if settings.progress else (lambda s: None))
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SettingError.of("out", f" {out} exists and is not a folder")
    settings.validate()
    weights = weights_of(settings)
    names, skipped = select_metrics(settings.metrics, weights)
    jobs = _prepare(inputs, settings)
    _check_sizes(jobs, names)
    backend.init(threads=settings.threads)
    check_metrics_load(names, weights)  # last input check: nothing has been written so far

    _plan_jobs(jobs, settings, say)
    renderers: dict[tuple[int, int | None], ViewRenderer] = {}  # per (spp, background features' spp): one
    # without --setting auto; its choices per scene may add others
    rows: list[dict[str, Any]] = []
    entries: list[dict[str, Any]] = []
    scenes: dict[str, dict[str, Any]] = {}
    per_run: list[dict[str, Any]] = []
    bg_users: dict[str, int] = {}
    t_all = time.perf_counter()
    for j in jobs:
        e = j.entry
        secs = e.seconds
        method_cols = {"seconds_setup": secs["setup"], "seconds_stage1": secs["stage1"],
                       "seconds_stage2": secs["stage2"], "seconds_method": secs["total"]}
        ident = {"run": e.name, "scene": e.scene, "object": e.object, "method": e.method, "ablation": e.ablation}
        warnings = list(e.warnings) + (list(e.asset.warnings) if e.asset is not None else [])
        if e.kind == "triplets":
            t = e.triplets
            n, h, w = t.mask.shape
            say(f"scoring {e.name} (triplets, {e.scene}, {e.method}): {n} views, {w}x{h} px")
            cam_key = t.key()
            base = {**ident, "seed": settings.seed, "spp": 0, "width": w, "height": h, "jitter": 0.0,
                    "camera_set": cam_key, "source": "triplets", **method_cols}
            for v in range(n):
                from camo_base.imaging import srgb_to_linear

                lin_o = t.obj_linear[v] if t.obj_linear is not None else srgb_to_linear(t.obj8[v] / 255.0)
                lin_b = t.bg_linear[v] if t.bg_linear is not None else srgb_to_linear(t.bg8[v] / 255.0)
                depth = t.depth[v] if t.depth is not None else None
                paths = write_view_files(out, e.name, v, lin_o, lin_b, t.mask[v], depth, obj8=t.obj8[v], bg8=t.bg8[v])
                entries.append({**ident, "view": v, **paths})
                for row in score_view(t.obj8[v], t.bg8[v], t.mask[v], names, weights):
                    rows.append({**base, "view": v, **row, "_bg": None, "_obj_seconds": math.nan, "_bg_seconds": 0.0})
            per_run.append({"name": e.name, "kind": e.kind, "path": str(e.path.resolve()), "scene": e.scene,
                            "object": e.object, "method": e.method, "ablation": e.ablation, "camera_set": cam_key,
                            "views": list(t.views), "seconds": _plain_seconds(secs), "warnings": warnings})
            for wmsg in warnings:
                say(f"warning: {wmsg}")
            continue
        ec = j.cams
        st = chosen_setting(j.plan)
        spp = st.spp if st else settings.spp
        key_r = (spp, st.background_feature_spp if st else None)
        if key_r not in renderers:
            renderers[key_r] = ViewRenderer(spp, settings.seed, noise_match=settings.noise_match,
                                            feature_spp=key_r[1])
        rr = renderers[key_r]
        say(f"evaluating {e.name} ({e.kind}, {e.scene}, {e.method}, ablation {e.ablation}): {len(ec.cams)} views, "
            f"{ec.cams[0].width}x{ec.cams[0].height} px, {spp} spp" + (f" ({st.label})" if st else ""))
        bg = rr.background(e.pack, j.env, ec.cams, j.plan.integrator, j.plan.denoise)
        bg_users[bg.key] = bg_users.get(bg.key, 0) + 1
        objr = rr.with_object(j.env, e.asset.mesh, ec.cams, j.plan.integrator, bg,
                              j.plan.region_threshold if j.plan.region_search else None,
                              object_spp=j.plan.object_spp, object_combine=st.combine if st else "product",
                              object_feature_spp=st.feature_spp if st else None)
        cam_key = ec.key()
        scenes.setdefault(bg.key, {
            "scene": e.scene, "camera_set": cam_key, "background_key": bg.key, "integrator": dict(j.plan.integrator),
            "plan_reasons": [f"{k}: {v}" for k, v in j.plan.reasons], "jitter_bound": ec.bound,
            "plan_effects": [e_.to_dict() for e_ in j.plan.effects], "pilot": j.plan.pilot,
            "width": ec.cams[0].width, "height": ec.cams[0].height,
            "training_cameras": [list(c.origin) for c in ec.training],
            "cameras": [list(c.origin) for c in ec.cams], "targets": [list(c.target) for c in ec.cams],
            "base_views": ec.base, "background_seconds": bg.seconds,
            "denoise": bg.denoise or "off", "background_denoise_seconds": bg.denoise_seconds,
        })
        base = {**ident, "seed": settings.seed, "spp": spp, "width": ec.cams[0].width,
                "height": ec.cams[0].height, "jitter": float(settings.jitter), "camera_set": cam_key,
                "source": e.kind, **method_cols}
        for v in range(len(ec.cams)):
            paths = write_view_files(out, e.name, v, objr.image[v], bg.image[v], objr.mask[v], bg.depth[v])
            entries.append({**ident, "view": v, **paths})
            o8, b8 = srgb8(objr.image[v]), srgb8(bg.image[v])
            for row in score_view(o8, b8, objr.mask[v], names, weights):
                rows.append({**base, "view": v, **row, "_bg": bg.key, "_obj_seconds": objr.seconds / len(ec.cams),
                             "_bg_seconds": bg.seconds / len(ec.cams)})
        per_run.append({"name": e.name, "kind": e.kind, "path": str(e.path.resolve()), "scene": e.scene,
                        "object": e.object, "method": e.method, "ablation": e.ablation, "camera_set": cam_key,
                        "background_key": bg.key, "object_render_seconds": objr.seconds,
                        "region_seconds": objr.region_seconds,
                        "region_share": None if objr.region is None else float(objr.region.mean()),
                        "noise_match": None if objr.noise is None else objr.noise.to_dict(),
                        "denoise": objr.denoise or "off", "denoise_seconds": objr.denoise_seconds,
                        "object_spp": int(j.plan.object_spp),
                        "evaluation_setting": st.to_dict() if st else None,
                        "seconds": _plain_seconds(secs), "warnings": warnings, **e.placement})
        for wmsg in warnings:
            say(f"warning: {wmsg}")
    for row in rows:  # the background render is shared equally by the runs that use it
        key = row.pop("_bg")
        share = row.pop("_bg_seconds") / bg_users[key] if key is not None else 0.0
        row["seconds_render"] = row.pop("_obj_seconds") + share
    table = pd.DataFrame(rows, columns=list(COLUMNS))
    table = table.astype({c: "float64" for c in (*METRIC_COLUMNS, *SPLIT_COLUMNS, "jitter", *SECONDS_COLUMNS)})
    table = table.astype({c: "int64" for c in ("view", "seed", "spp", "width", "height", "region_y0", "region_x0",
                                                "region_height", "region_width", "mask_pixels")})

    with atomic.atomic_path(out / "metrics.parquet") as tmp:
        write_parquet(table, tmp)
    with atomic.atomic_path(out / "metrics.csv") as tmp:
        table.to_csv(tmp, index=False)
    write_renders(out, entries)
    n_bg = sum(r.background_renders for r in renderers.values())
    write_eval_config(out / "eval_config.toml", settings, names, skipped, weights, per_run, list(scenes.values()),
                      n_bg, time.perf_counter() - t_all)
    if settings.write_report:
        from evaluation.report import write_report

        write_report([out], out)
    say(f"{len(jobs)} input(s), {n_bg} background render(s), {len(table)} rows")
    return table


def _plain_seconds(secs: dict[str, float]) -> dict[str, float]:
    return {k: float(v) for k, v in secs.items() if math.isfinite(v)}


def write_eval_config(path: Path, settings: EvalSettings, names: Sequence[str], skipped: dict[str, str],
                      weights: dict[str, str], runs: list[dict[str, Any]], scenes: list[dict[str, Any]],
                      background_renders: int, seconds: float) -> None:
    import tomli_w

    from evaluation.metrics import METRICS, weights_sha256
    from camo_base import atomic
    from camo_base.provenance import versions

    doc: dict[str, Any] = {
        "evaluate": {
            "views": settings.views if settings.views is not None else "same as training",
            "jitter": float(settings.jitter),
            "jitter_meaning": "uniform offset per axis, up to +-jitter units at radius 4, scaled with the radius",
            "spp": settings.spp,
            "resolution": settings.resolution if settings.resolution else "run's",
            "seed": settings.seed,
            "render_seed": render_seed(settings.seed),
            "render_seed_meaning": "sampler seed of the background and the with-object renders (common random "
                                   "numbers), the same for every run",
            "metrics": list(names),
            "denoise": settings.denoise or "off",
            "denoise_meaning": "--denoise: the denoiser the plan applies where its pilot's noise at spp is above the "
                               "denoiser's bias (each scene's and run's denoise: where it did), or off",
            "sampler": settings.sampler,
            "sampler_meaning": "--sampler: how each pixel's samples are drawn in the background and with-object "
                               "renders (independent, or sobol: stratified; each scene's integrator carries it)",
            "setting": settings.setting or "as the options say",
            "setting_meaning": "--setting auto: each scene's render setting chosen by a pilot (each run's "
                               "evaluation_setting, each scene's pilot.setting; spp per row)",
            "regions": list(REGIONS),
            "image_encoding": IMAGE_ENCODING,
            "mask": "object coverage >= 0.5 (ray-cast, 4x4 rays per pixel, occlusion aware)",
            "crop": "GANmouflage: square of side 32*ceil(d/32)+32 around the mask's bounding box (d its larger "
                    "side), clamped to the image; no crop rows' scores when the object is not visible",
            "seconds": seconds,
            "background_renders": int(background_renders),
        },
        "hardware": hardware(),
        "skipped": dict(skipped),
        "metric_info": {n: {"higher_is_better": METRICS[n].higher_is_better, "units": METRICS[n].units,
                            "description": METRICS[n].description} for n in names},
        "weights": {k: {"path": str(Path(v).resolve()), "sha256": weights_sha256(v)} for k, v in weights.items()},
        "runs": runs,
        "scenes": scenes,
        "versions": versions(),
    }
    atomic.write_text(path, tomli_w.dumps(_toml_plain(doc)))


def _toml_plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _toml_plain(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_toml_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
