"""Analysis of the click-to-find study: Table I of the paper and more (``camo study report``).

Definitions (formal trials only; practice trials are stored but never analysed):

* **found**: the click hit the object's mask and came within the time limit.
  A click off the object (*miss*) and a *timeout* both count as **not found**.
* **confusion rate** of a method: share of its formal trials not found, with a
  Wilson score 95% CI (trials taken as independent) and a participant-level
  (cluster) percentile bootstrap 95% CI (participants resampled with
  replacement, seeded).
* **search time**, two variants:
  ``mean/median_time_found_s`` over **correct finds only** (as in Table I: the time
  it took to find the object when it was found), and ``mean/median_time_all_s`` over
  **all** formal trials, with timeouts at the time limit and misses at their click
  time (time spent on the trial).
* **time-to-find** (Kaplan-Meier, lifelines): event = found at its reaction time;
  timeouts are censored at the limit; misses are censored at the limit as well by
  default (``miss_censor="limit"``: within the window the object was not found, so
  ``1 - S(limit)`` equals the found share) or at their click time
  (``miss_censor="click"``: the search stopped there). ``km_median_s`` is ``inf``
  when fewer than half of the trials were found.
* **pairwise tests** between methods: two-proportion z-test (pooled, no continuity
  correction) and Fisher's exact test on the not-found counts, log-rank test on
  time-to-find; each family Holm-corrected over the pairs. These tests treat trials
  as independent; the bootstrap CI is the one that respects participant clustering.

By default only participants who completed the study are analysed
(``include_incomplete=True`` adds the formal trials of the others).

Conditions: every row of Table I is a condition (:mod:`optimizer.assets.conditions`: the run's method and
its ablations), keyed by its id (``condition``, e.g. ``ours-without-inpainting``) and shown with its label
(``label``, e.g. ``w/o Inpainting``), both stored with every trial when it was assigned -- the same id and
label as in the stimuli manifest and the evaluation report's Table II.

Trial clock: every time in Table I is the **server's** (``server_rt_ms``: from the arrival of the trial's
first start request to the arrival of the answer; one network round trip more than the page saw). The
page's own ``rt_ms`` is kept in ``trials.csv`` (``page_rt_s``) but decides nothing: a page claiming more
than the server measured is refused when the answer arrives, one claiming less by more than
``CLOCK_TOLERANCE_MS`` is flagged ``clock_mismatch`` (counted in the report). A click that arrived after the
limit (``late``) is stored as a timeout; an answer faster than ``RT_FLOOR_MS`` on the server's clock
(``too_fast``) is stored but **excluded** from Table I (the report says how many). ``starts > 1`` marks a
trial whose page was reloaded (its time counts from the first showing).

Location baselines (``stimuli_dir`` given): for the analysed formal trials, the hit rate a
participant would get by clicking the image centre (``centre_click``) and by clicking where the
object was in their own last practice image (``last_practice``, same relative position). They
show location bias and practice leakage next to Table I; with objects spread over the frame they
are close to the object's area share.
"""

from __future__ import annotations

import math
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from camo_base.atomic import atomic_path, write_text
from camo_base.errors import CamoError, SettingError
from camo_base.tables import write_parquet

Z95 = 1.959963984540054


# ---------------------------------------------------------------------------
# statistics
# ---------------------------------------------------------------------------


def wilson_ci(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for ``k`` successes out of ``n`` (``(nan, nan)`` when ``n == 0``)."""
    if n <= 0:
        return (math.nan, math.nan)
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def holm(pvalues) -> np.ndarray:
    """Holm-Bonferroni adjusted p-values, in the input order (NaN stays NaN and is not counted)."""
    p = np.asarray(pvalues, dtype=float)
    out = np.full_like(p, np.nan)
    ok = np.flatnonzero(~np.isnan(p))
    m = len(ok)
    if m == 0:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out


def two_proportion_z(k1: int, n1: int, k2: int, n2: int) -> tuple[float, float]:
    """Pooled two-proportion z-test (two-sided): ``(z, p)``; ``(0, 1)`` when the pooled variance is 0."""
    from scipy.stats import norm

    if n1 <= 0 or n2 <= 0:
        return (math.nan, math.nan)
    pooled = (k1 + k2) / (n1 + n2)
    se = math.sqrt(pooled * (1 - pooled) * (1 / n1 + 1 / n2))
    if se == 0:
        return (0.0, 1.0)
    z = (k1 / n1 - k2 / n2) / se
    return (z, float(2 * norm.sf(abs(z))))


def bootstrap_confusion(
    formal: pd.DataFrame, methods: list[str], n_boot: int = 2000, seed: int = 0, conf: float = 0.95,
    by: str = "condition",
) -> dict[str, tuple[float, float]]:
    """Participant-level percentile bootstrap CI of each condition's confusion rate (``methods``: values of
    column ``by``).

    Each replicate draws participants with replacement (multinomial weights) and
    recomputes ``sum(not found) / sum(trials)`` per condition over the drawn participants.
    """
    parts = sorted(formal["participant"].unique())
    if not parts or n_boot <= 0:
        return {m: (math.nan, math.nan) for m in methods}
    pidx = {p: i for i, p in enumerate(parts)}
    midx = {m: j for j, m in enumerate(methods)}
    n = np.zeros((len(parts), len(methods)))
    k = np.zeros((len(parts), len(methods)))
    for (p, m), g in formal.groupby(["participant", by]):
        n[pidx[p], midx[m]] = len(g)
        k[pidx[p], midx[m]] = int((~g["found"]).sum())
    rng = np.random.default_rng(seed)
    w = rng.multinomial(len(parts), np.full(len(parts), 1.0 / len(parts)), size=n_boot).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        rates = (w @ k) / (w @ n)
    alpha = (1 - conf) / 2
    out = {}
    for m, j in midx.items():
        col = rates[:, j]
        col = col[~np.isnan(col)]
        out[m] = (
            (float(np.quantile(col, alpha)), float(np.quantile(col, 1 - alpha))) if len(col) else (math.nan, math.nan)
        )
    return out


# ---------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------


def _engine(db):
    from sqlalchemy.engine import Engine

    from study_site.db import make_engine

    if isinstance(db, Engine):
        return db
    return make_engine(resolve_db_url(db, must_exist=True))


def resolve_db_url(db: str, must_exist: bool = False) -> str:
    """A SQLAlchemy URL from ``db``: a URL, or a path taken as a SQLite file."""
    db = str(db)
    if "://" not in db:
        db = f"sqlite:///{Path(db).resolve()}"
    if must_exist and db.startswith("sqlite:///"):
        path = Path(db[len("sqlite:///") :])
        if not path.is_file():
            raise CamoError(f"{path}: no such database file")
    return db


def stored_setting(db, key: str, default: str | None = None) -> str | None:
    """A value of the study database's ``settings`` table (``default`` when absent)."""
    from sqlalchemy import select

    from study_site.db import Setting

    with _engine(db).connect() as c:
        v = c.execute(select(Setting.value).where(Setting.key == key)).scalar()
    return default if v is None else v


def load_tables(db) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(trials, participants)`` DataFrames from a study database (URL, path or Engine).

    ``trials``: every stored trial (practice included, ``practice`` flag) with derived
    ``rt_s`` (the server's clock), ``page_rt_s`` (the page's claim), ``found``, ``time_on_trial_s`` and the
    participant's ``completed`` flag.
    ``participants``: one row per participant (HMAC id only) with trial counts.
    """
    from sqlalchemy import inspect, select

    from study_site.db import Participant, Trial

    engine = _engine(db)
    try:
        tables = set(inspect(engine).get_table_names())
    except Exception as exc:  # noqa: BLE001 - any driver error means we cannot read it
        raise CamoError(f"cannot read the database: {exc}") from None
    if not {"participants", "trials"} <= tables:
        raise CamoError("the database holds no study tables (participants, trials)")
    pcols = [c.name for c in Participant.__table__.columns if c.name != "token"]
    tcols = [c.name for c in Trial.__table__.columns]
    with engine.connect() as c:
        prows = c.execute(select(*[Participant.__table__.c[n] for n in pcols])).all()
        trows = c.execute(select(Trial.__table__).order_by(Trial.participant_id, Trial.trial_index)).all()
    participants = pd.DataFrame.from_records([tuple(r) for r in prows], columns=pcols).rename(
        columns={"id": "participant"}
    )
    trials = pd.DataFrame.from_records([tuple(r) for r in trows], columns=tcols).rename(
        columns={"participant_id": "participant"}
    )
    trials = trials.drop(columns=["id"])
    participants["completed"] = participants["completed_at"].notna()
    for col in ("hit", "timed_out", "practice", "late", "too_fast", "clock_mismatch"):
        trials[col] = trials[col].fillna(False).astype(bool)
    trials["page_rt_s"] = trials["rt_ms"].astype(float) / 1000.0
    # the server's clock decides; a row without it (none is written so) would fall back to the page's
    trials["rt_s"] = trials["server_rt_ms"].astype(float).fillna(trials["rt_ms"].astype(float)) / 1000.0
    # lateness was decided on the server when the answer arrived (limit + DEADLINE_GRACE_S): late is a timeout
    trials["found"] = trials["hit"] & ~trials["timed_out"]
    trials["time_on_trial_s"] = np.where(trials["timed_out"], trials["time_limit_s"], trials["rt_s"])
    trials = trials.merge(participants[["participant", "completed"]], on="participant", how="left")
    counts = trials.groupby("participant").agg(
        n_trials=("trial_index", "size"),
        n_formal=("practice", lambda s: int((~s).sum())),
    )
    found = trials[~trials["practice"]].groupby("participant")["found"].sum().rename("n_formal_found")
    participants = participants.merge(counts, on="participant", how="left").merge(
        found, on="participant", how="left"
    )
    for col in ("n_trials", "n_formal", "n_formal_found"):
        participants[col] = pd.to_numeric(participants[col], errors="coerce").fillna(0).astype(int)
    return trials, participants


def formal_trials(trials: pd.DataFrame, include_incomplete: bool = False, keep_too_fast: bool = False) -> pd.DataFrame:
    """Formal trials to analyse: completed participants (unless ``include_incomplete``), too-fast answers
    dropped (unless ``keep_too_fast``)."""
    f = trials[~trials["practice"]]
    if not include_incomplete:
        f = f[f["completed"]]
    if not keep_too_fast and "too_fast" in f:
        f = f[~f["too_fast"].astype(bool)]
    return f.copy()


def location_baselines(trials: pd.DataFrame, formal: pd.DataFrame, stimuli_dir) -> pd.DataFrame:
    """Per condition (and ``all``): hit rate of a click at the image centre and at the participant's last
    practice object's position (centroid, as a fraction of the image), over the trials in ``formal``;
    next to the formal stimuli's mean object area share."""
    from study_site.stimuli import StimulusSet

    ss = StimulusSet(stimuli_dir)
    last_practice: dict[Any, tuple[float, float]] = {}
    prac = trials[trials["practice"]].sort_values(["participant", "trial_index"])
    for pid, g in prac.groupby("participant"):
        st = ss.by_id.get(g.iloc[-1]["stimulus_id"])
        if st is not None and st.centroid_x is not None:
            last_practice[pid] = (st.centroid_x, st.centroid_y)
        elif st is not None:  # a version-1 manifest: measure the mask
            ys, xs = np.nonzero(ss.mask(st))
            last_practice[pid] = ((xs.mean() + 0.5) / st.width, (ys.mean() + 0.5) / st.height)
    rows = []
    for r in formal.itertuples():
        st = ss.by_id.get(r.stimulus_id)
        if st is None:
            continue
        centre = ss.hit(st, st.width // 2, st.height // 2)
        lp = last_practice.get(r.participant)
        lp_hit = ss.hit(st, min(st.width - 1, int(lp[0] * st.width)), min(st.height - 1, int(lp[1] * st.height))) \
            if lp else math.nan
        share = float(ss.mask(st).mean())
        rows.append({"condition": r.condition, "label": r.label, "centre": centre, "last_practice": lp_hit,
                     "share": share})
    df = pd.DataFrame(rows, columns=["condition", "label", "centre", "last_practice", "share"])
    out = []
    order = conditions_in_order(df) if len(df) else []
    for m, g in [("all", df)] + [(c, df[df["condition"] == c]) for c in order]:
        lp = g["last_practice"].dropna()
        out.append({
            "condition": m,
            "label": "All" if m == "all" else g["label"].iloc[0],
            "n_trials": len(g),
            "centre_click_hit_rate": float(g["centre"].mean()) if len(g) else math.nan,
            "last_practice_hit_rate": float(lp.astype(float).mean()) if len(lp) else math.nan,
            "mean_area_share": float(g["share"].mean()) if len(g) else math.nan,
        })
    return pd.DataFrame(out)


# ---------------------------------------------------------------------------
# Table I, Kaplan-Meier, pairwise tests
# ---------------------------------------------------------------------------


def conditions_in_order(formal: pd.DataFrame) -> list[str]:
    """The condition ids of ``formal`` in the paper's table order (:attr:`Condition.order`)."""
    from optimizer.assets.conditions import parse_id

    return sorted(formal["condition"].unique(), key=lambda c: (parse_id(c).order, c))


def durations(formal: pd.DataFrame, miss_censor: str = "limit") -> tuple[np.ndarray, np.ndarray]:
    """Time-to-find ``(duration_s, event)``: events at the reaction time of finds; censored otherwise."""
    if miss_censor not in ("limit", "click"):
        raise ValueError("miss_censor must be 'limit' or 'click'")
    found = formal["found"].to_numpy(bool)
    limit = formal["time_limit_s"].to_numpy(float)
    rt = formal["rt_s"].to_numpy(float)
    timed_out = formal["timed_out"].to_numpy(bool)
    if miss_censor == "limit":
        d = np.where(found, rt, limit)
    else:
        d = np.where(found | ~timed_out, np.minimum(rt, limit), limit)
    return d, found


def table_i(
    formal: pd.DataFrame, n_boot: int = 2000, seed: int = 0, miss_censor: str = "limit"
) -> pd.DataFrame:
    """Table I per condition, in the paper's order (see the module docstring for every definition)."""
    from lifelines import KaplanMeierFitter

    methods = conditions_in_order(formal)
    boot = bootstrap_confusion(formal, methods, n_boot=n_boot, seed=seed)
    rows = []
    for m in methods:
        g = formal[formal["condition"] == m]
        n = len(g)
        k = int((~g["found"]).sum())
        lo, hi = wilson_ci(k, n)
        ft = g.loc[g["found"], "rt_s"]
        d, e = durations(g, miss_censor)
        kmf = KaplanMeierFitter().fit(d, e)
        rows.append(
            {
                "condition": m,
                "label": str(g["label"].iloc[0]),
                "n_trials": n,
                "n_participants": int(g["participant"].nunique()),
                "n_found": n - k,
                "n_missed": int((~g["found"] & ~g["timed_out"]).sum()),
                "n_timeout": int(g["timed_out"].sum()),
                "confusion_rate": k / n if n else math.nan,
                "confusion_wilson_lo": lo,
                "confusion_wilson_hi": hi,
                "confusion_boot_lo": boot[m][0],
                "confusion_boot_hi": boot[m][1],
                "mean_time_found_s": float(ft.mean()) if len(ft) else math.nan,
                "median_time_found_s": float(ft.median()) if len(ft) else math.nan,
                "mean_time_all_s": float(g["time_on_trial_s"].mean()),
                "median_time_all_s": float(g["time_on_trial_s"].median()),
                "km_median_s": float(kmf.median_survival_time_),
            }
        )
    return pd.DataFrame(rows)


def pairwise_tests(formal: pd.DataFrame, miss_censor: str = "limit") -> pd.DataFrame:
    """Every pair of conditions: z-test and Fisher on not-found counts, log-rank on time-to-find; Holm per family."""
    from lifelines.statistics import logrank_test
    from scipy.stats import fisher_exact

    methods = conditions_in_order(formal)
    labels = formal.drop_duplicates("condition").set_index("condition")["label"]
    rows = []
    for a, b in combinations(methods, 2):
        ga, gb = formal[formal["condition"] == a], formal[formal["condition"] == b]
        na, nb = len(ga), len(gb)
        ka, kb = int((~ga["found"]).sum()), int((~gb["found"]).sum())
        z, pz = two_proportion_z(ka, na, kb, nb)
        odds, pf = fisher_exact([[ka, na - ka], [kb, nb - kb]])
        da, ea = durations(ga, miss_censor)
        db, eb = durations(gb, miss_censor)
        if ea.any() or eb.any():
            lr = logrank_test(da, db, event_observed_A=ea, event_observed_B=eb)
            chi2, plr = float(lr.test_statistic), float(lr.p_value)
        else:
            chi2, plr = math.nan, math.nan
        rows.append(
            {
                "condition_a": a,
                "condition_b": b,
                "label_a": labels[a],
                "label_b": labels[b],
                "n_a": na,
                "n_b": nb,
                "confusion_a": ka / na if na else math.nan,
                "confusion_b": kb / nb if nb else math.nan,
                "diff": (ka / na - kb / nb) if na and nb else math.nan,
                "z": z,
                "p_z": pz,
                "fisher_odds_ratio": float(odds),
                "p_fisher": float(pf),
                "logrank_chi2": chi2,
                "p_logrank": plr,
            }
        )
    df = pd.DataFrame(
        rows,
        columns=[
            "condition_a", "condition_b", "label_a", "label_b", "n_a", "n_b", "confusion_a", "confusion_b", "diff", "z", "p_z",
            "fisher_odds_ratio", "p_fisher", "logrank_chi2", "p_logrank",
        ],
    )
    for col in ("p_z", "p_fisher", "p_logrank"):
        df[col + "_holm"] = holm(df[col].to_numpy(float)) if len(df) else []
    return df


def plot_km(formal: pd.DataFrame, path: str | Path, miss_censor: str = "limit") -> None:
    """Kaplan-Meier curves 'share still hidden' vs seconds per condition (95% CI bands) as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from lifelines import KaplanMeierFitter

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=150)
    limit = float(formal["time_limit_s"].max())
    for m in conditions_in_order(formal):
        g = formal[formal["condition"] == m]
        d, e = durations(g, miss_censor)
        KaplanMeierFitter(label=f"{g['label'].iloc[0]} (n={len(g)})").fit(d, e).plot_survival_function(
            ax=ax, ci_show=True)
    ax.set_xlim(0, max(limit, float(formal["rt_s"].max())))
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("time since image onset (s, server clock)")
    ax.set_ylabel("share of trials with the object not yet found")
    ax.set_title("Time to find (Kaplan-Meier; misses and timeouts censored)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper right", framealpha=0.9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


# ---------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------


def _pct(x: float) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.2f}%"


def _sec(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if math.isinf(x):
        return "> limit"
    return f"{x:.2f}"


def table_markdown(table: pd.DataFrame, participants: pd.DataFrame, formal: pd.DataFrame, meta: dict) -> str:
    lines = [
        "# Perceptual study: Table I",
        "",
        f"Participants analysed: {formal['participant'].nunique()} "
        f"({'all with formal trials' if meta['include_incomplete'] else 'completed only'}); "
        f"formal trials: {len(formal)}; time limit: {', '.join(f'{t:g}' for t in sorted(formal['time_limit_s'].unique()))} s.",
        "",
        "| Condition | Id | Trials | Conf. rate | Wilson 95% CI | Bootstrap 95% CI | Avg. time (s) | Med. time (s) "
        "| Avg. time, all (s) | Med. time, all (s) | KM median (s) |",
        "|---|---|---:|---:|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in table.itertuples():
        lines.append(
            f"| {r.label} | `{r.condition}` | {r.n_trials} | {_pct(r.confusion_rate)} | "
            f"{_pct(r.confusion_wilson_lo)} - {_pct(r.confusion_wilson_hi)} | "
            f"{_pct(r.confusion_boot_lo)} - {_pct(r.confusion_boot_hi)} | "
            f"{_sec(r.mean_time_found_s)} | {_sec(r.median_time_found_s)} | "
            f"{_sec(r.mean_time_all_s)} | {_sec(r.median_time_all_s)} | {_sec(r.km_median_s)} |"
        )
    lines += [
        "",
        "Definitions:",
        "",
        "- *Conf. rate*: share of formal trials where the object was not found (a click off the object or a "
        "timeout). Wilson CI treats trials as independent; the bootstrap CI resamples participants "
        f"({meta['n_boot']} replicates, seed {meta['seed']}).",
        "- *Times*: the **server's clock** (`server_rt_ms`): from the arrival of the trial's start request to the "
        "arrival of the answer, so one network round trip more than the participant's screen showed "
        f"({meta.get('clock_note', 'page clock not compared')}). The page's own time (`rt_ms`) decides nothing; a page "
        f"claiming more time than the server measured was refused, {meta.get('n_clock_mismatch', 0)} analysed "
        f"trial(s) whose page claimed more than {meta.get('clock_tolerance_ms', 1000):g} ms less than the server "
        "measured are flagged `clock_mismatch` and counted at the server's time.",
        "- *Avg./Med. time*: over correct finds only (time from image onset to the correct click).",
        "- *Avg./Med. time, all*: over all formal trials, timeouts counted at the time limit and misses at their "
        "click time.",
        f"- *KM median*: Kaplan-Meier median time-to-find, misses censored at the "
        f"{'time limit' if meta['miss_censor'] == 'limit' else 'click time'}, timeouts at the limit "
        "('> limit': fewer than half were found). Curves: km.png. Pairwise tests (Holm-corrected): pairwise.csv.",
        "- Practice trials are excluded.",
    ]
    n_fast = meta.get("n_too_fast", 0)
    lines += [
        f"- Excluded: {n_fast} formal trial(s) answered faster than the plausible floor on the server's clock "
        "(`too_fast`). "
        f"Clicks after the deadline are counted as timeouts ({meta.get('n_late', 0)} `late`); "
        f"{meta.get('n_reloaded', 0)} trial(s) were shown again after a reload (the deadline held).",
    ]
    base = meta.get("baselines")
    if base is not None and len(base):
        lines += [
            "",
            "## Location baselines",
            "",
            "Hit rate of a participant who clicks the image centre, or where the object was in their last practice "
            "image, on the same formal trials; mean share of the image the object covers.",
            "",
            "| Condition | Trials | Centre click | Last-practice location | Object area share |",
            "|---|---:|---:|---:|---:|",
        ]
        for r in base.itertuples():
            lines.append(
                f"| {r.label} | {r.n_trials} | {_pct(r.centre_click_hit_rate)} | {_pct(r.last_practice_hit_rate)} | "
                f"{_pct(r.mean_area_share)} |"
            )
    ages = participants.loc[participants["participant"].isin(formal["participant"].unique()), "age_bracket"]
    if len(ages):
        labels = {"prefer_not": "prefer not to say"}
        counts = ages.fillna("not answered").replace(labels).value_counts()
        lines += ["", "## Age brackets", "", "| Age | n | % |", "|---|---:|---:|"]
        for age, n in counts.sort_index().items():
            lines.append(f"| {age} | {n} | {100 * n / len(ages):.1f}% |")
    return "\n".join(lines) + "\n"


def clock_note(formal: pd.DataFrame) -> str:
    """How far the page's clock was below the server's on these trials (median and 95th percentile, ms)."""
    d = (formal["rt_s"] - formal["page_rt_s"]).dropna() * 1000.0
    if d.empty:
        return "page clock not compared"
    return (f"server minus page: median {d.median():.0f} ms, 95th percentile {d.quantile(0.95):.0f} ms over "
            f"{len(d)} trials")


def write_report(
    db,
    out_dir: str | Path,
    n_boot: int = 2000,
    seed: int = 0,
    include_incomplete: bool = False,
    miss_censor: str = "limit",
    stimuli_dir=None,
) -> dict[str, Any]:
    """Write table_i.md/.csv, km.png, pairwise.csv, trials.csv/.parquet, participants.csv/.parquet
    (and baselines.csv when ``stimuli_dir`` is given)."""
    trials, participants = load_tables(db)
    all_formal = formal_trials(trials, include_incomplete, keep_too_fast=True)
    formal = formal_trials(trials, include_incomplete)
    if formal.empty:
        raise SettingError(
            f"no formal trials to analyse ({len(participants)} participants, "
            f"{int(participants['completed'].sum())} completed"
            + ("" if include_incomplete else "; {0} adds unfinished sessions")
            + ")", "include_incomplete"
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = table_i(formal, n_boot=n_boot, seed=seed, miss_censor=miss_censor)
    pairs = pairwise_tests(formal, miss_censor=miss_censor)
    baselines = location_baselines(trials, formal, stimuli_dir) if stimuli_dir is not None else None
    meta = {"n_boot": n_boot, "seed": seed, "include_incomplete": include_incomplete, "miss_censor": miss_censor,
            "n_too_fast": int(all_formal["too_fast"].astype(bool).sum()),
            "n_late": int(formal["late"].astype(bool).sum()),
            "n_reloaded": int((formal["starts"].fillna(1) > 1).sum()), "baselines": baselines,
            "n_clock_mismatch": int(formal["clock_mismatch"].sum()),
            "clock_tolerance_ms": float(stored_setting(db, "clock_tolerance_ms", "1000")),
            "clock_note": clock_note(formal)}
    write_text(out / "table_i.md", table_markdown(table, participants, formal, meta))
    if baselines is not None:
        with atomic_path(out / "baselines.csv") as tmp:
            baselines.to_csv(tmp, index=False)
    for name, df in (("table_i", table), ("pairwise", pairs), ("trials", trials), ("participants", participants)):
        with atomic_path(out / f"{name}.csv") as tmp:
            df.to_csv(tmp, index=False)
    for name, df in (("trials", trials), ("participants", participants)):
        with atomic_path(out / f"{name}.parquet") as tmp:
            write_parquet(df, tmp)
    plot_km(formal, out / "km.png", miss_censor=miss_censor)
    return {"table": table, "pairwise": pairs, "trials": trials, "participants": participants, "baselines": baselines}
