"""The tables and pictures of docs/results/observer.md, from stimulus sets with the observer's predictions.

For each pair (evaluation directory, stimulus set built from it): the predicted Table I per method on the formal
stimuli (what ``camo report --stimuli`` shows), next to the paper's human Table I, the human-range check for the
plainly visible baselines (Mean, Random, Transparent), Kendall's tau of the observer's method order against each
metric per scene, and a picture of the stimuli with the simulated clicks (green on the object, red off it; the
object's outline in magenta) next to the observer's priority and verification maps.

Usage: python bench/observer_results.py --pairs EVAL_DIR:STIMULI_DIR ... [--pictures OUT.jpg] [--views 0,1]
       [--bootstrap N]   (tau's sampling error: a bootstrap over each stimulus's simulated trials)
       [--compare LABEL=STIM_DIR,STIM_DIR ...]   (observer variants side by side: confusion / mean time of finds)
       [--methods mean,transparent] [--observer KEY=VALUE,...]   (the picture's rows and observer settings)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def tables(pairs: list[tuple[Path, Path]], n_boot: int = 0) -> str:
    from evaluation.observer import HUMAN_VISIBLE, PAPER_TABLE_I, predicted_table
    from evaluation.report import load_metrics, load_simulated, method_label, observer_agreement

    out = []
    visible = {"Mean [6]", "Random [6]", "Transparent"}
    for ev, st in pairs:
        df = load_metrics([ev])
        df["label"] = [method_label(m, a) for m, a in zip(df["method"], df["ablation"])]
        views, trials, _ = load_simulated([st])
        t = predicted_table(views, by=("label",), trials=trials).set_index("label")
        scene = ", ".join(sorted(views["scene"].unique()))
        out += [f"### {scene}", "",
                "| Method | stimuli | pred. confusion | P(miss) | P(timeout) | pred. avg. / med. time of finds (s) "
                "| human confusion (paper) | human avg. / med. (s) | visible: in human range? |",
                "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
        for lab, r in t.iterrows():
            hum = PAPER_TABLE_I.get(lab)
            ok = ""
            if lab in visible:
                lo, hi = HUMAN_VISIBLE["mean_time_s"]
                ok = "yes" if (r.confusion_rate <= HUMAN_VISIBLE["max_confusion"]
                               and lo <= r.mean_time_found_s <= hi) else "no"
            out.append(f"| {lab} | {int(r.n_views)} | {100 * r.confusion_rate:.1f} % | {100 * r.p_miss:.1f} % | "
                       f"{100 * r.p_timeout:.1f} % | {r.mean_time_found_s:.2f} / {r.median_time_found_s:.2f} | "
                       + (f"{100 * hum[0]:.1f} % | {hum[1]:.2f} / {hum[2]:.2f}" if hum else "— | —") + f" | {ok} |")
        taus, _ = observer_agreement(df, views)
        if taus:
            out += ["", "Kendall's tau, observer order (predicted confusion, then mean time of finds) vs metric order "
                    "(crop): " + ", ".join(f"{x['metric']} {x['tau']:+.2f}" for x in taus) + "."]
        if taus and n_boot:
            unc = tau_uncertainty(df, views, trials, n_boot=n_boot)
            if unc:
                out += ["", f"Sampling error ({n_boot} bootstrap resamples of each stimulus's simulated trials; "
                        f"observer's pairwise orders settled in >= 95 % of them: {unc[0]['settled']} of "
                        f"{unc[0]['pairs']}): " + ", ".join(
                            f"{x['metric']} {x['tau']:+.2f} [{x['lo']:+.2f}, {x['hi']:+.2f}]"
                            + (" (sign not settled)" if tau_sign(x) == "?" else "") for x in unc) + "."]
        out.append("")
    return "\n".join(out)


def tau_uncertainty(df, views, trials, n_boot: int = 1000, seed: int = 0, level: float = 0.95) -> list[dict]:
    """The simulation's sampling error on Kendall's tau of :func:`evaluation.report.observer_agreement`.

    The observer's order rests on a finite number of simulated trials per stimulus (``trials``: rows of
    ``predicted_trials.parquet``, columns ``id``, ``found``, ``rt_s``); a percentile bootstrap redraws each
    stimulus's trials with replacement ``n_boot`` times (Efron & Tibshirani 1993, ch. 13), recomputes its
    p found and mean time of finds, the observer's order (:func:`evaluation.report.observer_rank`) and tau
    against each metric (whose values are computed, not sampled, so fixed). Per scene and metric:
    ``{scene, metric, tau, lo, hi, settled, pairs}`` -- the point tau, its ``level`` percentile interval, and how
    many of the observer's pairwise orders (above, below or tied) hold the same way in at least ``level`` of the
    resamples.
    A pair that does not is a tie within sampling error, so a tau whose interval holds both signs, or that rests
    on an unsettled pair, has no defined sign on those trials."""
    from itertools import combinations

    from evaluation.report import AGREEMENT_METRICS, METRICS, _kendall, observer_rank

    rng = np.random.default_rng(seed)
    crop = df.loc[df["region"] == "crop"]
    metrics = [m for m in AGREEMENT_METRICS if m in crop.columns and crop[m].notna().any()]
    out = []
    for scene in sorted(views["scene"].unique()):
        sv = views.loc[views["scene"] == scene].reset_index(drop=True)
        # per stimulus: (n_boot, n_trials) resampled found flags and times
        p_b, t_b = np.empty((len(sv), n_boot)), np.empty((len(sv), n_boot))
        for i, sid in enumerate(sv["id"]):
            g = trials.loc[trials["id"] == sid]
            found, rt = g["found"].to_numpy(bool), g["rt_s"].to_numpy(float)
            idx = rng.integers(0, len(g), size=(n_boot, len(g)))
            f = found[idx]
            p_b[i] = f.mean(axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                t_b[i] = np.where(f, rt[idx], 0.0).sum(axis=1) / f.sum(axis=1)
        ranks = []
        for b in range(n_boot):
            bv = sv.assign(p_found=p_b[:, b], mean_time_found_s=t_b[:, b])
            ranks.append(observer_rank(bv))
        point = observer_rank(sv)
        pm = crop.loc[crop["scene"] == scene].groupby(["label", "run"])[metrics].mean().groupby("label").mean()
        labels = [lab for lab in point.index if lab in pm.index]
        if len(labels) < 2:
            continue
        rk = np.array([[float(r[lab]) for lab in labels] for r in ranks])  # (n_boot, labels)
        settled = sum(max((rk[:, i] > rk[:, j]).mean(), (rk[:, i] < rk[:, j]).mean(),
                          (rk[:, i] == rk[:, j]).mean()) >= level
                      for i, j in combinations(range(len(labels)), 2))
        pairs = len(labels) * (len(labels) - 1) // 2
        for m in metrics:
            good = [-METRICS[m].badness(float(pm.loc[lab, m])) if m in METRICS else float(pm.loc[lab, m])
                    for lab in labels]
            taus = np.array([_kendall(list(r), good) for r in rk])
            lo, hi = np.nanquantile(taus, [(1 - level) / 2, (1 + level) / 2])
            out.append({"scene": scene, "metric": m, "tau": _kendall([float(point[lab]) for lab in labels], good),
                        "lo": float(lo), "hi": float(hi), "settled": int(settled), "pairs": pairs})
    return out


def tau_sign(row: dict) -> str:
    """``"+"``, ``"-"`` or ``"0"`` where the interval of :func:`tau_uncertainty` lies above 0, below 0 or at 0;
    ``"?"`` where it holds 0 and another value: the sign is not settled by the simulated trials (undefined within
    their sampling error)."""
    lo, hi = row["lo"], row["hi"]
    if lo > 0:
        return "+"
    if hi < 0:
        return "-"
    if lo == hi == 0:
        return "0"
    return "?"


def compare(variants: list[tuple[str, list[Path]]]) -> str:
    """One row per scene x method (the visible baselines, then Ours), one column per observer variant: predicted
    confusion / mean time of finds, ``*`` where a visible baseline is in the human range. ``variants``: (label,
    stimulus sets predicted with that variant's settings: ``camo study predict DIR --observer ...``)."""
    from evaluation.observer import HUMAN_VISIBLE, PAPER_TABLE_I, predicted_table
    from evaluation.report import load_simulated

    from scipy.stats import spearmanr

    visible = ("Mean [6]", "Random [6]", "Transparent")
    cells, inrange, n_visible, ev = {}, {}, {}, {}
    for name, dirs in variants:
        views, trials, _ = load_simulated(dirs)
        f = views[views["p_found"] > 0]
        near = f["object_evidence"] < 10.0
        ev[name] = (f"rho {spearmanr(f['object_evidence'], f['mean_time_found_s']).statistic:+.2f}; "
                    f"{f.loc[near, 'mean_time_found_s'].mean():.2f} s ({int(near.sum())}) vs "
                    f"{f.loc[~near, 'mean_time_found_s'].mean():.2f} s ({int((~near).sum())})")
        t = predicted_table(views, by=("scene", "label"), trials=trials).set_index(["scene", "label"])
        for (scene, lab), r in t.iterrows():
            if lab not in visible + ("Ours",):
                continue
            lo, hi = HUMAN_VISIBLE["mean_time_s"]
            ok = (lab in visible and r.confusion_rate <= HUMAN_VISIBLE["max_confusion"]
                  and lo <= r.mean_time_found_s <= hi)
            inrange[name] = inrange.get(name, 0) + ok
            n_visible[name] = n_visible.get(name, 0) + (lab in visible)
            cells.setdefault((lab != "Ours", scene, lab), {})[name] = (
                f"{100 * r.confusion_rate:.1f} % / {r.mean_time_found_s:.2f} s" + (" *" if ok else ""))
    names = [n for n, _ in variants]
    out = ["| cell | " + " | ".join(names) + " | humans (paper) |", "|---" * (len(names) + 2) + "|"]
    for key in sorted(cells, key=lambda k: (not k[0], k[1], k[2])):
        _, scene, lab = key
        hum = PAPER_TABLE_I.get(lab)
        out.append(f"| {scene} {lab} | " + " | ".join(cells[key].get(n, "—") for n in names) + " | "
                   + (f"{100 * hum[0]:.1f} % / {hum[1]:.2f} s" if hum else "—") + " |")
    out.append("| **visible cells in the human range** | "
               + " | ".join(f"**{inrange.get(n, 0)} of {n_visible.get(n, 0)}**" for n in names) + " | |")
    out.append("| evidence vs time: Spearman's rho of the object's evidence and the mean time of finds over the "
               "stimuli found at all; mean time of finds with evidence < 10 (n) vs >= 10 (n) | "
               + " | ".join(ev[n] for n in names) + " | |")
    return "\n".join(out)


def pictures(stim_dirs: list[Path], path: Path, views: set[str], n: int = 100, observer: str | None = None,
             methods: set[str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    from evaluation.observer import ObserverConfig, evidence_maps, make_cells, simulate_search
    from study_site.stimuli import background_path

    rows = []
    for d in stim_dirs:
        man = json.loads((d / "manifest.json").read_text())
        for s in sorted(man["stimuli"], key=lambda s: (s["method"], s.get("ablation", ""), s["view"])):
            if not s["practice"] and s["view"] in views and (methods is None or s["method"] in methods):
                rows.append((d, s))
    fig, axes = plt.subplots(len(rows), 3, figsize=(9, 3 * len(rows)), squeeze=False)
    for ax, (d, s) in zip(axes, rows):
        img = np.asarray(Image.open(d / "images" / f"{s['id']}.png").convert("RGB"))
        mask = np.asarray(Image.open(d / "masks" / f"{s['id']}.png").convert("L")) > 127
        from study_site.simulate import parse_observer

        cfg = parse_observer(observer) if observer else ObserverConfig()
        bgp = background_path(d, s["scene"], s["view"])
        bg = np.asarray(Image.open(bgp).convert("RGB")) if bgp.is_file() else None
        maps = evidence_maps(img, cfg, bg)
        res = simulate_search(img, n=n, seed=0, config=cfg, mask=mask, cells=make_cells(img, cfg, maps=maps))
        ax[0].imshow(img)
        ax[0].contour(mask, [0.5], colors="m", linewidths=0.7)
        hit, miss = res.clicked & res.found, res.clicked & ~res.found
        ax[0].scatter(res.click_x[hit], res.click_y[hit], c="lime", s=7)
        ax[0].scatter(res.click_x[miss], res.click_y[miss], c="red", s=7)
        lab = s["method"] + (f"+{s['ablation']}" if s.get("ablation") not in ("", "none", None) else "")
        ax[0].set_title(f"{s['scene']} {lab} view {s['view']}: found {res.found.mean():.0%}, miss {miss.mean():.0%}, "
                        f"timeout {res.timed_out.mean():.0%}", fontsize=7)
        ax[1].imshow(maps.guidance, cmap="magma")
        ax[1].set_title("priority G (object-sized, on the ground, + near shadows)", fontsize=7)
        ax[2].imshow(maps.verify, cmap="magma", vmin=-3, vmax=3 * cfg.criterion)
        ax[2].set_title(f"verification z vs the background (criterion {cfg.criterion:g})", fontsize=7)
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=80, pil_kwargs={"quality": 85})
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", nargs="+", required=True, metavar="EVAL_DIR:STIMULI_DIR")
    ap.add_argument("--pictures", metavar="OUT.jpg")
    ap.add_argument("--bootstrap", type=int, default=0, metavar="N",
                    help="tau's sampling error: N bootstrap resamples of each stimulus's simulated trials (0: off)")
    ap.add_argument("--views", default="0", help="stimulus views in the picture (comma list)")
    ap.add_argument("--methods", help="only these methods in the picture (comma list; default all)")
    ap.add_argument("--observer", metavar="KEY=VALUE,...", help="the picture's observer settings (default: the default)")
    ap.add_argument("--compare", nargs="+", metavar="LABEL=STIM_DIR,STIM_DIR,...",
                    help="observer variants side by side (each set predicted with that variant's --observer settings)")
    args = ap.parse_args()
    pairs = [tuple(Path(x) for x in p.split(":", 1)) for p in args.pairs]
    if args.bootstrap < 0:
        ap.error("--bootstrap must be >= 0")
    print(tables(pairs, n_boot=args.bootstrap))
    if args.compare:
        print(compare([(c.split("=", 1)[0], [Path(x) for x in c.split("=", 1)[1].split(",")]) for c in args.compare]))
    if args.pictures:
        pictures([st for _, st in pairs], Path(args.pictures), set(args.views.split(",")), observer=args.observer,
                 methods=set(args.methods.split(",")) if args.methods else None)


if __name__ == "__main__":
    main()
