"""``camo grid``: grid files, cell keys, resumable runs, failures, the merged table and report, Ray.

The end-to-end tests run real tiny cells (4 views, 32 px, 2 iterations, Stage 1 only, 1,500 vertices, 32 px maps)
through the real worker processes (spawned process pool; Ray tasks).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest

from camo import cli
from camo.grid.cell import read_attempts
from camo.grid.executors import available_cores
from camo.grid.spec import load_grid
from camo_base.tables import read_parquet

TINY_OPTIMIZE = """
[optimize]
iterations = 2
views = 4
resolution = 32
spp = 2
target-spp = 8
stages = "1"
target-vertices = 1500
map-resolution = 32
displacement-resolution = 16
checkpoint-every = 1

[evaluate]
views = 4
spp = 8
metrics = ["psnr", "ssim"]
"""

TINY = """
name = "tiny"
scenes = ["gravel"]
methods = ["ours", "mean"]
ablations = ["none", "pose"]
""" + TINY_OPTIMIZE


def camo(*argv) -> int:
    return cli.main([str(a) for a in argv])


def write(path: Path, text: str) -> Path:
    path.write_text(textwrap.dedent(text))
    return path


def starts(cell_dir: Path) -> list[dict]:
    return [a for a in read_attempts(cell_dir) if a.get("event") == "start"]


# --------------------------------------------------------------------------------------------------------------
# grid files and cells (no rendering)
# --------------------------------------------------------------------------------------------------------------

BAD_GRIDS = [
    ("", "`scenes = [...]` is missing"),
    ("scenes = []", "scenes must be a non-empty list"),
    ('scenes = ["gravel"]\nmethod = ["ours"]', "unknown key(s) method"),
    ('scenes = ["nowhere"]', "unknown scene 'nowhere'"),
    ('scenes = ["gravel:spaceship"]', "unknown object 'spaceship'"),
    ('scenes = ["gravel"]\nobjects = ["spaceship"]', "unknown object(s) spaceship"),
    ('scenes = ["missing.toml"]', "scene pack not found"),
    ('scenes = ["gravel", "gravel"]', "lists gravel more than once"),
    ('scenes = ["gravel"]\nmethods = ["ours", "magic"]', "unknown method(s) magic"),
    ('scenes = ["gravel"]\nablations = ["wings"]', "unknown"),
    ('scenes = ["gravel"]\nmethods = ["mean"]\nablations = ["pose"]', "ablations apply to method \"ours\" only"),
    ('scenes = ["gravel"]\nseeds = ["a"]', "seeds must be a non-empty list of integers"),
    ('scenes = ["gravel"]\nseeds = [1, 1]', "more than once"),
    ('scenes = ["gravel"]\n[optimize]\niteraions = 3', "unknown option 'iteraions'"),
    ('scenes = ["gravel"]\n[optimize]\nseed = 3', "use `seeds = [...]`"),
    ('scenes = ["gravel"]\n[optimize]\nthreads = 3', "cores // workers"),
    ('scenes = ["gravel"]\n[optimize]\nout = "x"', "set by the grid"),
    ('scenes = ["gravel"]\n[optimize]\niterations = "many"', "[optimize] iterations must be an integer, got 'many'"),
    ('scenes = ["gravel"]\n[optimize]\niterations = 0', "[optimize] iterations must be an integer in [1, 100000], got 0"),
    ('scenes = ["gravel"]\n[optimize]\nno-planner = 1', "is a flag"),
    ('scenes = ["gravel"]\n[optimize]\ndomain = "everywhere"', "[optimize] domain must be one of object+shadow, frame, got 'everywhere'"),
    ('scenes = ["gravel"]\n[optimize]\niter = 3', "unknown option 'iter'"),  # no argparse abbreviations
    ('scenes = ["gravel"]\nmethods = ["ours", "mean"]\n[optimize.mean]\nspp = 3',
     "[optimize.mean] spp does not apply to method mean"),
    ('scenes = ["gravel"]\n[optimize]\nstages = "3"', "cell gravel__ours__s0: stages must include 1"),
    ('scenes = ["gravel"]\n[optimize.magic]\niterations = 3', "[optimize.magic]"),
    ('scenes = ["gravel"]\n[evaluate]\njitter = 0', "[evaluate] jitter must be a number in (0, 100], got 0"),
    ('scenes = ["gravel"]\n[evaluate]\nmetrics = ["nope"]', "unknown metric(s) nope"),
    ('scenes = ["gravel"]\n[evaluate]\nrun_dirs = ["x"]', "set by the grid"),
    # [evaluate] is made by EvalSettings.from_options: each problem names the grid's key as written
    ('scenes = ["gravel"]\n[evaluate]\nviewz = 3', "[evaluate] unknown option 'viewz'; `camo evaluate` options: "),
    ('scenes = ["gravel"]\n[evaluate]\nviews = "many"', "[evaluate] views must be an integer, got 'many'"),
    ('scenes = ["gravel"]\n[evaluate]\nspp = 0', "[evaluate] spp must be an integer in [1, 1048576], got 0"),
    ('scenes = ["gravel"]\n[evaluate]\nseed = 1.5', "[evaluate] seed must be an integer, got 1.5"),
    ('scenes = ["gravel"]\n[evaluate]\nno-noise-match = 1', "[evaluate] no-noise-match is a flag: write true or false"),
    ('scenes = ["gravel"]\n[evaluate]\nmetrics = ","', "[evaluate] metrics is empty"),
    ('scenes = ["gravel"]\n[evaluate]\nmetrics = []', "[evaluate] metrics: a list must hold plain numbers or strings"),
    ('scenes = ["gravel"]\n[evaluate]\nweights = ["lpips"]', "[evaluate] weights lpips: expected NAME=PATH"),
    ('scenes = ["gravel"]\n[evaluate]\nlpips-weights = "a"\nweights = "lpips=b"',
     "[evaluate] lpips-weights a: weights for lpips given twice"),
    ('scenes = ["gravel"]\n[evaluate]\nasset = "x.glb"', "[evaluate] asset is set by the grid: an input of `camo evaluate`"),
    ('scenes = ["gravel"\n', "not valid TOML"),
]


@pytest.mark.parametrize("text,message", BAD_GRIDS)
def test_bad_grid_is_one_line_exit_2(tmp_path, capsys, text, message):
    grid = write(tmp_path / "grid.toml", text)
    out = tmp_path / "out"
    assert camo("grid", "run", grid, "--out", out) == 2
    err = capsys.readouterr().err
    assert err.startswith("camo: error: ") and err.count("\n") == 1, err
    assert message in err, err
    assert not out.exists()  # nothing is written for a bad grid


def test_bad_cli_input(tmp_path, capsys):
    grid = write(tmp_path / "grid.toml", 'scenes = ["gravel"]')
    for argv in (["grid", "run", grid, "--out", tmp_path / "o", "--workers", "0"],
                 ["grid", "run", grid, "--out", tmp_path / "o", "--ray-address", "127.0.0.1:1"],
                 ["grid", "run", tmp_path / "missing.toml", "--out", tmp_path / "o"],
                 ["grid", "status", tmp_path]):
        assert camo(*argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("camo: error: ") and err.count("\n") == 1, err
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "precious.txt").write_text("x")
    assert camo("grid", "run", grid, "--out", tmp_path / "busy") == 2
    assert "not a grid output" in capsys.readouterr().err


def test_one_driver_per_output_folder(tmp_path, capsys):
    from camo.grid.runner import _driver_lock

    grid = write(tmp_path / "grid.toml", TINY)
    with _driver_lock(tmp_path / "out"):
        assert camo("grid", "run", grid, "--out", tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert "is in use by another `camo grid run` (pid" in err and err.count("\n") == 1
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [".lock"]


def test_a_running_cell_is_left_alone(tmp_path, capsys):
    """A cell whose lock another process holds (say a worker orphaned by a killed driver) is not run again."""
    from camo.grid.cell import _CellLock, run_cell

    grid = write(tmp_path / "grid.toml", 'scenes = ["gravel"]\nmethods = ["mean"]\n' + TINY_OPTIMIZE)
    (cell,) = load_grid(grid).cells
    out = tmp_path / "out"
    d = out / "cells" / cell.key
    d.mkdir(parents=True)
    lock = _CellLock(d)
    assert lock.acquire() is None
    try:
        assert camo("grid", "run", grid, "--out", out) == 1
        assert "1 running" in capsys.readouterr().err
        assert camo("grid", "status", out) == 0
        assert f"running  {cell.key}" in capsys.readouterr().out
        res = run_cell(cell.to_dict(), str(d), 1)  # a worker asked to run it anyway touches nothing
        assert res["status"] == "busy" and f"pid {os.getpid()}" in res["error"]
        assert not (d / "attempts.jsonl").exists() and not (d / "run").exists()
    finally:
        lock.release()
    assert camo("grid", "status", out) == 0
    assert "1 pending" in capsys.readouterr().out


def test_cell_evaluation_settings_are_camo_evaluates_of_the_same_flags(tmp_path):
    """A cell's evaluation settings are made from its [evaluate] options as data (no command line), and equal what
    `camo evaluate` makes of the equivalent flags, and of the command line the cell's log shows."""
    from evaluation.cli import settings_of

    grid = load_grid(write(tmp_path / "grid.toml", """
        scenes = ["gravel"]
        methods = ["mean"]
        [evaluate]
        views = 5
        jitter = 0.5
        spp = 8
        resolution = 48
        seed = 3
        metrics = ["psnr", "ssim", "psnr"]
        weights = ["sifid=/w/inception.pth"]
        lpips-weights = "/w/lpips"
        no-noise-match = true
        no_planner = false
        sampler = "sobol"
        """))
    cell = grid.cells[0]
    assert dict(cell.evaluate) == {"views": 5, "jitter": 0.5, "spp": 8, "resolution": 48, "seed": 3,
                                   "metrics": "psnr,ssim,psnr", "weights": "sifid=/w/inception.pth",
                                   "lpips_weights": "/w/lpips", "no_noise_match": True,
                                   "sampler": "sobol"}  # (defaults left out)
    settings = cell.evaluation_settings(threads=2)
    flags = ["--views", "5", "--jitter", "0.5", "--spp", "8", "--resolution", "48", "--seed", "3",
             "--metrics", "psnr,ssim,psnr", "--weights", "sifid=/w/inception.pth", "--lpips-weights", "/w/lpips",
             "--no-noise-match", "--sampler", "sobol", "--quiet", "--threads", "2"]
    parser = cli.build_parser()
    by_cli = settings_of(parser.parse_args(["evaluate", "RUN", "--out", "E", *flags]))
    assert settings == by_cli
    assert (settings.views, settings.jitter, settings.metrics, settings.weights, settings.noise_match,
            settings.planner, settings.progress, settings.threads, settings.sampler) == \
        (5, 0.5, ["psnr", "ssim"], {"sifid": "/w/inception.pth", "lpips": "/w/lpips"}, False, True, False, 2, "sobol")
    logged = cell.evaluate_command(tmp_path / "c", 2)
    assert settings_of(parser.parse_args(logged)) == settings
    # no [evaluate] table: camo evaluate's defaults
    plain = load_grid(write(tmp_path / "plain.toml", 'scenes = ["gravel"]\nmethods = ["mean"]\n')).cells[0]
    assert plain.evaluate == () and plain.evaluation_settings() == \
        settings_of(parser.parse_args(["evaluate", "RUN", "--out", "E", "--quiet"]))


def test_cells_expand_and_keys_are_stable(tmp_path):
    (tmp_path / "packs").mkdir()
    pack = write(tmp_path / "packs" / "yard.toml", """
        name = "yard"
        [object]
        primitive = "duck"
        [environment]
        builtin = "meadow"
    """)
    base = """
        scenes = ["gravel", "split:chair", "packs/yard.toml"]
        objects = ["vase", "torus"]
        methods = ["ours", "mean", "ganmouflage"]
        ablations = ["none", "pose", ["displacement", "pose"]]
        seeds = [0, 1]
        [optimize]
        iterations = 3
        map-resolution = 64
        [optimize.ganmouflage]
        iterations = 7
        [evaluate]
        spp = 16
    """
    g = load_grid(write(tmp_path / "g.toml", base))
    labels = {c.scene_label for c in g.cells}
    assert labels == {"gravel:vase", "gravel:torus", "split:chair", "packs/yard.toml"}  # objects x plain names only
    # per scene: ours x 3 ablations + mean + ganmouflage, x 2 seeds
    assert len(g.cells) == 4 * (3 + 1 + 1) * 2
    assert {c.ablation for c in g.cells if c.method != "ours"} == {"none"}
    assert {c.ablation for c in g.cells if c.method == "ours"} == {"none", "pose", "displacement,pose"}
    assert len({c.key for c in g.cells}) == len(g.cells) and len({c.name for c in g.cells}) == len(g.cells)
    gan = next(c for c in g.cells if c.method == "ganmouflage")
    ours = next(c for c in g.cells if c.method == "ours" and c.ablation == "pose" and c.seed == 1)
    mean = next(c for c in g.cells if c.method == "mean")
    # each cell holds its run spec: the shared options where the method uses them, its own table's on top
    assert gan.spec["options"]["iterations"] == 7 and "iterations" not in gan.spec["stage1"]
    assert ours.spec["stage1"]["iterations"] == 3 and ours.spec["appearance"]["map_resolution"] == 64
    assert ours.spec["seed"] == 1 and ours.spec["ablate"] == ["pose"] and ours.spec["appearance"]["pose"] is False
    assert mean.spec["appearance"] == {"map_resolution": 64, "eta": 1.5} and "iterations" not in mean.spec["stage1"]
    assert ours.run_spec().to_dict() == ours.spec  # what the worker runs is the stored spec
    yard = next(c for c in g.cells if c.scene_label == "packs/yard.toml")
    assert yard.scene == str(pack.resolve()) and yard.name.startswith("yard__")
    assert yard.spec["scene"] == str(pack.resolve()) and yard.spec["pack"]["object"]["primitive"] == "duck"
    keys = {(c.scene_label, c.method, c.ablation, c.seed): c.key for c in g.cells}

    def keys_of(text):
        return {(c.scene_label, c.method, c.ablation, c.seed): c.key for c in load_grid(write(tmp_path / "g.toml", text)).cells}

    # the same work gives the same keys: other key order, _ for -, explicit defaults, fewer or more other cells
    same = """
        seeds = [1, 0, 5]
        methods = ["mean", "ours", "ganmouflage"]
        ablations = [["pose", "displacement"], "pose", "none"]
        objects = ["torus", "vase"]
        scenes = ["packs/yard.toml", "split:chair", "gravel"]
        [optimize]
        map_resolution = 64
        iterations = 3
        loss = "gated"
        no-planner = false
        [optimize.ganmouflage]
        iterations = 7
        [evaluate]
        jitter = 0.25
        spp = 16
    """
    k2 = keys_of(same)
    assert all(k2[k] == v for k, v in keys.items()) and len(k2) == len(keys) + 4 * 5
    # different work, different keys: an optimise option, an evaluate option, the pack's content
    assert not set(keys_of(base.replace("iterations = 3", "iterations = 4")).values()) & {
        v for k, v in keys.items() if k[1] != "ganmouflage"}
    assert not set(keys_of(base.replace("spp = 16", "spp = 32")).values()) & set(keys.values())
    pack.write_text(pack.read_text().replace("duck", "teapot"))
    k3 = keys_of(base)
    assert all((k3[k] == v) == (k[0] != "packs/yard.toml") for k, v in keys.items())


#: Cell keys computed by camo before cells held run specs (git 380cf23) for OLD_KEYS_GRID: they must not change, or
#: every finished cell of a grid folder written then would run again.
OLD_KEYS_GRID = """
name = "tiny"
scenes = ["gravel", "split:chair"]
methods = ["ours", "mean", "ganmouflage", "diffusion2d"]
ablations = ["none", "pose"]
seeds = [0, 3]
""" + TINY_OPTIMIZE.replace("checkpoint-every = 1\n", 'checkpoint-every = 1\nloss = "gated"\nno-planner = false\n') + """
[optimize.ganmouflage]
iterations = 7
[optimize.diffusion2d]
stage2-backend = "patch"
"""
OLD_KEYS = {
    "gravel__ours__s0": "374ae9f32a7bd238", "gravel__ours__s3": "03719b115022cca2",
    "gravel__ours-wo-pose__s0": "abb5fe21d9129a2f", "gravel__ours-wo-pose__s3": "d20a8da84202df56",
    "gravel__mean__s0": "dcaa3bde2966805d", "gravel__mean__s3": "ccc0608e08ed49a6",
    "gravel__ganmouflage__s0": "06559ee012e5c228", "gravel__ganmouflage__s3": "ff042d03b48d2abf",
    "gravel__diffusion2d__s0": "4c0a4164a8cd1b57", "gravel__diffusion2d__s3": "7940da6ac148fdfa",
    "split_chair__ours__s0": "3a47ea8be92383e9", "split_chair__ours__s3": "5c1993d36dbfe8b0",
    "split_chair__ours-wo-pose__s0": "e7999cd0ea14834d", "split_chair__ours-wo-pose__s3": "243205ed4e1318ec",
    "split_chair__mean__s0": "3ceb420de34db17d", "split_chair__mean__s3": "84fc613fabe1a3fd",
    "split_chair__ganmouflage__s0": "6aec72dd20a615d7", "split_chair__ganmouflage__s3": "539bc3359619d972",
    "split_chair__diffusion2d__s0": "1c5b55f9a36353df", "split_chair__diffusion2d__s3": "a02bc681d203e07f",
}


def test_cell_keys_are_those_of_grids_written_before_run_specs(tmp_path):
    g = load_grid(write(tmp_path / "g.toml", OLD_KEYS_GRID))
    assert {c.name: c.key for c in g.cells} == OLD_KEYS
    diff = next(c for c in g.cells if c.name == "gravel__diffusion2d__s0")
    assert diff.spec["options"]["backend"] == "patch" and diff.spec["spp"] == {"target": 8}


def test_grid_output_written_before_run_specs_says_how_to_convert_and_converts(tmp_path, capsys):
    """An output folder whose grid.json / cell.json hold command lines (camo before run specs): `grid status` is a
    one-line error saying how to convert it; `grid run` with its grid file converts it and keeps the finished cell
    (same key: DONE found, not run again)."""
    grid = write(tmp_path / "grid.toml", OLD_KEYS_GRID.replace('scenes = ["gravel", "split:chair"]', 'scenes = ["gravel"]')
                 .replace('methods = ["ours", "mean", "ganmouflage", "diffusion2d"]', 'methods = ["ours", "mean"]')
                 .replace('ablations = ["none", "pose"]', "").replace("seeds = [0, 3]", "seeds = [0]")
                 .replace("[optimize.ganmouflage]\niterations = 7\n", "")
                 .replace('[optimize.diffusion2d]\nstage2-backend = "patch"\n', ""))
    old_mean = {"key": "dcaa3bde2966805d", "name": "gravel__mean__s0", "scene": "gravel", "scene_label": "gravel",
                "method": "mean", "ablation": "none", "seed": 0,
                "optimize": {"checkpoint_every": 1, "displacement_resolution": 16, "iterations": 2, "map_resolution": 32,
                             "resolution": 32, "spp": 2, "stages": "1", "target_spp": 8, "target_vertices": 1500,
                             "views": 4},
                "evaluate": {"metrics": "psnr,ssim", "spp": 8, "views": 4},
                "optimize_argv": ["--checkpoint-every=1", "--displacement-resolution=16", "--iterations=2",
                                  "--map-resolution=32", "--resolution=32", "--spp=2", "--stages=1", "--target-spp=8",
                                  "--target-vertices=1500", "--views=4"],
                "evaluate_argv": ["--metrics=psnr,ssim", "--spp=8", "--views=4"]}
    old_ours = dict(old_mean, key=OLD_KEYS["gravel__ours__s0"], name="gravel__ours__s0", method="ours")
    out = tmp_path / "out"
    cells = []
    for old in (old_ours, old_mean):
        cd = out / "cells" / old["key"]
        cd.mkdir(parents=True)
        (cd / "cell.json").write_text(json.dumps(old))
        (cd / "DONE").write_text(json.dumps({"key": old["key"], "config": old, "finished_at": "then",
                                             "seconds_optimize": 1.0, "seconds_evaluate": 1.0}))
        cells.append(cd)
    (out / "grid.json").write_text(json.dumps({"name": "tiny", "path": str(grid), "cells": [old_ours, old_mean]}))
    assert camo("grid", "status", out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camo grid run GRID --out DIR" in err[0] and "before cells held run specs" in err[0]
    assert camo("grid", "run", grid, "--out", out) == 0
    assert "2 done, 0 failed, 0 partial, 0 pending; 0 to run" in capsys.readouterr().err  # found under their keys
    assert not any((cd / "run").exists() for cd in cells)
    assert all("spec" in json.loads((cd / "cell.json").read_text()) for cd in cells)
    assert camo("grid", "status", out) == 0 and "2 done" in capsys.readouterr().out


def test_a_shared_option_no_method_uses_gets_a_note(tmp_path, capsys):
    """Shared [optimize] options apply to the methods that use them; one that none uses is said (not an error:
    grid files written before run specs carry such options, and their cells' keys include them)."""
    grid = write(tmp_path / "g.toml", 'scenes = ["gravel"]\nmethods = ["mean"]\n[optimize]\nstage2-iterations = 3\n'
                                      "spp = 2\ntarget-spp = 8\n")
    assert camo("grid", "run", grid, "--out", tmp_path / "o", "--dry-run") == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"note: {grid}: [optimize] stage2-iterations, spp apply to none of this grid's methods (mean): "
                   "no cell uses them"]
    (cell,) = load_grid(grid).cells
    assert cell.spec["spp"] == {"target": 8} and "stage2" not in cell.spec


def test_dry_run_lists_cells_and_writes_nothing(tmp_path, capsys):
    grid = write(tmp_path / "grid.toml", TINY)
    assert camo("grid", "run", grid, "--out", tmp_path / "out", "--dry-run") == 0
    out = capsys.readouterr().out
    assert "3 cell(s): 0 done, 0 failed, 0 partial, 3 pending" in out
    for name in ("gravel__ours__s0", "gravel__ours-wo-pose__s0", "gravel__mean__s0"):
        assert name in out
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------------------------
# running: interrupt, resume, merge, report
# --------------------------------------------------------------------------------------------------------------


def test_run_interrupt_resume_merge_and_report(tmp_path, monkeypatch, capsys):
    from evaluation.evaluate import COLUMNS

    grid = write(tmp_path / "grid.toml", TINY)
    out = tmp_path / "out"
    cells = load_grid(grid).cells
    c1, c2, c3 = cells
    d1, d2, d3 = (out / "cells" / c.key for c in cells)

    # 1. interrupted after the first cell finished (test hook = Ctrl-C in the driver)
    monkeypatch.setenv("CAMO_GRID_STOP_AFTER", "1")
    assert camo("grid", "run", grid, "--out", out, "--workers", "1", "--quiet") == 130
    monkeypatch.delenv("CAMO_GRID_STOP_AFTER")
    assert [c.name for c in cells if (out / "cells" / c.key / "DONE").is_file()] == [c1.name]
    done1 = json.loads((d1 / "DONE").read_text())
    assert done1["key"] == c1.key and done1["config"] == c1.to_dict()
    mtime1 = (d1 / "DONE").stat().st_mtime_ns
    assert camo("grid", "status", out) == 0
    assert "1 done, 0 failed" in capsys.readouterr().out

    # 2. cell 2 left with a checkpoint after its first iteration (as if killed there)
    import dataclasses

    from optimizer.optimise.run import run

    spec = c2.run_spec()
    run(dataclasses.replace(spec, stage1=dataclasses.replace(spec.stage1, iterations=1)), c2.run_dir(d2),
        overwrite=True, progress=False, threads=1)
    assert (c2.run_dir(d2) / "checkpoint.npz").is_file() and not (d2 / "DONE").exists()

    # 3. run again: cell 1 untouched, cell 2 resumed from its checkpoint, cell 3 run; then merged and reported
    assert camo("grid", "run", grid, "--out", out, "--workers", "2") == 0
    err = capsys.readouterr().err
    assert "1 done" in err and "2 to run" in err
    assert (d1 / "DONE").stat().st_mtime_ns == mtime1 and len(starts(d1)) == 1
    assert starts(d2)[-1]["mode"] == "resume"
    log = [json.loads(x) for x in (c2.run_dir(d2) / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2]
    assert all((d / "DONE").is_file() for d in (d1, d2, d3))
    # render threads per cell = max(1, cores // workers)
    assert starts(d2)[-1]["threads"] == starts(d3)[-1]["threads"] == max(1, available_cores() // 2)
    assert f"--threads {max(1, available_cores() // 2)}" in (d3 / "log.txt").read_text()

    table = read_parquet(out / "metrics.parquet")
    assert list(table.columns[: len(COLUMNS)]) == list(COLUMNS)
    assert {"cell", "run_seed", "label"} <= set(table.columns)
    assert set(table["run"]) == {c.name for c in cells} and len(table) == 3 * 4 * 2
    assert set(table["label"]) == {"Ours", "w/o Pose", "Mean [6]"}
    per_cell = pd.concat([read_parquet(c.eval_dir(out / "cells" / c.key) / "metrics.parquet") for c in cells])
    pd.testing.assert_series_equal(table["psnr"].reset_index(drop=True), per_cell["psnr"].reset_index(drop=True))
    assert len(pd.read_csv(out / "metrics.csv")) == len(table)
    report = (out / "report" / "report.md").read_text()
    assert "## Table II — object crop (GANmouflage protocol)" in report
    for label in ("Ours", "w/o Pose", "Mean [6]"):
        assert f"| {label} |" in report or f"| **{label}** |" in report
    rows = [ln.split("|")[1].strip() for ln in report.split("## Table II — object crop")[1].splitlines()
            if ln.startswith("| ") and "Model" not in ln][:3]
    assert rows == ["Mean [6]", "w/o Pose", "Ours"]  # the paper's order: baselines, ablations, Ours
    assert (out / "report" / "report.html").is_file()

    # 4. a third run has nothing to do
    stamps = {d: (d / "DONE").stat().st_mtime_ns for d in (d1, d2, d3)}
    assert camo("grid", "run", grid, "--out", out) == 0
    assert "0 to run" in capsys.readouterr().err
    assert {d: (d / "DONE").stat().st_mtime_ns for d in (d1, d2, d3)} == stamps
    assert [len(starts(d)) for d in (d1, d3)] == [1, 1]
    assert camo("grid", "status", out, "--json") == 0
    st = json.loads(capsys.readouterr().out)
    assert st["counts"] == {"done": 3, "failed": 0, "running": 0, "partial": 0, "pending": 0}


def test_failed_and_crashed_cells_are_recorded_and_do_not_stop_the_others(tmp_path, monkeypatch, capsys):
    (tmp_path / "broken.obj").write_text("this is not a mesh\n")
    write(tmp_path / "broken.toml", """
        name = "broken"
        [object]
        mesh = "broken.obj"
        [environment]
        builtin = "gravel"
    """)
    grid = write(tmp_path / "grid.toml", """
        scenes = ["gravel", "broken.toml"]
        methods = ["mean"]
        seeds = [0, 1]
    """ + TINY_OPTIMIZE)
    out = tmp_path / "out"
    cells = {c.name: c for c in load_grid(grid).cells}
    assert sorted(cells) == ["broken__mean__s0", "broken__mean__s1", "gravel__mean__s0", "gravel__mean__s1"]
    monkeypatch.setenv("CAMO_GRID_TEST_CRASH", "gravel__mean__s1")  # its worker process dies
    assert camo("grid", "run", grid, "--out", out, "--workers", "2") == 1
    capsys.readouterr()
    cd = {n: out / "cells" / c.key for n, c in cells.items()}
    assert (cd["gravel__mean__s0"] / "DONE").is_file()
    for n in ("broken__mean__s0", "broken__mean__s1"):
        err = (cd[n] / "ERROR").read_text()
        assert err.startswith("optimize: cannot read mesh") and err.count("\n") == 1, err
        assert "Traceback" in (cd[n] / "error.log").read_text()
        assert not (cd[n] / "DONE").exists()
    crash = (cd["gravel__mean__s1"] / "ERROR").read_text()
    assert "worker process died twice" in crash and crash.count("\n") == 1
    table = read_parquet(out / "metrics.parquet")
    assert set(table["run"]) == {"gravel__mean__s0"}
    assert (out / "report" / "report.md").is_file()
    assert camo("grid", "status", out) == 0
    status = capsys.readouterr().out
    assert "1 done, 3 failed, 0 partial, 0 pending" in status
    assert "failed   " in status and "cannot read mesh" in status

    # --skip-failed leaves them alone; without it they are retried (and fail again, one line each)
    before = {n: len(starts(d)) for n, d in cd.items()}
    assert camo("grid", "run", grid, "--out", out, "--skip-failed", "--quiet") == 1
    assert {n: len(starts(d)) for n, d in cd.items()} == before


# --------------------------------------------------------------------------------------------------------------
# Ray
# --------------------------------------------------------------------------------------------------------------


def test_ray_executor_on_a_local_loopback_ray(tmp_path, capsys):
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'camo-toolkit[cluster]')")
    from camo.grid.executors import RayExecutor

    grid = write(tmp_path / "grid.toml", 'scenes = ["gravel"]\nmethods = ["mean"]\n' + TINY_OPTIMIZE)
    out = tmp_path / "out"
    ex = RayExecutor(workers=1)  # no address: the executor starts a local Ray (127.0.0.1, no dashboard)
    try:
        assert ex.start() == available_cores() and ex.started
        assert ray.get_runtime_context().gcs_address.startswith("127.0.0.1:")
        assert {n["NodeManagerAddress"] for n in ray.nodes()} == {"127.0.0.1"}
        # `camo grid run --executor ray` uses the Ray that is already running in this process
        assert camo("grid", "run", grid, "--out", out, "--executor", "ray", "--workers", "1") == 0
        (cell,) = load_grid(grid).cells
        d = out / "cells" / cell.key
        assert (d / "DONE").is_file()
        st = starts(d)
        assert len(st) == 1 and st[0]["pid"] != os.getpid() and st[0]["threads"] == available_cores()
        assert set(read_parquet(out / "metrics.parquet")["run"]) == {cell.name}
    finally:
        ex.close()
    assert not ray.is_initialized()


def test_ray_missing_is_one_line(tmp_path, monkeypatch, capsys):
    import builtins

    real = builtins.__import__

    def no_ray(name, *a, **k):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("no ray")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    grid = write(tmp_path / "grid.toml", 'scenes = ["gravel"]')
    assert camo("grid", "run", grid, "--out", tmp_path / "out", "--executor", "ray") == 2
    err = capsys.readouterr().err
    assert "pip install 'camo-toolkit[cluster]'" in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------------------------
# a real Ctrl-C (slow)
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["local", "ray"])
def test_sigint_in_a_subprocess_then_resume(tmp_path, executor):
    """`camo grid run` in its own process group gets SIGINT (as from a terminal) after its first cell finished;
    a second run finishes the rest and does not redo the first cell. With Ray, the group also holds the local
    Ray's own processes, as it does in a terminal."""
    if executor == "ray":
        pytest.importorskip("ray", reason="ray is not installed (pip install 'camo-toolkit[cluster]')")
    grid = write(tmp_path / "grid.toml", TINY)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "camo.cli", "grid", "run", str(grid), "--out", str(out), "--quiet",
           "--executor", executor]
    # SIGINT's default disposition, as from a terminal (a background test run ignores it, and children inherit that)
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.time()
    while not list(out.glob("cells/*/DONE")):
        assert proc.poll() is None, proc.stdout.read().decode()
        assert time.time() - t0 < 300
        time.sleep(0.2)
    first = list(out.glob("cells/*/DONE"))[0]
    os.killpg(proc.pid, signal.SIGINT)
    assert proc.wait(timeout=60) == 130
    assert "camo: interrupted" in proc.stdout.read().decode()
    mtime = first.stat().st_mtime_ns
    assert subprocess.run(cmd, timeout=600).returncode == 0
    assert first.stat().st_mtime_ns == mtime and len(starts(first.parent)) == 1
    assert len(list(out.glob("cells/*/DONE"))) == 3


@pytest.mark.parametrize("name, cells, methods", [
    ("smoke", 27, {"ours", "mean", "random"}),
    ("all_scenes", 48, {"ours", "transparent", "mean", "random", "greedy", "diffusion2d", "ganmouflage"}),
    ("table2", 216, {"ours", "transparent", "mean", "random", "greedy", "diffusion2d", "ganmouflage"}),
])
def test_shipped_grid_files_load(name, cells, methods):
    """The grid files in grids/ (README examples) stay valid against the current `camo optimize` options."""
    grid = load_grid(Path(__file__).resolve().parents[1] / "grids" / f"{name}.toml")
    assert len(grid.cells) == cells and {c.method for c in grid.cells} == methods
    assert len({c.key for c in grid.cells}) == cells
    if name != "smoke":  # every built-in environment is in the two larger grids
        assert {c.scene_label.split(":")[0] for c in grid.cells} == {"meadow", "gravel", "split", "room", "occluded",
                                                                       "panorama"}
    gm = [c for c in grid.cells if c.method == "ganmouflage"]
    assert all(c.spec["options"]["iterations"] in (300, 2000) for c in gm)


@pytest.mark.parametrize("path", sorted((Path(__file__).resolve().parents[1] / "grids").glob("*.toml")),
                         ids=lambda p: p.name)
def test_every_shipped_grid_loads(path, tmp_path):
    """Each grid of grids/ parses with today's flags (an [evaluate] option `camo evaluate` dropped is caught here,
    not after hours of optimisation) and names its cells. Grids over the registry data load from a copy of grids/
    and packs/ beside stand-in files when data/real is not fetched (a clean clone, CI), so they are checked too."""
    from camo.doctor import real_packs
    from fixture_real_data import tree_with_fake_real_data

    if "real" in path.name and not all(ok for _, ok, _ in real_packs()):
        path = tree_with_fake_real_data(tmp_path) / "grids" / path.name
    grid = load_grid(path)
    assert grid.cells and all(c.evaluation_settings() is not None for c in grid.cells[:3])
