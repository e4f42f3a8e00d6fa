"""The analysis notebooks (notebooks/*.ipynb) run top to bottom on small generated inputs, so they never rot.

Each notebook is executed with nbclient in a kernel of this interpreter (a kernelspec written to a temporary
JUPYTER_PATH), its inputs given through the environment variables of its parameter cell:

* table2_metrics.ipynb   CAMO_METRICS       a metrics table in the `camo evaluate` / `camo grid` format
* table1_study.ipynb     CAMO_STUDY_DB      a study database made with study_site.db (synthetic participants/trials)
                         CAMO_STUDY_REPORT  the output folder of study_site.analysis.write_report
* accuracy_vs_time.ipynb CAMO_TRADEOFF, CAMO_EVAL_TRADEOFF  bench tables in the format the bench scripts write

The numbers shown are checked against the library functions computed here. Notebooks in git carry no outputs.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from camo_base.tables import write_parquet

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
NAMES = ("table2_metrics.ipynb", "table1_study.ipynb", "accuracy_vs_time.ipynb")


@pytest.fixture(scope="module")
def kernel_env(tmp_path_factory):
    """A kernelspec for this interpreter in a temporary JUPYTER_PATH (never the user's kernels)."""
    share = tmp_path_factory.mktemp("jupyter")
    spec = share / "kernels" / "camo-test"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "camo test kernel", "language": "python"}))
    return share


def run_notebook(name: str, kernel_env: Path, cwd: Path, monkeypatch, **env: str):
    monkeypatch.setenv("JUPYTER_PATH", str(kernel_env))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    for k, v in env.items():
        monkeypatch.setenv(k, str(v))
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=180, kernel_name="camo-test",
                                     resources={"metadata": {"path": str(cwd)}})
    client.execute()
    return nb


def texts(nb) -> str:
    """Every text / markdown / html output of an executed notebook, joined."""
    out = []
    for c in nb.cells:
        for o in c.get("outputs", []):
            if o.get("output_type") == "stream":
                out.append(o.get("text", ""))
            for key in ("text/markdown", "text/plain", "text/html"):
                v = o.get("data", {}).get(key)
                if v:
                    out.append(v if isinstance(v, str) else "".join(v))
    return "\n".join(out)


def images(nb) -> int:
    return sum(1 for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {}))


def test_notebooks_are_stripped_and_parameterised():
    for name in NAMES:
        nb = nbformat.read(NOTEBOOKS / name, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert all(not c.outputs and c.execution_count is None for c in code), f"{name}: outputs not stripped"
        assert any("parameters" in c.metadata.get("tags", []) for c in code), f"{name}: no parameters cell"
    assert (NOTEBOOKS / "README.md").is_file()


# ------------------------------------------------------------------------------------------------------------
# Table II
# ------------------------------------------------------------------------------------------------------------


def tiny_metrics(path: Path) -> pd.DataFrame:
    """A metrics table in the exact `camo evaluate` schema plus the grid columns: 2 scenes x (3 baselines,
    Ours and 3 ablations) x 2 seeds x 2 views x 2 regions, with known values."""
    from evaluation.evaluate import COLUMNS, METRIC_COLUMNS

    rng = np.random.default_rng(0)
    conds = [("transparent", "none"), ("mean", "none"), ("random", "none"), ("ours", "none"), ("ours", "pose"),
             ("ours", "displacement"), ("ours", "bsdf")]
    rows = []
    for si, scene in enumerate(("gravel", "split:chair")):
        for ci, (method, abl) in enumerate(conds):
            for seed in (0, 1):
                run = f"{scene.replace(':', '_')}__{method}{'' if abl == 'none' else '-wo-' + abl}__s{seed}"
                for view in range(2):
                    for region in ("full", "crop"):
                        row = {c: "" for c in COLUMNS}
                        row.update(run=run, scene=scene, object="chair" if si else "utility_box", method=method,
                                   ablation=abl, view=view, seed=0, region=region, spp=8, width=32, height=32,
                                   jitter=0.25, camera_set="abc", region_y0=0, region_x0=0, region_height=32,
                                   region_width=32, mask_pixels=100, seconds_render=0.1, seconds_metrics=0.01)
                        for m in METRIC_COLUMNS:
                            row[m] = math.nan
                        base = 20 + 2 * ci + si + 0.1 * seed
                        row["psnr"] = base + rng.normal(0, 0.2)
                        row["ssim"] = min(0.99, 0.5 + 0.05 * ci + rng.normal(0, 0.01))
                        row["lpips_proxy"] = 0.5 - 0.04 * ci + rng.normal(0, 0.01)
                        row["cell"] = f"{si}{ci}{seed}"
                        row["run_seed"] = seed
                        rows.append(row)
    df = pd.DataFrame(rows)
    write_parquet(df, path)
    return df


def test_table2_notebook(tmp_path, kernel_env, monkeypatch):
    from evaluation.report import _fmt, load_metrics, summary

    tiny_metrics(tmp_path / "metrics.parquet")
    nb = run_notebook("table2_metrics.ipynb", kernel_env, tmp_path, monkeypatch,
                      CAMO_METRICS=tmp_path / "metrics.parquet")
    out = texts(nb)
    assert "Table II — object crop (GANmouflage protocol)" in out and "Table II — full frame" in out
    for label in ("Transparent", "Mean [6]", "Random [6]", "w/o Pose", "w/o Displacement", "w/o BSDF (Only Albedo)",
                  "Ours"):
        assert f"| {label} |" in out or f"| **{label}** |" in out, label
    # the numbers are those of evaluation.report.summary on the same table
    t = summary(load_metrics([tmp_path]), "crop")
    ours = t.loc["Ours"]
    assert f"{_fmt('psnr', ours['psnr'])} ± {_fmt('psnr', ours['psnr_std'])}" in out
    assert images(nb) >= 3  # one figure per metric with values (psnr, ssim, lpips_proxy)
    # ablation deltas against Ours are shown for every ablation
    assert "Ablations" in "".join(c.source for c in nb.cells) and "w/o Pose" in out


def test_table2_notebook_reads_csv(tmp_path, kernel_env, monkeypatch):
    """Also: the kernel runs in notebooks/ (as Jupyter starts it) and the path is relative to the repository root,
    as a user types it there (`CAMO_METRICS=grid_out/metrics.csv jupyter lab notebooks/...`)."""
    df = tiny_metrics(tmp_path / "m.parquet")
    df.to_csv(tmp_path / "grid_metrics.csv", index=False)
    rel = os.path.relpath(tmp_path / "grid_metrics.csv", NOTEBOOKS.parent)
    assert not (NOTEBOOKS / rel).exists()  # relative to notebooks/ it would not resolve
    nb = run_notebook("table2_metrics.ipynb", kernel_env, NOTEBOOKS, monkeypatch, CAMO_METRICS=rel)
    assert "| Ours |" in texts(nb) or "| **Ours** |" in texts(nb)


# ------------------------------------------------------------------------------------------------------------
# Table I
# ------------------------------------------------------------------------------------------------------------


def tiny_study_db(path: Path) -> str:
    """A study database (the real schema, study_site.db) with 6 participants, 3 methods, 1 practice and 6 formal
    trials each: method A mostly found fast, C mostly not found."""
    import datetime

    from optimizer.assets.conditions import condition
    from study_site.db import Database, Participant, Trial

    url = f"sqlite:///{path}"
    db = Database(url)
    now = datetime.datetime(2024, 1, 1)
    rng = np.random.default_rng(1)
    p_found = {"ours": 0.3, "mean": 0.7, "transparent": 0.95}
    with db.write() as s:
        for i in range(6):
            p = Participant(token=f"tok{i}", pid_hmac=f"h{i}", id_source="generic", seed=i, time_limit_s=40.0,
                            created_at=now, last_seen_at=now, consent_at=now, instructions_at=now,
                            completed_at=now if i < 5 else None, age_bracket="20-29" if i % 2 else None)
            s.add(p)
            s.flush()
            trials = [("practice", True)] + [(m, False) for m in p_found for _ in range(2)]
            for k, (method, practice) in enumerate(trials):
                found = rng.random() < p_found.get(method, 1.0)
                timed_out = (not found) and rng.random() < 0.5
                rt = float(rng.uniform(1000, 20000)) if not timed_out else 40000.0
                s.add(Trial(participant_id=p.id, trial_index=k, client_trial_id=f"c{i}-{k}", practice=practice,
                            stimulus_id=f"s{k}", run=f"r_{method}", scene=f"scene{k % 3}", object="o", method=method,
                            ablation="none", condition=condition(method).id, label=condition(method).label, view="0", hit=bool(found), timed_out=bool(timed_out),
                            click_x=None if timed_out else 1, click_y=None if timed_out else 1, rt_ms=rt,
                            time_limit_s=40.0, server_received_at=now))
        s.commit()
    db.engine.dispose()
    return url


def _check_table_i(out: str, db_url: str) -> None:
    from study_site.analysis import _pct, formal_trials, load_tables, table_i

    trials, _ = load_tables(db_url)
    t = table_i(formal_trials(trials), n_boot=50, seed=0)
    assert "# Perceptual study: Table I" in out
    for r in t.itertuples():
        assert f"| {r.label} | `{r.condition}` | {r.n_trials} | {_pct(r.confusion_rate)} |" in out, r.condition
    assert "| Ours | `ours` |" in out and "| Mean [6] | `mean` |" in out


def test_table1_notebook_from_db(tmp_path, kernel_env, monkeypatch):
    url = tiny_study_db(tmp_path / "study.sqlite")
    nb = run_notebook("table1_study.ipynb", kernel_env, tmp_path, monkeypatch, CAMO_STUDY_DB=tmp_path / "study.sqlite",
                      CAMO_STUDY_BOOTSTRAP=50)
    out = texts(nb)
    _check_table_i(out, url)
    assert images(nb) >= 2  # confusion-rate bars and the Kaplan-Meier curves (plot_km's PNG)
    assert "p_logrank_holm" in out  # the pairwise tests


def test_table1_notebook_from_report_folder(tmp_path, kernel_env, monkeypatch):
    from study_site.analysis import write_report

    url = tiny_study_db(tmp_path / "study.sqlite")
    write_report(url, tmp_path / "report", n_boot=50)
    monkeypatch.delenv("CAMO_STUDY_DB", raising=False)
    nb = run_notebook("table1_study.ipynb", kernel_env, tmp_path, monkeypatch, CAMO_STUDY_REPORT=tmp_path / "report",
                      CAMO_STUDY_BOOTSTRAP=50)
    _check_table_i(texts(nb), url)


# ------------------------------------------------------------------------------------------------------------
# accuracy vs time
# ------------------------------------------------------------------------------------------------------------

#: The table header bench/bench_tradeoff.py writes (checked against its source below, so a change there shows).
TRADEOFF_HEADER = "| spp | resolution | iterations | planner | seconds | train loss | held-out loss | Pareto |"
#: The columns bench/bench_eval_tradeoff.py writes to eval_tradeoff.csv.
EVAL_COLUMNS = ("resolution", "spp", "metric", "seconds_render", "seconds_metric", "mask_equal", "full_value",
                "full_ref", "full_dev", "crop_value", "crop_ref", "crop_dev")


def test_bench_formats_match_the_benches():
    src = (ROOT / "bench" / "bench_tradeoff.py").read_text()
    assert TRADEOFF_HEADER in src and '"tradeoff.md"' in src
    src = (ROOT / "bench" / "bench_eval_tradeoff.py").read_text()
    assert '"eval_tradeoff.csv"' in src
    for col in ("resolution", "spp", "metric", "seconds_render", "seconds_metric", "mask_equal"):
        assert f'"{col}"' in src, col
    for suffix in ("value", "ref", "dev"):
        assert f'f"{{region}}_{suffix}"' in src, suffix


def tiny_bench(root: Path) -> None:
    lines = ["Stage 1 accuracy vs time — scene gravel, 8 views, 8000 vertices, maps 256^2, llvm_ad_rgb on 2 threads; "
             "losses at 64 spp", "", TRADEOFF_HEADER, "|---|---|---|---|---|---|---|---|"]
    rows = [(1, 64, 25, "on", 3.0, 0.050, 0.060, "*"), (4, 64, 10, "on", 4.0, 0.045, 0.055, "*"),
            (4, 64, 25, "on", 8.0, 0.040, 0.050, "*"), (4, 64, 50, "on", 16.0, 0.039, 0.049, "*"),
            (4, 64, 100, "on", 32.0, 0.0385, 0.0495, ""), (16, 64, 25, "on", 20.0, 0.039, 0.051, ""),
            (4, 128, 25, "on", 25.0, 0.038, 0.048, "*"), (4, 256, 25, "on", 90.0, 0.0375, 0.0478, "*"),
            (4, 64, 25, "off (full)", 30.0, 0.041, 0.052, "")]
    for r in rows:
        lines.append(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]:.1f} | {r[5]:.4f} | {r[6]:.4f} | {r[7]} |")
    (root / "tradeoff").mkdir(parents=True)
    (root / "tradeoff" / "tradeoff.md").write_text("\n".join(lines) + "\n")
    recs = []
    for res in (32, 64):
        for spp in (4, 16, 64):
            for m, ref in (("psnr", 30.0), ("ssim", 0.9)):
                dev = ref * 0.1 / math.sqrt(spp)
                recs.append({"resolution": res, "spp": spp, "metric": m, "seconds_render": 0.01 * spp * res / 32,
                             "seconds_metric": 0.002, "mask_equal": True, "full_value": ref + dev, "full_ref": ref,
                             "full_dev": dev, "crop_value": ref - dev, "crop_ref": ref, "crop_dev": dev})
    (root / "eval").mkdir()
    pd.DataFrame(recs, columns=list(EVAL_COLUMNS)).to_csv(root / "eval" / "eval_tradeoff.csv", index=False)


def test_accuracy_vs_time_notebook(tmp_path, kernel_env, monkeypatch):
    tiny_bench(tmp_path / "bench_out")
    nb = run_notebook("accuracy_vs_time.ipynb", kernel_env, tmp_path, monkeypatch,
                      CAMO_TRADEOFF=tmp_path / "bench_out" / "tradeoff",
                      CAMO_EVAL_TRADEOFF=tmp_path / "bench_out" / "eval" / "eval_tradeoff.csv")
    out = texts(nb)
    assert "Stage 1 accuracy vs time — scene gravel" in out
    assert images(nb) >= 3  # time vs held-out loss, one-factor panels, evaluation cost vs deviation
    assert re.search(r"no (tradeoff|eval_tradeoff)", out) is None
    # relative deviation of psnr at 4 spp = 0.1 / sqrt(4) = 5.00%
    assert "5.00%" in out


def test_accuracy_vs_time_notebook_without_inputs(tmp_path, kernel_env, monkeypatch):
    nb = run_notebook("accuracy_vs_time.ipynb", kernel_env, tmp_path, monkeypatch,
                      CAMO_TRADEOFF=tmp_path / "none", CAMO_EVAL_TRADEOFF=tmp_path / "none")
    out = texts(nb)
    assert "no tradeoff.md" in out and "no eval_tradeoff.csv" in out
