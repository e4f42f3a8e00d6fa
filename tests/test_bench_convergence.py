"""bench/bench_convergence.py's timing: another checkout as a variant, a run's phases read from its files, the CPU
seconds of the runs, the timing table, and a one-line refusal of a variant pointing at no checkout."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


def test_checkout_variant_is_split_off_and_a_wrong_folder_refused(bench_module, tmp_path):
    bc = bench_module("bench_convergence")
    (tmp_path / "old" / "camo").mkdir(parents=True)
    (tmp_path / "old" / "camo" / "cli.py").write_text("")
    name, flags = bc.variant_flags(f"old=@{tmp_path / 'old'} --preset fast --seed 1")
    assert name == "old"
    assert bc.split_checkout(flags) == ((tmp_path / "old").resolve(), ["--preset", "fast", "--seed", "1"])
    assert bc.split_checkout(["--preset", "fast"]) == (None, ["--preset", "fast"])
    with pytest.raises(ValueError, match="no checkout"):
        bc.split_checkout([f"@{tmp_path}"])


def test_cli_refuses_a_checkout_variant_without_camo_in_one_line(bench_module, monkeypatch, capsys, tmp_path):
    bc = bench_module("bench_convergence")
    monkeypatch.setattr("sys.argv", ["bench_convergence.py", "--variants", f"old=@{tmp_path}", "--out",
                                     str(tmp_path / "out")])
    with pytest.raises(SystemExit) as exc:
        bc.main()
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "no checkout of this project there" in err[-1]
    assert not (tmp_path / "out").exists()  # refused before anything is written


def test_phase_seconds_reads_summary_and_the_median_stage1_step(bench_module, tmp_path):
    bc = bench_module("bench_convergence")
    summary = {"seconds_setup": 5.0, "seconds_pose_search": 6.5, "seconds_start_search": 4.0,
               "seconds_warm_start": 1.5, "seconds_stage1": 120.0, "seconds_stage2": 45.0,
               "seconds_optimisation": 168.0, "holdout": {"seconds": 6.0}}
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    steps = [{"iteration": i, "stage": 1, "seconds": s} for i, s in enumerate([9.0, 2.0, 1.0, 3.0], 1)]
    steps += [{"iteration": 1, "stage": 2, "seconds": 15.0}]
    (tmp_path / "log.jsonl").write_text("\n".join(json.dumps(r) for r in steps) + "\n")
    got = bc.phase_seconds(tmp_path)
    assert got == {"setup": 5.0, "turn search": 6.5, "start search": 4.0, "warm start": 1.5, "Stage 1": 120.0,
                   "Stage 2": 45.0, "optimisation": 168.0, "held-out": 6.0, "s1 steps": 4, "s1 step": 2.5}
    # an older run without the start search or the held-out record: those phases are absent, not zero
    del summary["seconds_start_search"], summary["holdout"]
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    got = bc.phase_seconds(tmp_path)
    assert "start search" not in got and "held-out" not in got and got["Stage 1"] == 120.0
    table = bc.timing_table([{"scene": "gravel", "variant": "old", "wall": 40.2, "cpu": 75.6, "load_before": 0.5,
                              "load_after": 1.25, "phases": got}], {"cpu": 0.68, "wall": 1.36})
    assert "0.680 CPU s" in table.splitlines()[0]
    row = table.splitlines()[-1]
    assert row.startswith("| gravel | old | 40 | 76 | 0.5 / 1.2 | 168.0 | 5.0 | 6.5 | - | 1.5 | 120.0 | 4 | 2.50 |")


def test_child_cpu_seconds_count_a_finished_child(bench_module):
    bc = bench_module("bench_convergence")
    before = bc.child_cpu_seconds()
    subprocess.run([sys.executable, "-c", "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass"],
                   check=True)
    assert bc.child_cpu_seconds() - before >= 0.25
