"""Power analysis of the click-to-find study (``camo study power``): how many participants separate the methods.

Input: per-trial outcomes of each (scene, method) cell, either **predicted** (the simulated observer's
``simulated_trials.parquet`` of ``camo evaluate`` directories, :mod:`evaluation.observer`) or from a **pilot**
study database (its analysed formal trials, :func:`study_site.analysis.formal_trials`).

Method (a parametric bootstrap through the study's own analysis): for each number of participants ``N`` and
each of ``reps`` replicates, ``N`` participants are simulated as the site runs them -- one formal trial per
scene, the method of each scene rotated over participants (participant ``i`` sees method ``(i + j) mod M`` in
scene ``j``: every cell filled evenly, as the site's least-filled assignment does) -- and each trial's outcome
(found or not, search time, timeout) is drawn with replacement from that cell's outcomes. Each simulated study is
analysed by :func:`study_site.analysis.pairwise_tests`, exactly as ``camo study report`` does Table I's pairwise
tests: Fisher's exact test on the not-found counts (confusion rate) and the log-rank test on time-to-find, each
Holm-corrected over the method pairs. Power of a pair = share of replicates with a Holm-adjusted p below
``alpha``; the participants needed = the smallest ``N`` of the grid with power >= ``target`` (linear
interpolation between grid points is not attempted: the grid is reported as measured).

Like the analysis, the tests treat trials as independent: participants' individual differences are not in the
model (a predicted study has none; a pilot's are resampled away by drawing trials, not participants).

Output (``--out DIR``, atomically): ``power.csv`` (N, pair, test, power), ``power_needed.csv`` (per pair and
test: participants for the target power, or empty when the largest N does not reach it), ``power.md`` and the
curve ``power.png``.
"""

from __future__ import annotations

import math
from itertools import combinations
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from camo_base.errors import CamoError

DEFAULT_PARTICIPANTS = (10, 20, 30, 40, 60, 80, 100, 150, 200, 300)
TESTS = {"p_fisher_holm": "confusion rate (Fisher, Holm)", "p_logrank_holm": "time to find (log-rank, Holm)"}


def cells_from_predicted(eval_dirs: Sequence[str | Path]) -> pd.DataFrame:
    """Per simulated trial ``scene, method, found, timed_out, rt_s, time_limit_s`` from evaluations'
    ``simulated_trials.parquet`` (``method`` = the study's condition id, :mod:`optimizer.assets.conditions`)."""
    from optimizer.assets.conditions import condition

    frames = []
    for d in eval_dirs:
        p = Path(d) / "simulated_trials.parquet"
        if not p.is_file():
            raise CamoError(f"{d}: no simulated_trials.parquet (run `camo evaluate` with --observer-trials > 0)")
        try:
            frames.append(pd.read_parquet(p))
        except Exception as exc:  # pyarrow raises several types for a corrupt file
            raise CamoError(f"{p}: cannot read ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") \
                from None
    t = pd.concat(frames, ignore_index=True)
    t["method"] = [condition(m, a).id for m, a in zip(t["method"], t["ablation"])]
    return t[["scene", "method", "found", "timed_out", "rt_s", "time_limit_s"]].reset_index(drop=True)


def cells_from_pilot(db) -> pd.DataFrame:
    """The analysed formal trials of a pilot study database (URL or SQLite path)."""
    from study_site.analysis import formal_trials, load_tables

    trials, _ = load_tables(db)
    f = formal_trials(trials)
    if f.empty:
        raise CamoError("the pilot database has no analysed formal trials (completed participants)")
    f = f.drop(columns=["method"]).rename(columns={"condition": "method"})  # cells are conditions
    return f[["scene", "method", "found", "timed_out", "rt_s", "time_limit_s"]].reset_index(drop=True)


def _cell_arrays(cells: pd.DataFrame) -> dict[tuple[str, str], tuple[np.ndarray, ...]]:
    return {k: (g["found"].to_numpy(bool), g["timed_out"].to_numpy(bool), g["rt_s"].to_numpy(float),
                g["time_limit_s"].to_numpy(float)) for k, g in cells.groupby(["scene", "method"])}


def simulate_study(cells: pd.DataFrame | dict, n_participants: int, rng: np.random.Generator) -> pd.DataFrame:
    """One simulated study: ``n_participants`` x one trial per scene, methods rotated, outcomes drawn from the
    cells (a DataFrame, or :func:`_cell_arrays` of one). Columns as :func:`study_site.analysis.pairwise_tests`
    reads them."""
    arrays = cells if isinstance(cells, dict) else _cell_arrays(cells)
    scenes = sorted({s for s, _ in arrays})
    parts: list[pd.DataFrame] = []
    pid = np.array([f"p{i}" for i in range(n_participants)])
    for j, scene in enumerate(scenes):
        avail = sorted(m for s, m in arrays if s == scene)
        which = (np.arange(n_participants) + j) % len(avail)
        for k, m in enumerate(avail):
            sel = np.flatnonzero(which == k)
            if sel.size == 0:
                continue
            found, tout, rt, lim = arrays[(scene, m)]
            idx = rng.integers(len(found), size=sel.size)
            parts.append(pd.DataFrame({"participant": pid[sel], "scene": scene, "method": m, "condition": m,
                                       "label": m, "found": found[idx],
                                       "timed_out": tout[idx], "rt_s": rt[idx], "time_limit_s": lim[idx]}))
    return pd.concat(parts, ignore_index=True)


def power_curve(cells: pd.DataFrame, participants: Sequence[int] = DEFAULT_PARTICIPANTS, reps: int = 200,
                alpha: float = 0.05, seed: int = 0) -> pd.DataFrame:
    """Power per ``N`` participants, method pair and test (columns ``n_participants, method_a, method_b, test,
    power, reps``)."""
    from study_site.analysis import pairwise_tests

    if cells["method"].nunique() < 2:
        raise CamoError("power needs at least two methods")
    if reps < 1:
        raise CamoError("--reps must be >= 1")
    if not 0 < alpha < 1:
        raise CamoError("--alpha must be in (0, 1)")
    rng = np.random.default_rng(seed)
    arrays = _cell_arrays(cells)
    rows = []
    for n in participants:
        hits: dict[tuple[str, str, str], int] = {}
        for _ in range(reps):
            pw = pairwise_tests(simulate_study(arrays, int(n), rng))
            for r in pw.itertuples():
                for test in TESTS:
                    p = getattr(r, test)
                    key = (r.condition_a, r.condition_b, test)
                    hits[key] = hits.get(key, 0) + int(bool(np.isfinite(p) and p < alpha))
        for (a, b, test), k in hits.items():
            rows.append({"n_participants": int(n), "method_a": a, "method_b": b, "test": test, "power": k / reps,
                         "reps": reps})
    return pd.DataFrame(rows)


def participants_needed(curve: pd.DataFrame, target: float = 0.8) -> pd.DataFrame:
    """Per pair and test, the smallest N of the grid whose power reaches ``target`` (NaN when none does)."""
    out = []
    for (a, b, test), g in curve.groupby(["method_a", "method_b", "test"], sort=True):
        g = g.sort_values("n_participants")
        ok = g.loc[g["power"] >= target, "n_participants"]
        out.append({"method_a": a, "method_b": b, "test": test, "target": target,
                    "participants": int(ok.iloc[0]) if len(ok) else math.nan,
                    "power_at_max_n": float(g["power"].iloc[-1]), "max_n": int(g["n_participants"].iloc[-1])})
    return pd.DataFrame(out)


def plot_power(curve: pd.DataFrame, path: Path, target: float, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from camo_base.atomic import atomic_path

    fig, axes = plt.subplots(1, len(TESTS), figsize=(6 * len(TESTS), 4.2), dpi=120, squeeze=False)
    for ax, (test, name) in zip(axes[0], TESTS.items()):
        d = curve[curve["test"] == test]
        for (a, b), g in d.groupby(["method_a", "method_b"], sort=True):
            g = g.sort_values("n_participants")
            ax.plot(g["n_participants"], g["power"], "o-", ms=4, label=f"{a} vs {b}")
        ax.axhline(target, color="0.4", ls="--", lw=1)
        ax.text(ax.get_xlim()[0], target + 0.01, f" {100 * target:.0f} %", fontsize=8, color="0.3", va="bottom")
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("participants (one trial per scene each)")
        ax.set_ylabel("power")
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def write_power(cells: pd.DataFrame, out: str | Path, participants: Sequence[int] = DEFAULT_PARTICIPANTS,
                reps: int = 200, alpha: float = 0.05, target: float = 0.8, seed: int = 0,
                source: str = "") -> dict[str, Any]:
    """Run :func:`power_curve` and write ``power.csv``, ``power_needed.csv``, ``power.md``, ``power.png``."""
    from camo_base.atomic import atomic_path, write_text

    if not 0 < target < 1:
        raise CamoError("--target must be in (0, 1)")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CamoError(f"--out {out} exists and is not a folder")
    curve = power_curve(cells, participants, reps, alpha, seed)
    need = participants_needed(curve, target)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "power.csv") as tmp:
        curve.to_csv(tmp, index=False)
    with atomic_path(out / "power_needed.csv") as tmp:
        need.to_csv(tmp, index=False)
    scenes = cells["scene"].nunique()
    rates = cells.groupby("method").agg(trials=("found", "size"), confusion=("found", lambda s: 1 - s.mean()),
                                        median_rt_found=("rt_s", "median"))
    title = (f"Power to separate the methods ({source}; {scenes} scenes, {reps} simulated studies per N, "
             f"alpha {alpha:g}, Holm)")
    plot_power(curve, out / "power.png", target, title)
    lines = ["# Power analysis of the click-to-find study", "", f"Source: {source}. {scenes} scene(s) (one formal "
             f"trial per scene and participant, methods rotated), {reps} simulated studies per N, alpha {alpha:g}, "
             f"Holm over the pairs, target power {100 * target:.0f} %. Method: `study_site/power.py`.", "",
             "| Method | source trials | confusion rate |", "|---|---:|---:|"]
    for m, r in rates.iterrows():
        lines.append(f"| {_label(m)} | {int(r.trials)} | {100 * r.confusion:.1f}% |")
    lines += ["", "| Pair | Test | Participants for target | Power at largest N |", "|---|---|---:|---:|"]
    for r in need.itertuples():
        n = f"{int(r.participants)}" if np.isfinite(r.participants) else f"> {r.max_n}"
        lines.append(f"| {_label(r.method_a)} vs {_label(r.method_b)} | {TESTS[r.test]} | {n} | {100 * r.power_at_max_n:.0f}% "
                     f"(N = {r.max_n}) |")
    lines += ["", "![power curve](power.png)", ""]
    write_text(out / "power.md", "\n".join(lines))
    return {"curve": curve, "needed": need}


def _label(cond_id: str) -> str:
    """``label (id)`` of a condition id, for power.md."""
    from optimizer.assets.conditions import label_of_id

    lab = label_of_id(cond_id)
    return lab if lab == cond_id else f"{lab} (`{cond_id}`)"


def parse_participants(text: str) -> list[int]:
    try:
        ns = sorted({int(x) for x in text.split(",") if x.strip()})
    except ValueError:
        raise CamoError(f"--participants must be a comma list of integers, not {text!r}") from None
    if not ns or ns[0] < 2 or ns[-1] > 100_000:
        raise CamoError("--participants must list numbers of participants between 2 and 100000")
    return ns
