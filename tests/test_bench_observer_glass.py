"""bench/observer_glass.py: the outline-sharpness measure of docs/results/observer.md ("Room's Transparent cell")."""

from __future__ import annotations

import math

import numpy as np
import pytest


def _edge(width: float) -> np.ndarray:
    """A 64 x 64 map: 0 left, 1 right, a linear ramp of ``width`` px between (0: a step)."""
    x = np.arange(64, dtype=np.float64) - 31.5
    row = np.clip(x / width + 0.5, 0.0, 1.0) if width > 0 else (x > 0).astype(np.float64)
    return np.tile(row, (64, 1))


def test_a_step_reads_the_same_at_both_scales_and_a_penumbra_the_ratio_of_the_scales(bench_module):
    og = bench_module("observer_glass")
    s1, s2 = og.FINE_PX, 2.4
    step = _edge(0)
    ratio = og.scale_gradient(step, s1).max() / og.scale_gradient(step, s2).max()
    assert og.scale_gradient(step, s2).max() == pytest.approx(1 / math.sqrt(2 * math.pi), rel=0.02)
    # 1 in the continuum; 0.82 for a one-pixel step sampled at 0.7 px (the kernel is undersampled there)
    assert 0.75 < ratio <= 1.0
    blur = _edge(24)  # a penumbra 10 times the coarser scale
    ratio_blur = og.scale_gradient(blur, s1).max() / og.scale_gradient(blur, s2).max()
    assert ratio_blur == pytest.approx(s1 / s2, rel=0.05)
    assert ratio > 2.5 * ratio_blur


def test_a_folder_that_is_not_a_stimulus_set_is_refused(tmp_path, bench_module, capsys):
    og = bench_module("observer_glass")
    with pytest.raises(SystemExit) as e:
        og.main(["--outline", str(tmp_path)])
    assert e.value.code == 2
    assert "not a stimulus set" in capsys.readouterr().err
