"""The evaluation directory (output of ``camo evaluate``): its one owner.

Column names of ``metrics.parquet`` / ``metrics.csv`` (:data:`COLUMNS`), ``renders.json`` (written by
:func:`write_renders`; read by :func:`read_renders`, strict, for stimuli, and :func:`renders_json`, lenient, for
reports), ``eval_config.toml`` (:func:`read_eval_config`) and the hardware line the seconds were measured on
(:func:`hardware`, :func:`hardware_text`). :mod:`evaluation.evaluate` writes the directory, :mod:`evaluation.report`
and :mod:`study_site.stimuli` read it; none of them parses these files itself. Layout: CONTRIBUTING.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from camo_base import atomic
from camo_base.documents import read_json
from camo_base.errors import CamoError

#: Columns that identify a row (input, view, region and the evaluation protocol). ``source``: ``run`` (a run
#: directory), ``asset`` (a glTF/OBJ file placed in a scene) or ``triplets`` (given images; ``spp`` and ``jitter``
#: are 0 and ``camera_set`` is ``images:<hash>``: nothing was rendered).
KEY_COLUMNS = ("run", "scene", "object", "method", "ablation", "view", "seed", "region", "spp", "width", "height",
               "jitter", "camera_set", "source")
#: Seconds of the method (repeated on each row of an input): ``seconds_setup`` / ``seconds_stage1`` /
#: ``seconds_stage2`` from a run directory (:meth:`optimizer.assets.rundir.RunDir.seconds`), ``seconds_method`` their sum
#: or the user's ``seconds`` for an asset or triplets (NaN when unknown).
METHOD_SECONDS_COLUMNS = ("seconds_setup", "seconds_stage1", "seconds_stage2", "seconds_method")
#: Where the object gives itself away (:mod:`evaluation.giveaway`): the region's pixels split into the object (mask
#: + 1-px ring), its cast shadow (darker with the object, outside it; noise-aware threshold ``shadow_threshold`` in
#: sRGB luma) and the rest; per part the pixel count, its part of the region's mean squared error (sRGB [0, 1]; the
#: three add up to the MSE) and of its LPIPS (Shapley split of the ``lpips`` metric; the three add up to ``lpips``,
#: NaN without LPIPS weights).
SPLIT_PARTS = ("object", "shadow", "rest")
SPLIT_COLUMNS = ("shadow_threshold", *(f"pixels_{p}" for p in SPLIT_PARTS), *(f"sqerr_{p}" for p in SPLIT_PARTS),
                 *(f"lpips_{p}" for p in SPLIT_PARTS))


def _metric_columns() -> dict[str, tuple[str, ...]]:
    """The columns made from the metric registry (:data:`evaluation.metrics.METRICS`, in its order):

    * ``METRIC_COLUMNS``: one per metric (NaN where not computed);
    * ``VARIANT_COLUMNS``: ``{name}_variant`` of the metrics that have one ("" where not computed);
    * ``SHA_COLUMNS``: ``{name}_weights_sha256``, the SHA-256 of the weight files behind each learned metric;
    * ``METRIC_SECONDS_COLUMNS``: seconds of each metric on the row's image pair;
    * ``COLUMNS``: every column of metrics.parquet / metrics.csv, in order (the split :data:`SPLIT_COLUMNS` after
      the metrics; ``seconds_render``: evaluation rendering of this view -- with-object render + its share of the
      scene's background render; NaN for triplets --, ``seconds_metrics``: all metrics of the row);
    * ``SECONDS_COLUMNS``: the ``seconds_*`` columns."""
    from evaluation.metrics import METRICS

    metric = tuple(METRICS)
    variant = tuple(f"{n}_variant" for n, m in METRICS.items() if m.variant)
    sha = tuple(f"{n}_weights_sha256" for n, m in METRICS.items() if m.needs_weights)
    metric_seconds = tuple(f"seconds_{n}" for n in metric)
    columns = (*KEY_COLUMNS, "region_y0", "region_x0", "region_height", "region_width", "mask_pixels", *metric,
               *variant, *sha, *SPLIT_COLUMNS, "seconds_render", "seconds_metrics", *metric_seconds,
               *METHOD_SECONDS_COLUMNS)
    return {"METRIC_COLUMNS": metric, "VARIANT_COLUMNS": variant, "SHA_COLUMNS": sha,
            "METRIC_SECONDS_COLUMNS": metric_seconds, "COLUMNS": columns,
            "SECONDS_COLUMNS": tuple(c for c in columns if c.startswith("seconds_"))}


def __getattr__(name: str):
    """The column lists of :func:`_metric_columns`, made on first use (the metric registry imports torch; reading
    renders.json does not need it)."""
    if name in ("METRIC_COLUMNS", "VARIANT_COLUMNS", "SHA_COLUMNS", "METRIC_SECONDS_COLUMNS", "COLUMNS",
                "SECONDS_COLUMNS"):
        cols = _metric_columns()
        globals().update(cols)
        return cols[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


REGIONS = ("full", "crop")
IMAGE_ENCODING = "srgb8"  # linear -> sRGB (IEC 61966-2-1, clipped to [0, 1]) -> 8 bit, as in the PNGs

#: Keys every ``renders.json`` entry must have (non-empty) to become a stimulus.
RENDER_KEYS = ("run", "scene", "method", "view", "image", "mask")


def hardware() -> dict[str, Any]:
    """Where the seconds were measured: CPU model, logical cores (and those this process may use), GPU, threads."""
    import os
    import platform

    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    out: dict[str, Any] = {"cpu": model, "cpu_cores": os.cpu_count() or 0}
    try:
        out["cpu_cores_usable"] = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        out["cpu_cores_usable"] = out["cpu_cores"]
    gpu = "none"
    try:
        import torch

        if torch.cuda.is_available():
            gpu = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
        from evaluation.metrics._common import metric_threads

        out["torch_threads"] = torch.get_num_threads()
        out["metric_threads"] = metric_threads()
    except Exception:  # torch missing or broken CUDA: the hardware line just says less
        pass
    out["gpu"] = gpu
    try:
        from optimizer import backend

        info = backend.info()
        if info:
            out["mitsuba_variant"], out["render_threads"] = info.variant, int(info.threads)
    except Exception:
        pass
    return out


def hardware_text(hw: dict[str, Any]) -> str:
    """One line, e.g. ``AMD EPYC, 2 CPU cores (2 usable), GPU none; llvm_ad_rgb, 2 render threads``."""
    if not hw:
        return "not recorded"
    text = f"{hw.get('cpu', '?')}, {hw.get('cpu_cores', '?')} CPU cores ({hw.get('cpu_cores_usable', '?')} usable), " \
           f"GPU {hw.get('gpu', '?')}"
    if hw.get("mitsuba_variant"):
        text += f"; {hw['mitsuba_variant']}, {hw.get('render_threads', '?')} render threads"
    if hw.get("metric_threads"):
        text += f"; metrics on {hw['metric_threads']} torch thread(s)"
    elif hw.get("torch_threads"):
        text += f", {hw['torch_threads']} torch threads"
    return text


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
    data = read_json(p, "render list")
    return data if isinstance(data, list) else []


def write_renders(out: str | Path, entries: list[dict[str, Any]]) -> Path:
    """Write ``out/renders.json`` atomically: ``[{run, scene, object, method, ablation, view, image, background,
    mask, depth}]`` with paths relative to ``out``."""
    p = Path(out) / "renders.json"
    atomic.write_json(p, entries)
    return p


def read_renders(eval_dir: str | Path) -> list[dict[str, Any]]:
    """``renders.json`` of an evaluation directory, checked: a list of objects each with :data:`RENDER_KEYS`
    (non-empty) and names of sane length. Missing or malformed: a one-line :class:`CamoError`."""
    eval_dir = Path(eval_dir)
    rj = eval_dir / "renders.json"
    if not eval_dir.is_dir():
        raise CamoError(f"{eval_dir}: not a directory")
    if not rj.is_file():
        raise CamoError(f"{eval_dir}: no renders.json (is this an evaluation directory from `camo evaluate`?)")
    entries = read_json(rj, "render list", list)
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise CamoError(f"{rj}: entry {i} is not an object")
        missing = [k for k in RENDER_KEYS if e.get(k) in (None, "")]
        if missing:
            raise CamoError(f"{rj}: entry {i} lacks {', '.join(missing)}")
        for k, limit in (("run", 256), ("scene", 256), ("object", 256), ("method", 120), ("ablation", 120), ("view", 64)):
            if len(str(e.get(k) or "")) > limit:
                raise CamoError(f"{rj}: entry {i}: {k} is longer than {limit} characters")
    return entries
