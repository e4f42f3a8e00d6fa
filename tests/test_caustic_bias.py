"""bench/caustic_bias.py: the cast shadow's mean luminance as Stage 1's soft-clamped loss sees a caustic of rare bright
samples, against the linear mean, on known renders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image


def write_eval(d: Path, spp: int, renders: dict[str, dict[str, np.ndarray]], mask: np.ndarray) -> None:
    (d / "eval_config.toml").parent.mkdir(parents=True, exist_ok=True)
    (d / "eval_config.toml").write_text(f"[evaluate]\nspp = {spp}\n")
    for run, imgs in renders.items():
        r = d / "renders" / run
        r.mkdir(parents=True)
        for kind, img in imgs.items():
            np.save(r / f"view_00_{kind}.npy", img.astype(np.float32))
        Image.fromarray((mask * 255).astype(np.uint8)).save(r / "view_00_mask.png")


def test_a_caustic_of_rare_bright_samples_is_dimmed_by_the_soft_clamp(tmp_path, capsys, bench_module):
    cb = bench_module("caustic_bias")
    bg = np.full((8, 8, 3), 0.1)
    mask = np.zeros((8, 8), bool)
    mask[:2] = True  # the object: two rows
    opaque = bg.copy()
    opaque[4:6] = 0.02  # its shadow: 16 pixels at a fifth of the ground
    converged = bg.copy()
    converged[4:6] = 0.08  # the clear body's lit shadow, converged
    low = bg.copy()
    low[4:6] = 0.0
    low[4, :2] = 0.64  # at a few spp the same energy (16 x 0.08 = 2 x 0.64) in two bright samples
    write_eval(tmp_path / "ref", 512, {"opaque": {"bg": bg, "obj": opaque}, "clear": {"bg": bg, "obj": converged}}, mask)
    write_eval(tmp_path / "low", 4, {"clear": {"bg": bg, "obj": low}}, mask)
    assert cb.main(["--ref", str(tmp_path / "ref"), "--low", str(tmp_path / "low"), "--run", "clear",
                    "--shadow-run", "opaque", "--loss-clamp", "2"]) == 0
    rows = {r.split("|")[2].strip(): [c.strip() for c in r.split("|")[1:-1]]
            for r in capsys.readouterr().out.splitlines() if r.startswith("| **mean**")}
    # columns: view, spp, px, background, opaque, linear, soft-clamped, p99
    white = 2 * 0.1  # the clamp's white point: 2 x the background's 99th percentile
    assert float(rows["512"][5]) == pytest.approx(0.08, abs=1e-3)
    assert float(rows["512"][6]) == pytest.approx(white * np.tanh(0.08 / white), abs=1e-3)  # 0.076: barely clamped
    assert float(rows["4"][5]) == pytest.approx(0.08, abs=1e-3)  # the linear mean keeps the energy
    assert float(rows["4"][6]) == pytest.approx(2 * white * np.tanh(0.64 / white) / 16, abs=1e-3)  # 0.025: dimmed
    assert float(rows["4"][4]) == pytest.approx(0.02, abs=1e-3)


def test_shadow_mask_is_the_dark_ground_outside_the_object(bench_module):
    cb = bench_module("caustic_bias")
    bg = np.ones((3, 3, 3))
    op = bg.copy()
    op[0] = 0.5  # 0.5 < 0.6: shadow
    op[1] = 0.7  # not dark enough
    obj = np.zeros((3, 3), bool)
    obj[0, 0] = True
    assert cb.shadow_mask(bg, op, obj, 0.6).sum() == 2



def test_compare_finds_where_another_run_puts_the_light(tmp_path, capsys, bench_module):
    """--compare: the bright shadow pixels of two clear runs (above the ground's 99th percentile) and their overlap; a
    run evaluated into another eval*/SCENE beside --ref is found there."""
    cb = bench_module("caustic_bias")
    bg = np.full((8, 8, 3), 0.1)
    mask = np.zeros((8, 8), bool)
    mask[:2] = True
    opaque = bg.copy()
    opaque[4:6] = 0.02  # the shadow: rows 4-5, 16 pixels
    a, b = bg.copy(), bg.copy()
    a[4:6] = 0.05
    b[4:6] = 0.05
    a[4, :4] = 0.3  # run a lights pixels 0-3 of row 4, run b pixels 2-5: 2 shared of 6
    b[4, 2:6] = 0.3
    write_eval(tmp_path / "eval" / "meadow", 512, {"opaque": {"bg": bg, "obj": opaque}, "a": {"bg": bg, "obj": a}}, mask)
    write_eval(tmp_path / "eval_later" / "meadow", 512, {"b": {"bg": bg, "obj": b}}, mask)
    assert cb.main(["--ref", str(tmp_path / "eval" / "meadow"), "--run", "a", "--shadow-run", "opaque",
                    "--compare", "b"]) == 0
    row = next(r for r in capsys.readouterr().out.splitlines() if r.startswith("| **mean** | b |"))
    _, _, bright_a, bright_b, iou, corr = [c.strip() for c in row.split("|")[1:-1]]
    assert (float(bright_a), float(bright_b), float(iou)) == (0.25, 0.25, 0.33)
    x, y = cb.luminance(a)[4:6].ravel(), cb.luminance(b)[4:6].ravel()
    assert float(corr) == pytest.approx(np.corrcoef(x, y)[0, 1], abs=1e-3)
    with pytest.raises(SystemExit, match="no renders of missing"):
        cb.main(["--ref", str(tmp_path / "eval" / "meadow"), "--run", "a", "--shadow-run", "opaque",
                 "--compare", "missing"])
