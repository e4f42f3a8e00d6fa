"""Run directories are written as transactions (optimizer.assets.rundir.RunTransaction): a run writes into a staging
folder beside its run directory and moves it into place only when it finished, so a failure -- an exception,
Ctrl-C, a killed process -- leaves an earlier run byte for byte as it was; `--resume` continues the checkpoint of an
unfinished attempt or of a finished run; a resume of a run recorded by another spec layout or major camo / Mitsuba
version is refused in one line unless `--accept-versions`, and every attempt is appended to config.toml's history;
`camo evaluate` refuses an incomplete run directory in one line."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from camo.cli import main
from optimizer.assets.rundir import CHECKPOINT, RunTransaction, major_version, resume_mismatch, staging_dir

TINY = ["--views", "3", "--resolution", "24", "--map-resolution", "32", "--displacement-resolution", "16",
        "--target-vertices", "1500", "--spp", "2", "--target-spp", "8", "--quiet", "--stages", "1", "--threads", "1",
        "--warm-start", "off", "--pose-search", "0", "--holdout-views", "0", "--checkpoint-every", "1"]


def optimize(out, iterations, *extra) -> int:
    return main(["optimize", "gravel", "--out", str(out), "--iterations", str(iterations), *TINY, *extra])


def digest(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder`` (and the file list), to compare a run directory byte for byte."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    out = tmp_path_factory.mktemp("tx") / "run"
    assert optimize(out, 2) == 0
    return out


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("camo: error: "), err
    return err[0]


# --------------------------------------------------------------------------------------------------------------
# the transaction on its own
# --------------------------------------------------------------------------------------------------------------


def test_commit_replaces_and_abort_keeps_the_old_folder(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with RunTransaction(out, overwrite=True) as txn:
            (txn.path / "new.txt").write_text("new")
            raise RuntimeError("boom")
    assert digest(out) == {"old.txt": hashlib.sha256(b"old").hexdigest()}
    assert not staging_dir(out).exists()  # no checkpoint: nothing worth keeping
    with RunTransaction(out, overwrite=True) as txn:
        (txn.path / "new.txt").write_text("new")
        (txn.path / CHECKPOINT).write_bytes(b"x")
    assert sorted(digest(out)) == [CHECKPOINT, "new.txt"] and not staging_dir(out).exists()
    assert not (tmp_path / ".run.lock").exists() and not (tmp_path / ".run.old").exists()


def test_an_interrupted_two_rename_commit_is_recovered(tmp_path):
    """Where no atomic exchange exists, a commit is two renames; a kill between them leaves `.name.old` and no run
    directory: the next transaction puts the old run back."""
    out = tmp_path / "run"
    old = tmp_path / ".run.old"
    old.mkdir()
    (old / "summary.json").write_text("{}")
    with pytest.raises(Exception):
        with RunTransaction(out, resume=True):
            pass
    assert (out / "summary.json").is_file() and not old.exists()


def test_one_writer_at_a_time(tmp_path, capsys):
    import fcntl

    out = tmp_path / "run"
    fd = os.open(tmp_path / ".run.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)
    os.pwrite(fd, b"camo (pid 4242)", 0)
    try:
        assert optimize(out, 1) == 2
        assert "being written by camo (pid 4242)" in one_line(capsys)
    finally:
        os.close(fd)
    assert not out.exists() and not staging_dir(out).exists()


def test_major_versions_and_the_mismatch_rule():
    assert major_version("3.9.1") == "3" and major_version("0.1.0") == "0.1" and major_version("12") == "12"
    cfg = {"spec_version": 2, "versions": {"camo": "0.1.0", "mitsuba": "3.9.1"}}
    assert resume_mismatch(cfg, {"camo": "0.1.3", "mitsuba": "3.10.0"}) is None
    assert "mitsuba 3.9.1 (now 4.0.0)" in resume_mismatch(cfg, {"camo": "0.1.0", "mitsuba": "4.0.0"})
    assert "camo 0.1.0 (now 0.2.0)" in resume_mismatch(cfg, {"camo": "0.2.0", "mitsuba": "3.9.1"})
    assert "no spec_version" in resume_mismatch({"versions": cfg["versions"]}, {"camo": "0.1.0", "mitsuba": "3.9.1"})
    assert "no config.toml" in resume_mismatch(None, {})


# --------------------------------------------------------------------------------------------------------------
# camo optimize: failures leave the old run alone
# --------------------------------------------------------------------------------------------------------------


def test_an_exception_mid_overwrite_leaves_the_old_run_byte_identical(finished, tmp_path, monkeypatch, capsys):
    import shutil

    from camo_base.errors import CamoError
    from optimizer.optimise import run as run_mod

    shutil.copytree(finished, tmp_path / "run")
    finished = tmp_path / "run"
    before = digest(finished)

    def fail(*a, **k):
        raise CamoError("simulated failure while writing the result")

    monkeypatch.setattr(run_mod, "finish_run", fail)
    assert optimize(finished, 3, "--overwrite", "--seed", "5") == 2
    assert "simulated failure" in one_line(capsys)
    assert digest(finished) == before
    # it reached checkpoints: the unfinished attempt is kept for --resume, and a plain run is refused in one line
    part = staging_dir(finished)
    assert (part / CHECKPOINT).is_file()
    assert optimize(finished, 3, "--seed", "5") == 2
    line = one_line(capsys)
    assert "unfinished run" in line and "--resume" in line and "--overwrite" in line
    assert digest(finished) == before
    # --overwrite discards it (and now succeeds)
    monkeypatch.undo()
    assert optimize(finished, 3, "--overwrite", "--seed", "5") == 0
    assert not part.exists() and tomllib.loads((finished / "config.toml").read_text())["seed"] == 5


def test_ctrl_c_leaves_the_old_run_byte_identical(tmp_path, monkeypatch, capsys):
    from optimizer.optimise import stage1 as s1_mod

    out = tmp_path / "run"
    assert optimize(out, 2) == 0
    before = digest(out)
    calls = {"n": 0}
    step = s1_mod.Stage1.step

    def interrupted(self):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return step(self)

    monkeypatch.setattr(s1_mod.Stage1, "step", interrupted)
    assert optimize(out, 4, "--overwrite", "--seed", "1") == 130
    assert digest(out) == before


def _wait_for(path: Path, proc, seconds: float = 600) -> None:
    t0 = time.time()
    while not path.is_file():
        assert proc.poll() is None, proc.stdout.read().decode()
        assert time.time() - t0 < seconds, f"no {path} after {seconds} s"
        time.sleep(0.05)


def test_a_killed_overwrite_leaves_the_old_run_and_resume_continues_it(finished, tmp_path, capsys):
    """A real `camo optimize --overwrite` process, killed (SIGKILL) after its first checkpoint: the old run is byte
    for byte as it was; `--resume` continues the killed attempt's checkpoint to the end, moves the result into place,
    and the history records both attempts."""
    out = tmp_path / "run"
    import shutil

    shutil.copytree(finished, out)
    before = digest(out)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    cmd = [sys.executable, "-m", "camo.cli", "optimize", "gravel", "--out", str(out), "--iterations", "20", *TINY,
           "--overwrite", "--seed", "3"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        _wait_for(staging_dir(out) / CHECKPOINT, proc)
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert digest(out) == before  # the killed run never touched it
    assert (staging_dir(out) / CHECKPOINT).is_file()
    with np.load(staging_dir(out) / CHECKPOINT) as z:
        reached = int(z["iteration"])
    assert reached < 20
    assert optimize(out, 20, "--seed", "3", "--resume") == 0
    assert not staging_dir(out).exists()
    cfg = tomllib.loads((out / "config.toml").read_text())
    assert cfg["seed"] == 3 and [h["event"] for h in cfg["history"]] == ["start", "resume"]
    assert cfg["history"][1]["from_iteration"] >= reached
    log = [r for r in (out / "log.jsonl").read_text().splitlines() if r.strip()]
    assert len(log) == 20


def test_evaluate_refuses_an_incomplete_run_directory(finished, tmp_path, capsys):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(finished, broken)
    (broken / "summary.json").unlink()
    assert main(["evaluate", str(broken), "--out", str(tmp_path / "ev"), "--metrics", "psnr", "--quiet"]) == 2
    line = one_line(capsys)
    assert "incomplete run directory" in line and "summary.json" in line
    assert not (tmp_path / "ev").exists()


# --------------------------------------------------------------------------------------------------------------
# --resume: versions and provenance
# --------------------------------------------------------------------------------------------------------------


def _edit_config(run: Path, old: str, new: str) -> None:
    p = run / "config.toml"
    text = p.read_text()
    assert old in text, old
    p.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize("old,new,needle", [
    ("spec_version = 2", "spec_version = 3", "spec_version 3, this camo writes 2"),
    ("spec_version = 2\n", "", "no spec_version"),
    ('camo = "0.1.0"', 'camo = "0.7.0"', "camo 0.7.0 (now 0.1.0)"),
    ('mitsuba = "3.', 'mitsuba = "2.', "mitsuba 2."),
])
def test_resume_refuses_other_versions_in_one_line(finished, tmp_path, capsys, old, new, needle):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(finished, out)
    _edit_config(out, old, new)
    before = digest(out)
    assert optimize(out, 3, "--resume") == 2
    line = one_line(capsys)
    assert needle in line and "--accept-versions" in line and "--resume" in line, line
    assert digest(out) == before and not staging_dir(out).exists()


def test_accept_versions_resumes_and_appends_the_history(finished, tmp_path):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(finished, out)
    _edit_config(out, 'camo = "0.1.0"', 'camo = "0.7.0"')
    first = tomllib.loads((out / "config.toml").read_text())
    assert optimize(out, 3, "--resume", "--accept-versions") == 0
    cfg = tomllib.loads((out / "config.toml").read_text())
    assert cfg["versions"] == first["versions"]  # what the run first recorded is never rewritten
    assert [h["event"] for h in cfg["history"]] == ["start", "resume"]
    assert cfg["history"][:1] == first["history"]  # appended, never rewritten
    assert cfg["versions"]["camo"] == "0.7.0" and cfg["history"][1]["camo"] == "0.1.0"
    assert cfg["history"][1]["from_iteration"] == 2
    assert len((out / "log.jsonl").read_text().splitlines()) == 3
