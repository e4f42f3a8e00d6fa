"""Hard cases converge, not only stay finite: every hard case through ``camo optimize``, scored on held-out views.

The stress tests (tests/test_stress_*.py) prove that hard cases stay *finite*; this benchmark measures whether they
*converge*. Each case is a tiny run of the default method (``ours``, the ``fast`` preset) made through
:func:`optimizer.optimise.run.run` exactly as ``camo optimize`` makes it, and for every case the table gives:

* ``nonfinite``: gradient entries dropped as NaN/Inf over the run (``log.jsonl``) plus non-finite result values;
* ``spike``: the largest Stage 1 photometric loss relative to the median of the iterations before it (from the
  second iteration on), on the loss the optimiser minimised; ``spike lin``: the same on the linear-radiance loss
  (``loss_linear``, logged when ``--loss-clamp`` is on; equal to ``spike`` otherwise);
* ``start``, ``result``, ``mean``: PSNR (dB, sRGB in [0, 1], object+shadow domain) of the case's start (the maps
  the run starts from before any warm start or search), of the run's result and of the ``mean`` baseline (Owens et
  al. 2014) on 4 jittered views of the training rig drawn from a seed of their own (``BENCH_SEED``: neither the
  run's held-out views, which pick its result, nor the evaluation's), each a bias + 64-spp-noise score
  (:class:`optimizer.optimise.holdout.Holdout`, two 16-spp pairs);
* ``ok``: the issue-32 targets: finite, spike <= 10, result >= start - ``TOLERANCE_DB``, result >= mean -
  ``TOLERANCE_DB`` (``TOLERANCE_DB`` = 0.1 dB: two scores of one image at these spp differ by up to ~0.05 dB).

Cases (``CASES``): starts (mirror, black under the sun, fully transparent, fully opaque and rough), light (sun
glints from a smooth start, a low sun, an area light indoors, a panorama with a 1e5 hot pixel), geometry (zero-area
and sliver triangles, thin parts, an open mesh, an object covering ~2 % of the frame and one filling it) and
grazing views (2 degrees above the ground). Sizes are tiny (3 views at 40 px, 128 px maps, 2,000 vertices,
10 + 2 iterations; the fast preset otherwise, its pose and roughness searches included) so the default run of every
case takes ~10-15 min on a 2-core machine (each run ~30 s idle, ~60-90 s at a load average of 10).

Variants (``--variants``): ``after`` (the fast preset as it is), ``before`` (its three issue-32 additions off:
``--loss-clamp 0 --grad-clip 0 --init-search off``, the optimiser as it was) and one ablation per addition
(``no-clamp``, ``no-clip``, ``no-init-search``). ``--builtin`` instead runs the six built-in scenes with the same
variants at the hard cases' sizes and iterations (one run each, equal iterations) and scores them the same way; at
equal CPU seconds, several seeds, with ``camo evaluate``'s metrics: ``bench/bench_equal_seconds.py``.

    python bench/bench_hard_cases.py                                     # every case, variant after
    python bench/bench_hard_cases.py --variants before,after --write     # the table in docs/results/hard_cases.md
    python bench/bench_hard_cases.py --cases start_mirror,light_hot_pixel --variants before,after,no-clip
    python bench/bench_hard_cases.py --builtin --variants before,after --write     # its "builtin" block
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: Seed of the benchmark's own scoring views (the run's seed is 0).
BENCH_SEED = 9173
#: Score differences below this (dB) are noise (two scores of one image at 16 spp differ by up to ~0.05 dB).
TOLERANCE_DB = 0.1
#: Largest allowed loss spike (x the running median), from the second iteration on.
SPIKE_LIMIT = 10.0

SIZES = {"views": 3, "resolution": 40, "iterations": 10, "stage2_iterations": 2, "map_resolution": 128,
         "displacement_resolution": 64, "target_vertices": 2000, "target_spp": 32}
#: Options only ``ours`` reads (the mean baseline refuses them).
OURS_ONLY = ("iterations", "stage2_iterations", "displacement_resolution", "spp", "init", "loss_clamp", "grad_clip",
             "init_search", "time_budget", "holdout_every", "snapshot_every")

VARIANTS: dict[str, dict[str, Any]] = {
    "after": {},
    "before": {"loss_clamp": 0.0, "grad_clip": 0.0, "init_search": "off"},
    "no-clamp": {"loss_clamp": 0.0},
    "no-clip": {"grad_clip": 0.0},
    "no-init-search": {"init_search": "off"},
}

MIRROR = "albedo=1,metallic=1,roughness=0,transmittance=0"


# ------------------------------------------------------------------------------------------------------------------
# the cases: each writes what it needs into a work folder and returns the run options

def _pack(work: Path, name: str, *, obj: str = 'primitive = "backpack"', env: str = 'builtin = "meadow"',
          cameras: str = "", size: float = 1.0, roughness: float = 0.5) -> str:
    """A scene pack file around a built-in environment (the built-in scenes' start: roughness 0.5)."""
    path = work / f"{name}.toml"
    path.write_text(f'name = "{name}"\n[object]\n{obj}\nsize = {size}\n[environment]\n{env}\n'
                    f"[cameras]\nviews = 16\n{cameras}\n[render]\nresolution = 48\n"
                    f"[material]\nroughness = {roughness}\n")
    return str(path)


def _mesh(work: Path, name: str, vertices: np.ndarray, faces: np.ndarray) -> str:
    path = work / f"{name}.ply"
    import trimesh

    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return f'mesh = "{path}"'


def _sphere() -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3)
    m.apply_translation([0.0, 0.0, 1.0])
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def degenerate_sphere() -> tuple[np.ndarray, np.ndarray]:
    """An icosphere with zero-area faces (collinear vertices, repeated indices) and sliver triangles (aspect ratio
    ~1e4) fanned over a band of its surface."""
    v, f = _sphere()
    n = len(v)
    collinear = np.array([[0.1, 0.1, 1.0], [0.2, 0.2, 1.0], [0.3, 0.3, 1.0]])
    zero = np.array([[n, n + 1, n + 2], [0, 0, 1], [2, 3, 2], [5, 5, 5]])
    slivers, extra = [], []
    for k, (a, b, _) in enumerate(f[:40]):
        mid = 0.5 * (v[a] + v[b]) * (1.0 + 1e-4)  # just off the edge: a sliver on the surface
        extra.append(mid)
        slivers.append([a, b, n + 3 + k])
    return np.vstack([v, collinear, np.array(extra)]), np.vstack([f, zero, np.array(slivers)])


def thin_parts() -> tuple[np.ndarray, np.ndarray]:
    """A 1 x 0.6 x 0.01 plate standing on the ground beside a pole of radius 0.01."""
    import trimesh

    plate = trimesh.creation.box(extents=(1.0, 0.01, 0.6))
    plate.apply_translation([0.0, 0.0, 0.3])
    pole = trimesh.creation.cylinder(radius=0.01, height=1.0, sections=12)
    pole.apply_translation([0.6, 0.0, 0.5])
    m = trimesh.util.concatenate([plate, pole])
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def open_sphere() -> tuple[np.ndarray, np.ndarray]:
    """The icosphere with its top cap removed (a boundary loop; the inside is seen from above)."""
    v, f = _sphere()
    return v, f[v[f].mean(1)[:, 2] < 1.6]


def hot_pixel_panorama(work: Path) -> str:
    """The built-in panorama (halved) with one pixel at 1e5 (the sun in it peaks at ~3e4)."""
    from camo_base import imaging
    from optimizer.scenes.environments import builtin_panorama

    pano = imaging.load_exr(builtin_panorama()).astype(np.float32)
    pano = pano[::2, ::2].copy()
    h, w = pano.shape[:2]
    pano[h // 3, w // 5] = 1e5
    path = work / "hot_pixel.exr"
    imaging.save_exr(path, pano)
    return f'panorama = "{path}"'


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    group: str
    what: str
    make: Callable[[Path], dict[str, Any]]  # work folder -> run options (scene and case-specific ones)


CASES: tuple[Case, ...] = (
    Case("start_mirror", "start", "meadow from a mirror (albedo 1, metallic 1, roughness 0, transmittance 0)",
         lambda w: {"scene": "meadow", "init": MIRROR}),
    Case("start_black_sun", "start", "meadow (sun) from a black opaque start (albedo 0, transmittance 0)",
         lambda w: {"scene": "meadow", "init": "albedo=0,transmittance=0"}),
    Case("start_transparent", "start", "meadow from a fully transparent start (transmittance 1)",
         lambda w: {"scene": "meadow", "init": "transmittance=1"}),
    Case("start_opaque_rough", "start", "meadow from a fully opaque, fully rough start (transmittance 0, roughness 1)",
         lambda w: {"scene": "meadow", "init": "transmittance=0,roughness=1"}),
    Case("light_glints", "light", "meadow from a smooth dielectric start (roughness 0: sun glints)",
         lambda w: {"scene": "meadow", "init": "roughness=0"}),
    Case("light_low_sun", "light", "gravel: a low, hazy sun (long shadows)", lambda w: {"scene": "gravel"}),
    Case("light_area_indoor", "light", "room: a ceiling area light indoors", lambda w: {"scene": "room"}),
    Case("light_hot_pixel", "light", "a panorama with a 1e5 hot pixel (plus its own ~3e4 sun)",
         lambda w: {"scene": _pack(w, "hot", obj='primitive = "utility_box"', env=hot_pixel_panorama(w))}),
    Case("geo_degenerate", "geometry", "zero-area and sliver triangles (aspect ~1e4) on a sphere",
         lambda w: {"scene": _pack(w, "degenerate", obj=_mesh(w, "degenerate", *degenerate_sphere()))}),
    Case("geo_thin", "geometry", "thin parts: a 1 cm plate and a 1 cm pole",
         lambda w: {"scene": _pack(w, "thin", obj=_mesh(w, "thin", *thin_parts()))}),
    Case("geo_open", "geometry", "an open mesh (a sphere without its top cap)",
         lambda w: {"scene": _pack(w, "open", obj=_mesh(w, "open", *open_sphere()))}),
    Case("geo_tiny", "geometry", "an object covering 1.6 % of the frame (size 0.35 at radius 4)",
         lambda w: {"scene": _pack(w, "tiny", size=0.35)}),
    Case("geo_filling", "geometry", "an object close to the cameras: 44 % of the frame (radius 1.9, fov 30)",
         lambda w: {"scene": _pack(w, "filling", cameras="radius = 1.9")}),
    Case("view_grazing", "views", "grazing views: cameras 2 degrees above the ground",
         lambda w: {"scene": _pack(w, "grazing", cameras="elevation = 2.0\nradius = 4.0")}),
)

#: The built-in scenes (``--builtin``; bench/bench_equal_seconds.py runs them too).
BUILTIN = ("meadow", "gravel", "split", "room", "occluded", "panorama")
DOC = ROOT / "docs" / "results" / "hard_cases.md"


# ------------------------------------------------------------------------------------------------------------------
# measuring

def loss_spike(losses: list[float]) -> float:
    """The largest ``losses[i] / median(losses[:i])`` for ``i >= 1`` (1 when flat; inf for a non-finite loss).

    >>> loss_spike([1.0, 1.0, 12.0, 1.0])
    12.0
    >>> loss_spike([0.5])
    1.0
    """
    worst = 1.0
    for i in range(1, len(losses)):
        med = float(np.median(losses[:i]))
        x = losses[i]
        if not math.isfinite(x):
            return float("inf")
        if med > 0:
            worst = max(worst, x / med)
    return worst


class Scorer:
    """PSNR of parameter values on the benchmark's own 4 jittered views of a run spec's rig (module doc)."""

    def __init__(self, spec):
        from optimizer.optimise.holdout import Holdout, HoldoutSettings
        from optimizer.optimise.run import glint_safe_start
        from optimizer.optimise.stage1 import Stage1
        from optimizer.rendering.placement import prepare_object
        from optimizer.rendering.planner import plan
        from optimizer.scenes.cameras import cameras
        from optimizer.scenes.environments import get_environment

        env = get_environment(spec.pack.environment)
        pack, _ = glint_safe_start(spec.pack, env, spec)
        app = spec.appearance
        pl = plan(pack, env, app.planner_params(), "optimize", spec.shadow_gradients)
        cfg = dataclasses.replace(spec.stage1_config(), seed=BENCH_SEED)
        self.stage = Stage1(pack, env, prepare_object(pack), cameras(pack), pl, cfg, app)
        self.start = {k: v.copy() for k, v in self.stage.values.items()}  # before any warm start or search
        self.holdout = Holdout.for_stage(HoldoutSettings(views=4, spp=16), self.stage)

    def psnr(self, values: dict[str, np.ndarray]) -> float:
        from optimizer.optimise.holdout import psnr_of

        full = {**self.start, **{k: v for k, v in values.items() if k in self.start}}
        return psnr_of(self.holdout.score(full)[0])

    def coverage(self) -> float:
        """Mean fraction of the scoring views' pixels the object covers (at its start)."""
        return float(np.mean(self.holdout._coverage(self.start, self.holdout.cams) > 0))


def mean_values(options: dict[str, Any]) -> dict[str, np.ndarray]:
    """The ``mean`` baseline's parameters for the case's scene and sizes."""
    from optimizer.optimise.baselines import common, owens2014
    from optimizer.optimise.spec import RunSpec

    spec = RunSpec.from_options({**{k: v for k, v in options.items() if k not in OURS_ONLY}, "method": "mean"})
    values, _, _ = owens2014.compute(common.setup(spec), "mean")
    return values


def run_case(options: dict[str, Any], out: Path) -> dict[str, Any]:
    """One ``ours`` run of ``options`` into ``out``; its log figures and result values."""
    from optimizer.optimise.run import run
    from optimizer.optimise.spec import RunSpec

    spec = RunSpec.from_options({**options, "snapshot_every": 100_000})
    t0 = time.perf_counter()
    run(spec, out, progress=False)
    seconds = time.perf_counter() - t0
    recs = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines() if line.strip()]
    s1 = [r for r in recs if r.get("stage") == 1]
    summary = json.loads((out / "summary.json").read_text())
    with np.load(out / "snapshots" / "result.npz") as z:
        values = {k: z[k] for k in z.files if k not in ("seconds", "iteration", "stage")}
    nonfinite = sum(int(r.get("nonfinite_grads", 0)) for r in recs) + \
        sum(int((~np.isfinite(v)).sum()) for v in values.values())
    photo = [r["loss_photo"] for r in s1]
    linear = [r.get("loss_linear", r["loss_photo"]) for r in s1]
    return {"spec": spec, "values": values, "nonfinite": nonfinite, "spike": loss_spike(photo),
            "spike_linear": loss_spike(linear), "loss": photo, "loss_linear": linear, "seconds": seconds,
            "clipped": sum(bool(r.get("grad_clipped")) for r in recs),
            "iterations": len(recs), "seconds_per_iteration": float(summary.get("seconds_iterations", float("nan")))
            / max(len(recs), 1),
            "init_search": (summary.get("init_search") or {}).get("chosen"),
            "holdout": [(c["stage"], c["iteration"], round(c["psnr"], 2)) for c in
                        (summary.get("holdout") or {}).get("checks", [])]}


def measure(name: str, options: dict[str, Any], variants: list[str], work: Path, say) -> list[dict[str, Any]]:
    """Every variant of one case (or built-in scene), with its start and the mean baseline scored once."""
    from optimizer.optimise.spec import RunSpec

    rows = []
    scorer = Scorer(RunSpec.from_options(options))
    start = scorer.psnr(scorer.start)  # first: fixes the scoring domain (the start's object + shadow)
    try:
        mean = scorer.psnr(mean_values(options))
    except Exception as exc:  # a baseline that cannot paint this object: "where Mean is defined"
        say(f"  mean undefined: {type(exc).__name__}: {exc}")
        mean = float("nan")
    for variant in variants:
        try:
            r = run_case({**options, **VARIANTS[variant]}, work / f"{name}_{variant}")
        except Exception as exc:  # a crash is a finding: a row that misses every target
            say(f"  {variant:>14}: FAILED {type(exc).__name__}: {exc}")
            rows.append({"case": name, "variant": variant, "nonfinite": -1, "spike": float("inf"),
                         "spike_linear": float("inf"), "start": start, "result": float("nan"), "mean": mean,
                         "ok": False, "seconds": float("nan"), "error": f"{type(exc).__name__}: {exc}",
                         "loss": [], "loss_linear": [], "holdout": []})
            continue
        result = scorer.psnr(r["values"])
        ok = (r["nonfinite"] == 0 and r["spike"] <= SPIKE_LIMIT and result >= start - TOLERANCE_DB
              and (not math.isfinite(mean) or result >= mean - TOLERANCE_DB))
        row = {"case": name, "variant": variant, "nonfinite": r["nonfinite"], "spike": r["spike"],
               "spike_linear": r["spike_linear"], "start": start, "result": result, "mean": mean, "ok": ok,
               "seconds": r["seconds"], "clipped_steps": r["clipped"], "init_search": r["init_search"],
               "iterations": r["iterations"], "seconds_per_iteration": r["seconds_per_iteration"],
               "coverage": scorer.coverage(), "loss": r["loss"], "loss_linear": r["loss_linear"],
               "holdout": r["holdout"]}
        say(f"  {variant:>14}: nonfinite {row['nonfinite']}, spike {row['spike']:.3g} (linear "
            f"{row['spike_linear']:.3g}), start {start:.2f} dB -> result {result:.2f} dB, mean {mean:.2f} dB, "
            f"{'ok' if ok else 'MISSED'} ({r['seconds']:.0f} s)")
        rows.append(row)
    return rows


# ------------------------------------------------------------------------------------------------------------------
# the table

def table(rows: list[dict[str, Any]], what: dict[str, str]) -> str:
    per_it = any(math.isfinite(r.get("seconds_per_iteration", float("nan"))) for r in rows)
    head = ("| case | variant | non-finite | spike | spike (linear) | start dB | result dB | Mean dB | targets | s |"
            + (" s/it |" if per_it else "") + "\n|---|---|---:|---:|---:|---:|---:|---:|---|---:|"
            + ("---:|" if per_it else "") + "\n")
    lines = []
    for r in rows:
        def f(x, d=2):
            return "n/a" if not math.isfinite(x) else f"{x:.{d}f}"

        lines.append(f"| {r['case']} | {r['variant']} | {r['nonfinite']} | {r['spike']:.3g} | "
                     f"{r['spike_linear']:.3g} | {f(r['start'])} | {f(r['result'])} | {f(r['mean'])} | "
                     f"{'met' if r['ok'] else '**missed**'} | {f(r['seconds'], 0)} |"
                     + (f" {f(r.get('seconds_per_iteration', float('nan')), 1)} |" if per_it else ""))
    cases = "\n".join(f"* `{k}`: {v}" for k, v in what.items())
    return head + "\n".join(lines) + "\n\n" + cases + "\n"


END = "<!-- /bench_hard_cases -->"


def write_block(path: Path, text: str, name: str) -> None:
    """Replace the generated block ``name`` of ``path`` (between ``<!-- bench_hard_cases: NAME -->`` and ``END``) by
    ``text``; the block is appended when the file has none."""
    BEGIN = f"<!-- bench_hard_cases: {name} -->"
    old = path.read_text() if path.is_file() else ""
    block = f"{BEGIN}\n{text}{END}"
    if BEGIN in old and END in old[old.index(BEGIN):]:
        i = old.index(BEGIN)
        j = old.index(END, i)
        new = old[:i] + block + old[j + len(END):]
    else:
        new = old + ("\n" if old else "") + block + "\n"
    path.write_text(new)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="", help="comma list of case names (default: all)")
    ap.add_argument("--variants", default="after", help=f"comma list of {', '.join(VARIANTS)}")
    ap.add_argument("--builtin", action="store_true",
                    help="the six built-in scenes at the cases' sizes and iterations instead (equal iterations)")
    ap.add_argument("--scenes", default=",".join(BUILTIN), help="--builtin: comma list of scenes")
    ap.add_argument("--json", default=None, help="also write every row (with loss curves) to this JSON file")
    ap.add_argument("--write", nargs="?", const=str(DOC), default=None,
                    help=f"write the table into this Markdown file's generated block (default "
                         f"{DOC.relative_to(ROOT)})")
    ap.add_argument("--work", default=None, help="keep the run directories here (default: a temporary folder)")
    ap.add_argument("--rows", default=None, help="no runs: the table of rows an earlier --json wrote")
    ap.add_argument("--block", default=None,
                    help="the --write block's name (default: builtin with --builtin, else cases)")
    args = ap.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        ap.error(f"unknown variant(s) {', '.join(bad)}; choose from {', '.join(VARIANTS)}")
    from optimizer import backend

    backend.init()
    say = lambda s: print(s, flush=True)  # noqa: E731
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    if args.rows:
        saved = json.loads(Path(args.rows).read_text())
        if isinstance(saved, list):  # rows only: the cases' descriptions from this file, no timing
            names = list(dict.fromkeys(r["case"] for r in saved))
            known = {c.name: c.what for c in CASES}
            saved = {"rows": saved, "what": {n: known.get(n, f"built-in scene {n}") for n in names},
                     "seconds": float("nan"), "load": float("nan")}
        rows, what, elapsed, load = saved["rows"], saved["what"], saved["seconds"], saved["load"]
        return _report(rows, what, elapsed, load, args)
    with tempfile.TemporaryDirectory(prefix="hard_cases_") as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        if args.builtin:
            what = {sc: f"built-in scene {sc} at {SIZES['iterations']} + {SIZES['stage2_iterations']} iterations"
                    for sc in args.scenes.split(",") if sc}
            cases = [(sc, {"scene": sc, **SIZES}) for sc in what]
        else:
            names = [c for c in args.cases.split(",") if c] or [c.name for c in CASES]
            known = {c.name: c for c in CASES}
            unknown = [n for n in names if n not in known]
            if unknown:
                ap.error(f"unknown case(s) {', '.join(unknown)}; choose from {', '.join(known)}")
            what = {n: known[n].what for n in names}
            cases = [(n, None) for n in names]
        for n, opts in cases:
            say(f"{n}: {what[n]}")
            rows += measure(n, opts or {**known[n].make(work), **SIZES}, variants, work, say)
            if args.json:  # after every case: a run stopped part-way still leaves its rows (--rows tables them)
                _save(args.json, rows, {k: what[k] for k in dict.fromkeys(r["case"] for r in rows)}, t0)
    elapsed, load = time.perf_counter() - t0, os.getloadavg()[0]
    if args.json:
        _save(args.json, rows, what, t0)
    return _report(rows, what, elapsed, load, args)


def _save(path: str, rows: list[dict[str, Any]], what: dict[str, str], t0: float) -> None:
    Path(path).write_text(json.dumps({"rows": rows, "what": what, "seconds": time.perf_counter() - t0,
                                      "load": os.getloadavg()[0]}, indent=1, default=float))


def _report(rows, what, elapsed: float, load: float, args) -> int:
    text = table(rows, what)
    met = sum(r["ok"] for r in rows)
    text += (f"\n{met} of {len(rows)} rows meet every target; {elapsed:.0f} s in all, load average {load:.1f} at "
             f"the end.\n")
    print(text)
    if args.write:
        write_block(Path(args.write), text, args.block or ("builtin" if args.builtin else "cases"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
