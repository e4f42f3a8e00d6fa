"""bench/glint_roughness.py: the sun's direction from the emitter alone, and the mirror facet's glint per roughness."""

from __future__ import annotations

import math

import numpy as np
import pytest


def test_fibonacci_hemisphere_is_unit_and_upper(bench_module):
    gr = bench_module("glint_roughness")
    d = gr.fibonacci_hemisphere(10_000)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert (d[:, 2] > 0).all()
    assert abs(d[:, 0].mean()) < 0.01 and abs(d[:, 1].mean()) < 0.01 and d[:, 2].mean() == pytest.approx(0.5, abs=0.01)


def test_brightest_direction_finds_the_sun_disc_centre(bench_module, mi_backend):
    from optimizer.scenes.environments import sun_direction, sunsky

    gr = bench_module("glint_roughness")
    found, lum = gr.brightest_direction({"sky": sunsky(30.0, 100.0, turbidity=3.0)}, n=1_000_000)
    want = np.array(sun_direction(30.0, 100.0))
    assert math.degrees(math.acos(min(1.0, float(found @ want)))) < 0.02  # the disc is 0.27 deg in radius
    assert lum > 1e3  # the sun, not the sky (~1-10)


def test_mirror_facet_glint_falls_with_roughness(bench_module, mi_backend):
    gr = bench_module("glint_roughness")
    rep = gr.scene_report("gravel", 64, (0.0, 0.2, 1.0))
    ratios = [row[3] for row in rep["rows"]]
    assert [row[1] for row in rep["rows"]] == pytest.approx([0.035, 0.228, 1.0])
    # a near-mirror reflects the sun far above any background pixel; a fully rough facet does not
    assert ratios[0] > 100 and ratios[0] > ratios[1] > ratios[2] and ratios[2] < 1.0
    # the facet halves the angle between the sun and the camera
    cam = np.asarray(rep["view"])
    half = 0.5 * math.degrees(math.acos(float(np.clip(rep["sun"] @ cam, -1, 1))))
    assert rep["angle"] == pytest.approx(half, abs=1e-3)
    assert gr.needed(rep["rows"]) == 1.0


def test_needed_is_the_roughness_from_which_all_rougher_values_pass(bench_module):
    gr = bench_module("glint_roughness")
    rows = [(0.0, 0, 0, 50.0), (0.3, 0, 0, 0.9), (0.4, 0, 0, 1.1), (0.5, 0, 0, 0.8), (1.0, 0, 0, 0.5)]
    assert gr.needed(rows) == 0.5
    assert gr.needed([(0.0, 0, 0, 5.0), (1.0, 0, 0, 2.0)]) is None


def test_unknown_scene_is_one_line_and_exit_2(bench_module, capsys):
    gr = bench_module("glint_roughness")
    assert gr.main(["--scenes", "gravel,nowhere"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere" in err[0] and "gravel" in err[0]
