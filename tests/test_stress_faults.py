"""Stress tests: faults and bad input through the ``camo`` CLI.

* A run killed mid-optimisation (a real SIGKILL of a ``camo optimize`` process after its first checkpoint,
  a simulated kill inside Stage 2, a torn last log line) and resumed with ``--resume`` must end with
  exactly the numbers of an uninterrupted run (``--threads 1``: bit-exact, README "Determinism").
* Corrupt meshes, EXR panoramas, checkpoints, scene packs and weight files must give one line
  ``camo: error: ...`` on stderr and exit code 2, and leave an earlier run directory byte-for-byte and
  mtime-for-mtime untouched (CONTRIBUTING: "never overwrites earlier results").

Extends tests/test_optimize_cli.py (resume of a Stage-1-only run from a checkpoint at its last iteration, a
non-zip checkpoint in an empty folder, a non-empty --out) and tests/test_stage2.py (missing Stage 2 weights).
Runs are tiny (2 views, 24 px, 400 vertices, 32 px maps, 4 + 2 iterations).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from camo.cli import main

TINY = ["--views", "2", "--resolution", "24", "--map-resolution", "32", "--displacement-resolution", "16",
        "--target-vertices", "400", "--spp", "2", "--target-spp", "8", "--threads", "1", "--quiet",
        "--checkpoint-every", "2"]
FULL = ["--iterations", "4", "--stage2-iterations", "2"]  # the uninterrupted run: 4 Stage 1 + 2 Stage 2 steps
TIME_KEYS = {"seconds", "seconds_inpaint", "seconds_total", "seconds_holdout"}


def optimize(out, *extra) -> int:
    return main(["optimize", "gravel", "--out", str(out), *TINY, *extra])


@pytest.fixture(autouse=True, scope="module")
def _restore_threads():
    """``--threads 1`` pins the process-wide Dr.Jit pool; give the next module its thread count back."""
    from optimizer import backend

    info = backend.init()
    n = info.threads
    yield
    backend.set_threads(n)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted run every resume is compared with."""
    out = tmp_path_factory.mktemp("stress_runs") / "reference"
    assert optimize(out, *FULL) == 0
    return out


def records(run: Path) -> list[dict]:
    """log.jsonl without the wall-clock fields."""
    out = []
    for line in (run / "log.jsonl").read_text().splitlines():
        rec = json.loads(line)
        out.append({k: v for k, v in rec.items() if k not in TIME_KEYS})
    return out


def assert_same_numbers(run: Path, ref: Path, stopped_at: tuple[int, int] | None = None) -> None:
    """Bit-identical optimisation result: every log number, every map, the pose, the final renders.

    ``stopped_at``: ``(stage, iteration)`` where a shorter run ended before it was resumed to the full count; a
    stage's end is always a held-out check, so that run has one check (and one ``holdout_mse``) more than the
    uninterrupted run, and the rest must agree."""
    extra = {"holdout_mse"} if stopped_at else set()
    assert [{k: v for k, v in r.items() if k not in extra} for r in records(run)] == \
        [{k: v for k, v in r.items() if k not in extra} for r in records(ref)]
    a, b = json.loads((run / "summary.json").read_text())["holdout"], json.loads((ref / "summary.json").read_text())["holdout"]
    if stopped_at and (a["chosen"]["stage"], a["chosen"]["iteration"]) == stopped_at:
        # the shorter run's end-of-stage check won: a lower score than anything the uninterrupted run checked, so
        # the result is that iterate and cannot equal the reference's maps (the trajectory above does)
        assert a["chosen"]["mse"] < b["chosen"]["mse"]
        return
    for name in ("albedo", "metallic", "roughness", "transmittance", "displacement"):
        np.testing.assert_array_equal(np.load(run / "maps" / f"{name}.npy"), np.load(ref / "maps" / f"{name}.npy"))
    assert json.loads((run / "pose.json").read_text()) == json.loads((ref / "pose.json").read_text())
    a, b = json.loads((run / "summary.json").read_text()), json.loads((ref / "summary.json").read_text())
    for k in ("iterations", "initial_loss_high_spp", "final_loss_high_spp", "final_loss_per_view",
              "nonfinite_grads_total"):
        assert a[k] == b[k], k
    # the held-out views chose the same iterate by the same scores (the fast preset's selection survives the kill)
    def untimed(checks):
        return [{k: v for k, v in c.items() if k not in ("seconds", "check_seconds", "best")} for c in checks
                if (c["stage"], c["iteration"]) != stopped_at]

    assert untimed(a["holdout"]["checks"]) == untimed(b["holdout"]["checks"])
    assert (a["holdout"]["chosen"]["stage"], a["holdout"]["chosen"]["iteration"]) == \
        (b["holdout"]["chosen"]["stage"], b["holdout"]["chosen"]["iteration"])
    assert a["pose_search"]["chosen_deg"] == b["pose_search"]["chosen_deg"]
    with np.load(run / "renders.npz") as ra, np.load(ref / "renders.npz") as rb:
        np.testing.assert_array_equal(ra["final"], rb["final"])


def snapshot(folder: Path) -> dict[str, tuple[str, int]]:
    """SHA-256 and mtime (ns) of every file below ``folder``."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            out[str(p.relative_to(folder))] = (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
    return out


def one_error_line(capfd) -> str:
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    assert err[0].startswith("camo: error: "), err
    return err[0]


# =============================================================================================
# killed runs


def test_sigkill_after_the_first_checkpoint_then_resume_is_bit_exact(reference, tmp_path):
    """Hard case: a real ``camo optimize`` process SIGKILLed as soon as its first checkpoint (Stage 1,
    iteration 2 of 4) appears, then ``--resume`` with the same arguments.

    Expected: the killed process left no summary (it really died mid-run); the resumed run ends with
    exactly the numbers of the uninterrupted run (log records, maps, pose, final renders), with one
    log record per iteration (records written after the checkpoint but before the kill are replaced).
    """
    from optimizer.assets.rundir import staging_dir

    out = tmp_path / "killed"
    part = staging_dir(out)  # where the unfinished run writes (the run directory appears when it finished)
    cmd = [sys.executable, "-m", "camo.cli", "optimize", "gravel", "--out", str(out), *TINY, *FULL]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=dict(os.environ))
    deadline = time.monotonic() + 300
    try:
        while not (part / "checkpoint.npz").exists():
            assert proc.poll() is None, f"camo exited ({proc.returncode}) early: {proc.stderr.read()}"
            assert time.monotonic() < deadline, "no checkpoint within 300 s"
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists() and not (part / "summary.json").exists(), \
        "the run finished before the kill: nothing was tested"
    with np.load(part / "checkpoint.npz") as ck:
        killed_at = (int(ck["stage"]), int(ck["iteration"]))
    assert killed_at[0] == 1 and killed_at[1] < 4
    logged = len((part / "log.jsonl").read_text().splitlines())
    assert optimize(out, *FULL, "--resume") == 0
    assert_same_numbers(out, reference)
    print(f"STRESS sigkill: checkpoint at stage {killed_at[0]} iteration {killed_at[1]}, {logged} log records "
          f"at the kill, resumed to {len(records(out))} records, identical to the uninterrupted run")


def test_kill_inside_stage2_then_resume_is_bit_exact(reference, tmp_path):
    """Hard case: a run stopped after its first Stage 2 step (checkpoint of stage 2: pseudo ground truths,
    Adam state, the Stage 1 result) and resumed to the full Stage 2 count.

    Expected: the same numbers as the uninterrupted run, Stage 1 and Stage 2 records alike. The stopped run's
    Stage 2 ended at step 1, and a stage's end is a held-out check, so the resumed run has one check more; if that
    check scored best, the result is that iterate (assert_same_numbers says so) -- a real kill resumes exactly.
    """
    out = tmp_path / "stage2"
    assert optimize(out, "--iterations", "4", "--stage2-iterations", "1") == 0
    with np.load(out / "checkpoint.npz") as ck:
        assert int(ck["stage"]) == 2 and int(ck["iteration"]) == 1
    assert optimize(out, *FULL, "--resume") == 0
    assert_same_numbers(out, reference, stopped_at=(2, 1))


def test_small_iteration_count_then_resume_to_the_full_count(reference, tmp_path, capfd):
    """Hard case: the README's workflow with the default stages (1 and 2): ``camo optimize`` with a small
    ``--iterations`` (2), then ``--resume`` with the full count (4).

    Expected: either the numbers of the uninterrupted 4-iteration run, or -- if a finished Stage 1 cannot be
    extended -- a one-line error (exit 2) that leaves the run directory untouched. BUG (optimizer/optimise/run.py):
    the first run's Stage 2 checkpoint makes the resume skip Stage 1 silently; it exits 0 with the 2-iteration
    Stage 1 result, while config.toml now records ``iterations = 4``.
    """
    out = tmp_path / "short"
    assert optimize(out, "--iterations", "2", "--stage2-iterations", "2") == 0
    before = snapshot(out)
    capfd.readouterr()
    code = optimize(out, *FULL, "--resume")
    if code == 2:
        one_error_line(capfd)
        assert snapshot(out) == before
        return
    assert code == 0
    assert_same_numbers(out, reference)


def test_resume_after_a_torn_last_log_line(reference, tmp_path):
    """Hard case: log.jsonl ends in half a JSON record (disk full or power loss while appending), then
    ``--resume``.

    Expected: the resume succeeds and rewrites the log from the checkpoint (the torn record was never
    covered by a checkpoint), ending with the uninterrupted run's numbers. BUG (optimizer/optimise/run.py
    ``_read_log``): ``json.loads`` of the torn line raises JSONDecodeError -- a traceback, exit 1.
    """
    out = tmp_path / "torn"
    shutil.copytree(reference, out)
    with open(out / "log.jsonl", "a", encoding="utf-8") as fh:
        fh.write('{"iteration": 3, "stage": 2, "lo')
    assert optimize(out, *FULL, "--resume") == 0
    assert_same_numbers(out, reference)


# =============================================================================================
# corrupt inputs: one error line, exit 2, earlier results untouched


def _write(path: Path, data: bytes | str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    path.write_bytes(data)
    return path


def _real_glb(path: Path) -> bytes:
    import trimesh

    trimesh.creation.box().export(path)
    return path.read_bytes()


def _mesh_case(kind: str, d: Path) -> Path:
    if kind == "garbage_obj":
        return _write(d / "m.obj", os.urandom(3000))
    if kind == "empty_obj":
        return _write(d / "m.obj", b"")
    if kind == "nan_vertex_obj":
        return _write(d / "m.obj", "v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 2 3 4\nf 1 3 4\n")
    if kind == "degenerate_only_obj":
        return _write(d / "m.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nf 1 1 2\n")
    if kind == "index_out_of_range_obj":
        return _write(d / "m.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    if kind == "truncated_glb":
        full = _real_glb(d / "full.glb")
        return _write(d / "m.glb", full[: len(full) // 2])
    if kind == "ply_header_only":
        return _write(d / "m.ply", "ply\nformat ascii 1.0\nelement vertex 1000\nproperty float x\nproperty float y\n"
                      "property float z\nelement face 10\nproperty list uchar int vertex_indices\nend_header\n")
    raise AssertionError(kind)


def _pack(d: Path, obj: str = 'primitive = "utility_box"', env: str = 'builtin = "gravel"', extra: str = "") -> Path:
    return _write(d / "pack.toml", f'name = "stress"\n[object]\n{obj}\n[environment]\n{env}\n{extra}')


@pytest.fixture
def guarded(reference):
    """The reference run directory, with a check that the test leaves every file as it was."""
    before = snapshot(reference)
    yield reference
    assert snapshot(reference) == before, "an earlier run directory was modified"


@pytest.mark.parametrize("kind", ["garbage_obj", "empty_obj", "nan_vertex_obj", "degenerate_only_obj",
                                  "index_out_of_range_obj", "truncated_glb", "ply_header_only"])
def test_corrupt_mesh_is_one_line_error_and_keeps_earlier_results(kind, guarded, tmp_path, capfd):
    """Hard case: a scene pack whose mesh is random bytes, empty, has a NaN vertex, only degenerate faces,
    an index past the vertex list, a GLB cut in half, or a PLY header without data, optimised into an
    existing run directory with ``--overwrite``.

    Expected: exit 2, one stderr line ``camo: error: ...``, the earlier run directory unchanged.
    """
    mesh = _mesh_case(kind, tmp_path)
    pack = _pack(tmp_path, obj=f'mesh = "{mesh.name}"')
    capfd.readouterr()
    assert main(["optimize", str(pack), "--out", str(guarded), "--overwrite", *TINY]) == 2
    line = one_error_line(capfd)
    assert "mesh" in line.lower()


def _exr(path: Path, img: np.ndarray) -> Path:
    from camo_base.imaging import save_exr

    save_exr(path, img.astype(np.float32))
    return path


def _panorama_case(kind: str, d: Path) -> Path:
    good = np.ones((16, 32, 3), np.float32)
    if kind == "garbage_exr":
        return _write(d / "p.exr", os.urandom(4000))
    if kind == "truncated_exr":
        full = _exr(d / "full.exr", np.random.default_rng(0).random((64, 128, 3))).read_bytes()
        return _write(d / "p.exr", full[: len(full) // 2])
    if kind == "nan_exr":
        bad = good.copy()
        bad[3, 4, 1] = np.nan
        return _exr(d / "p.exr", bad)
    if kind == "inf_exr":
        bad = good.copy()
        bad[3, 4, 0] = np.inf
        return _exr(d / "p.exr", bad)
    if kind == "negative_exr":
        bad = good.copy()
        bad[0, 0] = -1.0
        return _exr(d / "p.exr", bad)
    if kind == "not_equirect_exr":
        return _exr(d / "p.exr", np.ones((16, 16, 3)))
    if kind == "garbage_hdr":
        return _write(d / "p.hdr", b"#?RADIANCE\n" + os.urandom(500))
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["garbage_exr", "truncated_exr", "nan_exr", "inf_exr", "negative_exr",
                                  "not_equirect_exr", "garbage_hdr"])
def test_corrupt_panorama_is_one_line_error_and_keeps_earlier_results(kind, guarded, tmp_path, capfd):
    """Hard case: a panorama environment that is random bytes, an EXR cut in half, an EXR with a NaN, +Inf or
    negative pixel, a square (not 2:1 equirect) EXR, or a broken Radiance .hdr.

    Expected: exit 2, one stderr line, the earlier run directory unchanged.
    """
    pano = _panorama_case(kind, tmp_path)
    pack = _pack(tmp_path, env=f'panorama = "{pano.name}"')
    capfd.readouterr()
    assert main(["optimize", str(pack), "--out", str(guarded), "--overwrite", *TINY]) == 2
    one_error_line(capfd)


PACK_CASES = {
    "toml_syntax": 'name = "x"\n[object\nprimitive = "vase"\n',
    "binary": None,
    "nan_size": 'name = "x"\n[object]\nprimitive = "vase"\nsize = nan\n[environment]\nbuiltin = "gravel"\n',
    "inf_translation": 'name = "x"\n[object]\nprimitive = "vase"\ntranslation = [inf, 0.0]\n'
                       '[environment]\nbuiltin = "gravel"\n',
    "unknown_key": 'name = "x"\n[object]\nprimitive = "vase"\ncolour = "red"\n[environment]\nbuiltin = "gravel"\n',
    "albedo_out_of_range": 'name = "x"\n[object]\nprimitive = "vase"\n[environment]\nbuiltin = "gravel"\n'
                           '[material]\nalbedo = [2.0, 0.5, -0.1]\n',
    "camera_inside_object": 'name = "x"\n[object]\nprimitive = "vase"\nsize = 2.0\n[environment]\nbuiltin = "gravel"\n'
                            '[cameras]\nradius = 0.5\n',
    "missing_environment": 'name = "x"\n[object]\nprimitive = "vase"\n',
    "wrong_type": 'name = "x"\n[object]\nprimitive = "vase"\n[environment]\nbuiltin = "gravel"\n'
                  '[render]\nspp = "many"\n',
}


@pytest.mark.parametrize("kind", sorted(PACK_CASES))
def test_corrupt_scene_pack_is_one_line_error_and_keeps_earlier_results(kind, guarded, tmp_path, capfd):
    """Hard case: a scene pack with broken TOML, random bytes, NaN / Inf numbers, an unknown key, an albedo
    outside [0, 1], cameras inside the object, no environment, or a string where a number belongs.

    Expected: exit 2, one stderr line, the earlier run directory unchanged.
    """
    text = PACK_CASES[kind]
    pack = _write(tmp_path / "pack.toml", os.urandom(600) if text is None else text)
    capfd.readouterr()
    assert main(["optimize", str(pack), "--out", str(guarded), "--overwrite", *TINY]) == 2
    one_error_line(capfd)


def _corrupt_checkpoint(kind: str, path: Path) -> None:
    raw = path.read_bytes()
    if kind == "garbage":
        path.write_bytes(os.urandom(len(raw)))
        return
    if kind == "truncated":
        path.write_bytes(raw[: len(raw) // 2])
        return
    with np.load(path) as z:
        st = {k: z[k].copy() for k in z.files}
    if kind == "missing_key":
        del st["value/albedo"]
    elif kind == "wrong_shape":
        st["value/albedo"] = st["value/albedo"][:5]
    elif kind == "nan_values":
        st["value/albedo"][...] = np.nan
    elif kind == "bad_iteration":
        st["iteration"] = np.array("three")
    with open(path, "wb") as fh:
        np.savez(fh, **st)


@pytest.mark.parametrize("kind", ["garbage", "truncated", "missing_key", "wrong_shape", "nan_values", "bad_iteration"])
def test_corrupt_checkpoint_is_one_line_error_and_keeps_the_run(kind, reference, tmp_path, capfd):
    """Hard case: ``--resume`` of a finished run whose checkpoint.npz is random bytes, cut in half, or a
    valid archive with the right configuration fingerprint but a missing array, a wrongly shaped array,
    NaN parameters or a non-numeric iteration count.

    Expected: exit 2, one stderr line, every file of the run directory (including the checkpoint) unchanged.
    BUG (optimizer/optimise/run.py, adam.py, stage1.py): only unreadable archives are caught; a missing key
    (KeyError), a wrong shape (ValueError after config.toml and log.jsonl were rewritten) and a bad
    iteration (ValueError) are tracebacks, and NaN parameters are accepted silently (exit 0).
    """
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    _corrupt_checkpoint(kind, run / "checkpoint.npz")
    before = snapshot(run)
    capfd.readouterr()
    code = optimize(run, *FULL, "--resume")
    assert code == 2
    one_error_line(capfd)
    assert snapshot(run) == before


def _torch_file(path: Path, obj) -> Path:
    import torch

    torch.save(obj, path)
    return path


def _weights_case(kind: str, d: Path) -> list[str]:
    import torch

    if kind == "lpips_garbage":
        return ["--lpips-weights", str(_write(d / "alexnet-owt-7be5be79.pth", os.urandom(5000)))]
    if kind == "lpips_truncated":
        p = _torch_file(d / "full.pth", {"features.0.weight": torch.zeros(64, 3, 11, 11)})
        return ["--lpips-weights", str(_write(d / "alexnet-owt-7be5be79.pth", p.read_bytes()[:3000]))]
    if kind == "lpips_wrong_keys":
        return ["--lpips-weights", str(_torch_file(d / "alexnet-owt-7be5be79.pth", {"conv1.weight": torch.zeros(3)}))]
    if kind == "lpips_wrong_shape":
        sd = {"features.0.weight": torch.zeros(64, 3, 3, 3), "features.0.bias": torch.zeros(64)}
        return ["--lpips-weights", str(_torch_file(d / "alexnet-owt-7be5be79.pth", sd))]
    if kind == "lpips_not_a_state_dict":
        return ["--lpips-weights", str(_torch_file(d / "alexnet-owt-7be5be79.pth", [1, 2, 3]))]
    if kind == "inception_garbage":
        return ["--inception-weights", str(_write(d / "inception.pth", os.urandom(5000)))]
    if kind == "inception_empty":
        return ["--inception-weights", str(_write(d / "inception.pth", b""))]
    if kind == "inception_wrong_keys":
        return ["--inception-weights", str(_torch_file(d / "inception.pth", {"features.0.weight": torch.zeros(1)}))]
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["lpips_garbage", "lpips_truncated", "lpips_wrong_keys", "lpips_wrong_shape",
                                  "lpips_not_a_state_dict", "inception_garbage", "inception_empty",
                                  "inception_wrong_keys"])
def test_corrupt_weights_are_one_line_error_before_any_output(kind, guarded, tmp_path, capfd):
    """Hard case: ``camo evaluate`` of a finished run with an LPIPS trunk or Inception weight file that is
    random bytes, a torch archive cut short, empty, not a state dict, or a state dict with foreign keys or
    wrong shapes.

    Expected: exit 2, one stderr line, no evaluation output written, the run directory unchanged.
    """
    out = tmp_path / "eval"
    args = _weights_case(kind, tmp_path)
    capfd.readouterr()
    code = main(["evaluate", str(guarded), "--out", str(out), "--views", "1", "--spp", "4", "--quiet", *args])
    assert code == 2
    one_error_line(capfd)
    assert not out.exists() or not any(out.rglob("*"))
