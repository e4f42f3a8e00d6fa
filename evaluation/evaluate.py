"""``camo evaluate``: the automatic benchmark of run directories (paper Sec. IV-D, Table II).

For each run directory: rebuild its scene, render jittered novel views (:mod:`evaluation.views`) with and
without the object at evaluation quality, and score every view in two regions -- the ``full`` frame and the
GANmouflage object ``crop`` (:func:`evaluation.metrics.object_crop_box` of the visible-object mask) -- with the
image metrics of :mod:`evaluation.metrics`, comparing the with-object image to the background image.

Images enter the metrics exactly as the saved PNGs hold them: linear radiance -> sRGB
(``optimizer.imaging.linear_to_srgb``, tone-clipped) -> 8 bit. So every score can be recomputed from the PNGs
(or from the linear ``.npy`` renders through the same two steps).

Output (EVAL_DIR, every file written atomically; see CONTRIBUTING.md)::

    metrics.parquet, metrics.csv   one row per run x view x region, columns :data:`COLUMNS`
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

from optimizer.errors import CamoError

from .views import DEFAULT_JITTER, EvalCameras, RunInfo, ViewRenderer, evaluation_cameras, evaluation_plan, \
    load_result, load_run, object_mesh_of, render_seed

#: The metric columns, one per metric of :data:`evaluation.metrics.METRICS` (NaN where not computed).
METRIC_COLUMNS = ("psnr", "ssim", "lpips", "lpips_proxy", "sifid", "sifid_proxy", "dreamsim")
#: Variant strings of the metrics that have one ("" where not computed).
VARIANT_COLUMNS = ("lpips_variant", "lpips_proxy_variant", "sifid_variant", "sifid_proxy_variant", "dreamsim_variant")
#: SHA-256 of the weight files behind each learned metric ("" where not computed).
SHA_COLUMNS = ("lpips_weights_sha256", "sifid_weights_sha256", "dreamsim_weights_sha256")
#: Columns that identify a row (run, view, region and the evaluation protocol).
KEY_COLUMNS = ("run", "scene", "object", "method", "ablation", "view", "seed", "region", "spp", "width", "height",
               "jitter", "camera_set")
#: Every column of metrics.parquet / metrics.csv, in order.
COLUMNS = (*KEY_COLUMNS, "region_y0", "region_x0", "region_height", "region_width", "mask_pixels",
           *METRIC_COLUMNS, *VARIANT_COLUMNS, *SHA_COLUMNS, "seconds_render", "seconds_metrics")
REGIONS = ("full", "crop")
#: Metrics computed when --metrics is not given (plus the learned ones whose weights are given or found).
DEFAULT_METRICS = ("psnr", "ssim", "lpips_proxy", "sifid_proxy")
LEARNED = ("lpips", "sifid", "dreamsim")
IMAGE_ENCODING = "srgb8"  # linear -> sRGB (IEC 61966-2-1, clipped to [0, 1]) -> 8 bit, as in the PNGs


@dataclasses.dataclass
class EvalSettings:
    views: int | None = None  # default: the number of training views
    jitter: float = DEFAULT_JITTER
    spp: int = 64
    resolution: int | None = None  # default: the run's
    metrics: Sequence[str] | None = None  # default: DEFAULT_METRICS + available learned metrics
    seed: int = 0
    lpips_weights: str | None = None
    inception_weights: str | None = None
    dreamsim_weights: str | None = None
    threads: int | None = None
    progress: bool = True
    write_report: bool = True

    def validate(self) -> None:
        if self.views is not None and self.views < 1:
            raise CamoError(f"--views must be >= 1, got {self.views}")
        if not math.isfinite(self.jitter) or self.jitter <= 0:
            raise CamoError(f"--jitter must be > 0 (evaluation never uses the training cameras), got {self.jitter}")
        if self.spp < 1:
            raise CamoError(f"--spp must be >= 1, got {self.spp}")
        if self.resolution is not None and self.resolution < 8:
            raise CamoError(f"--resolution must be >= 8, got {self.resolution}")
        if self.threads is not None and self.threads < 1:
            raise CamoError(f"--threads must be >= 1, got {self.threads}")


# --------------------------------------------------------------------------------------------------------------
# metric selection and weights
# --------------------------------------------------------------------------------------------------------------


def _lpips_paths(path: str) -> dict[str, str]:
    """``--lpips-weights``: a trunk file (AlexNet, torchvision format; the v0.1 linear layers then come from an
    installed lpips/torchmetrics wheel), or a folder holding the trunk file and ``alex.pth``."""
    from evaluation.metrics.weights import TRUNK_FILE_PATTERNS

    p = Path(path).expanduser()
    if p.is_dir():
        trunk = next((h for pat in TRUNK_FILE_PATTERNS["alex"] for h in sorted(p.glob(pat))), None)
        if trunk is None:
            raise CamoError(f"--lpips-weights {p}: no AlexNet trunk file ({', '.join(TRUNK_FILE_PATTERNS['alex'])}) in it")
        out = {"lpips_trunk": str(trunk)}
        if (p / "alex.pth").is_file():
            out["lpips_lin"] = str(p / "alex.pth")
        return out
    if not p.is_file():
        raise CamoError(f"--lpips-weights: file not found: {p}")
    return {"lpips_trunk": str(p)}


def weights_of(settings: EvalSettings) -> dict[str, str]:
    weights: dict[str, str] = {}
    if settings.lpips_weights:
        weights.update(_lpips_paths(settings.lpips_weights))
    if settings.inception_weights:
        p = Path(settings.inception_weights).expanduser()
        if not p.is_file():
            raise CamoError(f"--inception-weights: file not found: {p}")
        weights["sifid"] = str(p)
    if settings.dreamsim_weights:
        p = Path(settings.dreamsim_weights).expanduser()
        if not p.is_dir():
            raise CamoError(f"--dreamsim-weights: folder not found: {p}")
        weights["dreamsim"] = str(p)
    return weights


def parse_metrics(text: str | None) -> list[str] | None:
    """``--metrics psnr,ssim`` -> names (None when not given); CamoError for unknown names."""
    from evaluation.metrics import METRICS

    if text is None:
        return None
    names = [t.strip() for t in text.split(",") if t.strip()]
    if not names:
        raise CamoError("--metrics is empty; give a comma list, e.g. psnr,ssim,lpips_proxy")
    bad = [n for n in names if n not in METRICS]
    if bad:
        raise CamoError(f"unknown metric(s) {', '.join(bad)}; known: {', '.join(METRICS)}")
    return list(dict.fromkeys(names))


#: The weights keys (see :func:`weights_of`) that a --*-weights option sets, per learned metric.
GIVEN_KEYS = {"lpips": "lpips_trunk", "sifid": "sifid", "dreamsim": "dreamsim"}


def given_learned(weights: dict[str, str]) -> list[str]:
    """The learned metrics whose weights the user gave explicitly (they must load)."""
    return [n for n in LEARNED if GIVEN_KEYS[n] in weights]


def select_metrics(requested: Sequence[str] | None, weights: dict[str, str]) -> tuple[list[str], dict[str, str]]:
    """The metrics to compute and ``{skipped metric: why}``.

    Without ``requested``: the weight-free defaults plus each learned metric whose weights are given or found
    locally. A learned metric that is asked for by name, or whose weights were given, but cannot run is an
    error, not a skip.
    """
    from evaluation.metrics import METRICS, metric_unavailable

    skipped: dict[str, str] = {}
    for name in given_learned(weights):
        why = metric_unavailable(name, weights)
        if why is not None:
            raise CamoError(f"{name} weights given but unusable: {why}")
    if requested is None:
        names = list(DEFAULT_METRICS)
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
                raise CamoError(f"--metrics {name}: {why}")
        for name in METRICS:
            if name not in names:
                skipped[name] = "not requested (--metrics)"
    return names, skipped


def check_metrics_load(names: Sequence[str], weights: dict[str, str]) -> None:
    """Load every learned metric once on a dummy pair, so weights that do not load fail before any output."""
    from evaluation.metrics import compute_metrics

    learned = [n for n in LEARNED if n in names or n in given_learned(weights)]
    if learned:
        rng = np.random.default_rng(0)
        a = rng.random((64, 64, 3)).astype(np.float32)
        compute_metrics(a, a[::-1].copy(), learned, weights)


# --------------------------------------------------------------------------------------------------------------
# one run
# --------------------------------------------------------------------------------------------------------------


def srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear radiance -> the 8-bit sRGB values of the saved PNG (what the metrics compare)."""
    from optimizer.imaging import linear_to_srgb, to_uint8

    return to_uint8(linear_to_srgb(linear))


def _empty_metric_fields() -> dict[str, Any]:
    out: dict[str, Any] = {m: math.nan for m in METRIC_COLUMNS}
    out.update({c: "" for c in (*VARIANT_COLUMNS, *SHA_COLUMNS)})
    return out


def score_view(obj8: np.ndarray, bg8: np.ndarray, mask: np.ndarray, names: Sequence[str],
               weights: dict[str, str]) -> list[dict[str, Any]]:
    """The ``full`` and ``crop`` score rows (region box, mask pixels, metrics, seconds) of one view."""
    from evaluation.metrics import apply_crop, compute_metrics, object_crop_box

    h, w = mask.shape
    rows = []
    for region in REGIONS:
        row: dict[str, Any] = {"region": region, **_empty_metric_fields()}
        if region == "full":
            box = (0, 0, h, w)
            a, b, m = obj8, bg8, mask
        elif mask.any():
            y0, x0, side = object_crop_box(mask)
            box = (y0, x0, side, side)
            a, b, m = (apply_crop(x, (y0, x0, side)) for x in (obj8, bg8, mask))
        else:  # the object is not visible in this view: no crop, no crop scores
            box, a = (0, 0, 0, 0), None
            m = mask[:0, :0]
        row.update(region_y0=box[0], region_x0=box[1], region_height=box[2], region_width=box[3],
                   mask_pixels=int(m.sum()))
        t = time.perf_counter()
        if a is not None:
            for key, val in compute_metrics(a, b, names, weights).items():
                row[key] = val
        row["seconds_metrics"] = time.perf_counter() - t
        rows.append(row)
    return rows


def view_stem(v: int) -> str:
    return f"view_{v:02d}"


def write_view_files(out: Path, run: str, v: int, obj: np.ndarray, bg: np.ndarray, mask: np.ndarray,
                     depth: np.ndarray) -> dict[str, str]:
    """``renders/<run>/view_XX_*``; returns the renders.json paths (relative to ``out``)."""
    from optimizer import atomic
    from optimizer.imaging import save_png

    rel = Path("renders") / run
    stem = view_stem(v)
    save_png(out / rel / f"{stem}_obj.png", srgb8(obj))
    save_png(out / rel / f"{stem}_bg.png", srgb8(bg))
    save_png(out / rel / f"{stem}_mask.png", mask.astype(bool))
    for suffix, arr in (("obj", obj), ("bg", bg), ("depth", depth)):
        with atomic.atomic_path(out / rel / f"{stem}_{suffix}.npy") as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, np.asarray(arr, dtype=np.float32))
    return {"image": (rel / f"{stem}_obj.png").as_posix(), "background": (rel / f"{stem}_bg.png").as_posix(),
            "mask": (rel / f"{stem}_mask.png").as_posix(), "depth": (rel / f"{stem}_depth.npy").as_posix()}


# --------------------------------------------------------------------------------------------------------------
# the whole evaluation
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Job:
    run: RunInfo
    assets: Any
    env: Any
    cams: EvalCameras
    plan: Any


def _prepare(run_dirs: Sequence[str | Path], settings: EvalSettings) -> list[_Job]:
    from optimizer.environments import get_environment

    if not run_dirs:
        raise CamoError("evaluate needs at least one RUN_DIR")
    runs = [load_run(d) for d in run_dirs]
    seen: dict[str, Path] = {}
    for r in runs:
        if r.name in seen and seen[r.name].resolve() != r.path.resolve():
            raise CamoError(f"two run directories are both named {r.name!r} ({seen[r.name]}, {r.path}); "
                            "renders/<run>/ needs distinct names")
        seen[r.name] = r.path
    unique = list({r.path.resolve(): r for r in runs}.values())
    jobs = []
    for r in unique:
        res = (settings.resolution, settings.resolution) if settings.resolution else tuple(r.pack.render.resolution)
        cams = evaluation_cameras(r.pack, settings.views, settings.jitter, settings.seed, res)
        env = get_environment(r.pack.environment)
        jobs.append(_Job(r, load_result(r), env, cams, evaluation_plan(r.pack, env)))
    return jobs


def _check_sizes(jobs: list[_Job], names: Sequence[str]) -> None:
    from evaluation.metrics import MIN_SIZE

    for j in jobs:
        c = j.cams.cams[0]
        need = max(MIN_SIZE.get(n, 1) for n in names)
        if min(c.width, c.height) < need:
            worst = max(names, key=lambda n: MIN_SIZE.get(n, 1))
            raise CamoError(f"{j.run.name}: {c.width}x{c.height} px is too small for metric {worst} (needs >= "
                            f"{need} px); raise --resolution or drop it from --metrics")


def evaluate(run_dirs: Sequence[str | Path], out: str | Path, settings: EvalSettings | None = None,
             log: Callable[[str], None] | None = None):
    """Evaluate run directories into ``out``; returns the metrics table (pandas DataFrame)."""
    import pandas as pd

    from optimizer import atomic, backend

    settings = settings or EvalSettings()
    say = log or ((lambda s: print(s, file=sys.stderr)) if settings.progress else (lambda s: None))
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CamoError(f"--out {out} exists and is not a folder")
    settings.validate()
    weights = weights_of(settings)
    names, skipped = select_metrics(settings.metrics, weights)
    jobs = _prepare(run_dirs, settings)
    _check_sizes(jobs, names)
    backend.init(threads=settings.threads)
    check_metrics_load(names, weights)  # last input check: nothing has been written so far

    renderer = ViewRenderer(settings.spp, settings.seed)
    rows: list[dict[str, Any]] = []
    entries: list[dict[str, Any]] = []
    scenes: dict[str, dict[str, Any]] = {}
    per_run: list[dict[str, Any]] = []
    bg_users: dict[str, int] = {}
    t_all = time.perf_counter()
    for j in jobs:
        r, ec = j.run, j.cams
        say(f"evaluating {r.name} ({r.scene}, {r.method}, ablation {r.ablation_label}): {len(ec.cams)} views, "
            f"{ec.cams[0].width}x{ec.cams[0].height} px, {settings.spp} spp")
        bg = renderer.background(r.pack, j.env, ec.cams, j.plan.integrator)
        bg_users[bg.key] = bg_users.get(bg.key, 0) + 1
        objr = renderer.with_object(j.env, lambda: object_mesh_of(r, j.assets), ec.cams, j.plan.integrator)
        cam_key = ec.key()
        scenes.setdefault(bg.key, {
            "scene": r.scene, "camera_set": cam_key, "background_key": bg.key, "integrator": dict(j.plan.integrator),
            "plan_reasons": [f"{k}: {v}" for k, v in j.plan.reasons], "jitter_bound": ec.bound,
            "width": ec.cams[0].width, "height": ec.cams[0].height,
            "training_cameras": [list(c.origin) for c in ec.training],
            "cameras": [list(c.origin) for c in ec.cams], "targets": [list(c.target) for c in ec.cams],
            "base_views": ec.base, "background_seconds": bg.seconds,
        })
        base = {"run": r.name, "scene": r.scene, "object": r.object, "method": r.method, "ablation": r.ablation_label,
                "seed": settings.seed, "spp": settings.spp, "width": ec.cams[0].width, "height": ec.cams[0].height,
                "jitter": float(settings.jitter), "camera_set": cam_key}
        for v in range(len(ec.cams)):
            paths = write_view_files(out, r.name, v, objr.image[v], bg.image[v], objr.mask[v], bg.depth[v])
            entries.append({"run": r.name, "scene": r.scene, "object": r.object, "method": r.method,
                            "ablation": r.ablation_label, "view": v, **paths})
            o8, b8 = srgb8(objr.image[v]), srgb8(bg.image[v])
            for row in score_view(o8, b8, objr.mask[v], names, weights):
                rows.append({**base, "view": v, **row, "_bg": bg.key, "_obj_seconds": objr.seconds / len(ec.cams),
                             "_bg_seconds": bg.seconds / len(ec.cams)})
        per_run.append({"name": r.name, "path": str(r.path.resolve()), "scene": r.scene, "object": r.object,
                        "method": r.method, "ablation": r.ablation_label, "camera_set": cam_key,
                        "background_key": bg.key, "object_render_seconds": objr.seconds,
                        "warnings": list(j.assets.warnings)})
        for w in j.assets.warnings:
            say(f"warning: {w}")
    for row in rows:  # the background render is shared equally by the runs that use it
        row["seconds_render"] = row.pop("_obj_seconds") + row.pop("_bg_seconds") / bg_users[row.pop("_bg")]
    table = pd.DataFrame(rows, columns=list(COLUMNS))
    table = table.astype({c: "float64" for c in (*METRIC_COLUMNS, "jitter", "seconds_render", "seconds_metrics")})
    table = table.astype({c: "int64" for c in ("view", "seed", "spp", "width", "height", "region_y0", "region_x0",
                                                "region_height", "region_width", "mask_pixels")})

    with atomic.atomic_path(out / "metrics.parquet") as tmp:
        table.to_parquet(tmp, index=False)
    with atomic.atomic_path(out / "metrics.csv") as tmp:
        table.to_csv(tmp, index=False)
    atomic.write_json(out / "renders.json", entries)
    write_eval_config(out / "eval_config.toml", settings, names, skipped, weights, per_run, list(scenes.values()),
                      renderer, time.perf_counter() - t_all)
    if settings.write_report:
        from .report import write_report

        write_report([out], out)
    say(f"{len(jobs)} run(s), {renderer.background_renders} background render(s), {len(table)} rows")
    return table


def write_eval_config(path: Path, settings: EvalSettings, names: Sequence[str], skipped: dict[str, str],
                      weights: dict[str, str], runs: list[dict[str, Any]], scenes: list[dict[str, Any]],
                      renderer: ViewRenderer, seconds: float) -> None:
    import tomli_w

    from evaluation.metrics import METRICS, weights_sha256
    from optimizer import atomic
    from optimizer.run import versions

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
            "regions": list(REGIONS),
            "image_encoding": IMAGE_ENCODING,
            "mask": "object coverage >= 0.5 (ray-cast, 4x4 rays per pixel, occlusion aware)",
            "crop": "GANmouflage: square of side 32*ceil(d/32)+32 around the mask's bounding box (d its larger "
                    "side), clamped to the image; no crop rows' scores when the object is not visible",
            "seconds": seconds,
            "background_renders": renderer.background_renders,
        },
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


def read_eval_config(eval_dir: str | Path) -> dict[str, Any]:
    import tomllib

    p = Path(eval_dir) / "eval_config.toml"
    if not p.is_file():
        return {}
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError):
        return {}


def renders_json(eval_dir: str | Path) -> list[dict[str, Any]]:
    p = Path(eval_dir) / "renders.json"
    if not p.is_file():
        return []
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise CamoError(f"{p}: not valid JSON ({exc})") from None
    return data if isinstance(data, list) else []
