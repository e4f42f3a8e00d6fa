"""Power analysis of the click-to-find study (``camo study power``): how many participants separate the methods.

Input: per-trial outcomes of each (scene, method) cell, either **predicted** (the simulated observer on a stimulus
set, ``predicted_trials.parquet`` written by ``camo study build-stimuli`` / ``camo study predict``:
:mod:`study_site.predict`) or from a **pilot** study database (its analysed formal trials,
:func:`study_site.analysis.formal_trials`).

Method (a parametric bootstrap through the study's own tests): for each number of participants ``N`` and each of
``reps`` replicates, ``N`` participants are simulated as the site runs them -- one formal trial per scene, the
method of each scene rotated over participants (participant ``i`` sees method ``(i + j) mod M`` in scene ``j``:
every cell filled evenly, as the site's least-filled assignment does) -- and each trial's outcome (found or not,
search time, timeout) is drawn with replacement from that cell's outcomes. Each simulated study gets Table I's
pairwise tests (:func:`study_site.analysis.pairwise_tests`, as ``camo study report`` runs them): Fisher's exact
test on the not-found counts and the log-rank test on time-to-find (misses and timeouts censored at the limit),
each Holm-corrected over the method pairs. Power of a pair = share of replicates with a Holm-adjusted p below
``alpha``; the participants needed = the smallest ``N`` of the grid with power >= ``target`` (the grid is reported
as measured, not interpolated).

**Vectorised**: the ``reps`` replicates of one ``N`` are drawn at once as index arrays, and both tests are computed
on all of them together -- Fisher's two-sided p from the hypergeometric log-pmf over the whole support, the
log-rank statistic (with the hypergeometric variance, as ``lifelines.statistics.logrank_test``) from per-time
event and at-risk counts -- then Holm per replicate. :func:`replicate_frame` turns one replicate back into the
trial table the loop version fed to :func:`study_site.analysis.pairwise_tests`; ``tests/test_power.py`` checks
that both give the same p-values replicate by replicate. The loop version took 29-31 s per scene on a quiet machine
and 714 s under load 17-25 (pandas and lifelines per replicate); the vectorised one does the same resampling in a
few seconds (``bench/bench_power.py`` measures both side by side).

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

#: Search times are rounded to this grid (seconds) before the log-rank test: ~800 distinct times in a 40 s trial
#: instead of one per simulated trial (20,000 for a scene's 5 methods x 20 stimuli x 200 trials), which made the
#: per-time counts the bulk of the work. 50 ms is below the site's timing precision over the network and far below
#: the differences the study measures; times already on a coarser grid are unchanged.
TIME_BIN_S = 0.05
DEFAULT_PARTICIPANTS = (10, 20, 30, 40, 60, 80, 100, 150, 200, 300)
TESTS = {"p_fisher_holm": "confusion rate (Fisher, Holm)", "p_logrank_holm": "time to find (log-rank, Holm)"}


def cells_from_predicted(stim_dirs: Sequence[str | Path]) -> pd.DataFrame:
    """Per simulated formal trial ``scene, method, found, timed_out, rt_s, time_limit_s`` from stimulus sets'
    ``predicted_trials.parquet`` (``method`` = the study's condition id, :mod:`optimizer.assets.conditions`)."""
    from study_site.predict import read_predicted

    frames = []
    for d in stim_dirs:
        _, t, _ = read_predicted(d)
        frames.append(t[~t["practice"].astype(bool)])
    t = pd.concat(frames, ignore_index=True)
    if t.empty:
        raise CamoError("the stimulus sets' predictions hold no formal trials")
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


def cell_counts(scenes_methods: dict[str, list[str]], n_participants: int) -> dict[tuple[str, str], int]:
    """Trials per (scene, method) cell when ``n_participants`` take one trial per scene with the methods rotated
    (as :func:`simulate_study` assigns them)."""
    out = {}
    for j, scene in enumerate(sorted(scenes_methods)):
        avail = sorted(scenes_methods[scene])
        which = (np.arange(n_participants) + j) % len(avail)
        for k, m in enumerate(avail):
            out[(scene, m)] = int((which == k).sum())
    return out


def draw_replicates(arrays: dict, n_participants: int, reps: int, rng: np.random.Generator,
                    times: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    """``reps`` simulated studies at once: per method ``{found, timed_out, rt, limit, t}`` arrays ``(reps, n_m)``
    (the method's trials over all scenes, scene by scene in sorted order; ``t`` = index of the time-to-find in
    ``times``)."""
    scenes: dict[str, list[str]] = {}
    for s, m in arrays:
        scenes.setdefault(s, []).append(m)
    counts = cell_counts(scenes, n_participants)
    parts: dict[str, list[dict[str, np.ndarray]]] = {}
    for (scene, m), c in sorted(counts.items()):
        if c == 0:
            continue
        found, tout, rt, lim = arrays[(scene, m)]
        idx = rng.integers(len(found), size=(reps, c))
        ttf = np.where(found, rt, lim)
        parts.setdefault(m, []).append({"found": found[idx], "timed_out": tout[idx], "rt": rt[idx],
                                        "limit": lim[idx], "t": np.searchsorted(times, ttf)[idx]})
    return {m: {k: np.concatenate([p[k] for p in ps], axis=1) for k in ps[0]} for m, ps in parts.items()}


def replicate_frame(draws: dict[str, dict[str, np.ndarray]], r: int) -> pd.DataFrame:
    """Replicate ``r`` of :func:`draw_replicates` as the trial table :func:`study_site.analysis.pairwise_tests`
    reads (for checking the vectorised tests against it)."""
    return pd.concat([pd.DataFrame({"method": m, "condition": m, "label": m, "found": d["found"][r],
                                    "timed_out": d["timed_out"][r], "rt_s": d["rt"][r], "time_limit_s": d["limit"][r]})
                      for m, d in sorted(draws.items())], ignore_index=True)


def fisher_two_sided(ka: np.ndarray, na: int, kb: np.ndarray, nb: int) -> np.ndarray:
    """Two-sided Fisher exact p of the tables ``[[ka, na - ka], [kb, nb - kb]]`` for arrays ``ka, kb`` (the row
    totals fixed): the sum of the hypergeometric probabilities not above the observed one (relative tolerance
    1e-7, as SciPy's ``fisher_exact``)."""
    from scipy.special import gammaln

    ka, kb = np.asarray(ka, np.int64), np.asarray(kb, np.int64)
    K = ka + kb
    N = na + nb
    x = np.arange(na + 1)[None, :]
    Kc = K[:, None]

    def lchoose(n, k):
        return gammaln(n + 1) - gammaln(k + 1) - gammaln(n - k + 1)

    valid = (x <= Kc) & (na - x <= N - Kc)
    with np.errstate(invalid="ignore"):
        lp = np.where(valid, lchoose(Kc, np.minimum(x, Kc)) + lchoose(N - Kc, np.clip(na - x, 0, N - Kc))
                      - lchoose(N, na), -np.inf)
    lobs = np.take_along_axis(lp, ka[:, None], 1)
    p = np.where(lp <= lobs + 1e-7, np.exp(lp), 0.0).sum(1)
    return np.minimum(p, 1.0)


def logrank(ta: np.ndarray, ea: np.ndarray, tb: np.ndarray, eb: np.ndarray, k: int) -> np.ndarray:
    """Two-sided log-rank p for every row: times as indices ``< k`` into one sorted time grid, events ``ea, eb``
    (bool); NaN where neither group has an event (as :func:`study_site.analysis.pairwise_tests`)."""
    from scipy.stats import chi2

    reps = ta.shape[0]
    off = (np.arange(reps) * k)[:, None]

    def counts(t, w=None):
        return np.bincount((t + off).ravel(), weights=None if w is None else w.ravel().astype(float),
                           minlength=reps * k).reshape(reps, k)

    all_a, all_b = counts(ta), counts(tb)
    d_a, d_b = counts(ta, ea), counts(tb, eb)
    n_a = ta.shape[1] - np.cumsum(all_a, 1) + all_a  # at risk: time >= t_k
    n_b = tb.shape[1] - np.cumsum(all_b, 1) + all_b
    n, d = n_a + n_b, d_a + d_b
    with np.errstate(invalid="ignore", divide="ignore"):
        e_a = np.where(n > 0, d * n_a / n, 0.0)
        v = np.where(n > 1, d * (n_a / n) * (1 - n_a / n) * (n - d) / (n - 1), 0.0)
        stat = (d_a.sum(1) - e_a.sum(1)) ** 2 / v.sum(1)
    p = chi2.sf(stat, 1)
    p[(d.sum(1) == 0) | ~np.isfinite(stat)] = np.nan
    return p


def holm_rows(p: np.ndarray) -> np.ndarray:
    """Holm-adjusted p-values along each row of ``p`` (NaN stays NaN and is not counted), as
    :func:`study_site.analysis.holm` per row."""
    p = np.asarray(p, float)
    fin = np.isfinite(p)
    m = fin.sum(1, keepdims=True)
    order = np.argsort(np.where(fin, p, np.inf), axis=1, kind="stable")
    sp = np.take_along_axis(np.where(fin, p, np.inf), order, 1)
    rank = np.arange(p.shape[1])[None, :]
    adj = np.where(rank < m, np.minimum(1.0, (m - rank) * np.where(rank < m, sp, 0.0)), -np.inf)
    adj = np.maximum.accumulate(adj, axis=1)
    out = np.full_like(p, np.nan)
    np.put_along_axis(out, order, np.where(rank < m, adj, np.nan), 1)
    return out


def replicate_pvalues(draws: dict[str, dict[str, np.ndarray]], k: int) -> dict[tuple[str, str], dict[str, np.ndarray]]:
    """Per condition pair (in the paper's order, as :func:`study_site.analysis.pairwise_tests`), the Holm-adjusted
    Fisher and log-rank p of every replicate: ``{(a, b): {test: (reps,)}}`` with the keys of :data:`TESTS`."""
    from optimizer.assets.conditions import parse_id

    methods = sorted(draws, key=lambda c: (parse_id(c).order, c))  # the paper's order, as pairwise_tests
    pairs = list(combinations(methods, 2))
    fis, lr = [], []
    for a, b in pairs:
        da, db = draws[a], draws[b]
        fis.append(fisher_two_sided((~da["found"]).sum(1), da["found"].shape[1], (~db["found"]).sum(1),
                                    db["found"].shape[1]))
        lr.append(logrank(da["t"], da["found"], db["t"], db["found"], k))
    hf, hl = holm_rows(np.stack(fis, 1)), holm_rows(np.stack(lr, 1))
    return {pr: {"p_fisher_holm": hf[:, i], "p_logrank_holm": hl[:, i]} for i, pr in enumerate(pairs)}


def power_curve(cells: pd.DataFrame, participants: Sequence[int] = DEFAULT_PARTICIPANTS, reps: int = 200,
                alpha: float = 0.05, seed: int = 0, progress: bool = False) -> pd.DataFrame:
    """Power per ``N`` participants, method pair and test (columns ``n_participants, method_a, method_b, test,
    power, reps``), vectorised over the replicates (module docstring). ``progress``: a bar on stderr."""
    if cells["method"].nunique() < 2:
        raise CamoError("power needs at least two methods")
    if reps < 1:
        raise CamoError("--reps must be >= 1")
    if not 0 < alpha < 1:
        raise CamoError("--alpha must be in (0, 1)")
    rng = np.random.default_rng(seed)
    arrays = _cell_arrays(cells)
    arrays = {k: (f, to, np.round(rt / TIME_BIN_S) * TIME_BIN_S, lim) for k, (f, to, rt, lim) in arrays.items()}
    times = np.unique(np.concatenate([np.where(f, rt, lim) for f, _, rt, lim in arrays.values()]))
    rows = []
    it = list(participants)
    bar = None
    if progress:
        import sys

        from tqdm import tqdm

        bar = tqdm(total=len(it) * reps, desc="power", unit="study", file=sys.stderr, leave=False)
    for n in it:
        chunk = max(1, min(reps, 2_000_000 // max(1, int(n) * 4)))  # bound memory: ~chunk x N x methods draws
        hits: dict[tuple[str, str, str], int] = {}
        done = 0
        while done < reps:
            r = min(chunk, reps - done)
            draws = draw_replicates(arrays, int(n), r, rng, times)
            if len(draws) < 2:
                raise CamoError(f"with {n} participants fewer than two methods get a trial")
            for (a, b), ps in replicate_pvalues(draws, len(times)).items():
                for test, p in ps.items():
                    hits[(a, b, test)] = hits.get((a, b, test), 0) + int((np.isfinite(p) & (p < alpha)).sum())
            done += r
            if bar is not None:
                bar.update(r)
        for (a, b, test), k in sorted(hits.items()):
            rows.append({"n_participants": int(n), "method_a": a, "method_b": b, "test": test, "power": k / reps,
                         "reps": reps})
    if bar is not None:
        bar.close()
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
                source: str = "", progress: bool = False) -> dict[str, Any]:
    """Run :func:`power_curve` and write ``power.csv``, ``power_needed.csv``, ``power.md``, ``power.png``."""
    from camo_base.atomic import atomic_path, write_text

    if not 0 < target < 1:
        raise CamoError("--target must be in (0, 1)")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CamoError(f"--out {out} exists and is not a folder")
    curve = power_curve(cells, participants, reps, alpha, seed, progress)
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


def write_predicted_power(stim_dir: str | Path, reps: int = 200, seed: int = 0, progress: bool = False):
    """The power curve of a stimulus set's predictions into ``STIMULI_DIR/predicted_power/`` (the report embeds
    it); None when the set has fewer than two methods."""
    cells = cells_from_predicted([stim_dir])
    if cells["method"].nunique() < 2:
        return None
    return write_power(cells, Path(stim_dir) / "predicted_power", reps=reps, seed=seed, progress=progress,
                       source="predicted by the simulated observer on this stimulus set")
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
