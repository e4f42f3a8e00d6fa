"""The Stage 1 loss-term weights (``--detail-match W``, ``--tint-match W``) and the maps' coarse level (``--coarse-grid
K``): parsed into the spec, at their defaults when not given (the terms off, the level 1 in the fast preset), refused out of range or by a method without Stage 1, and a bad value is one
line on the CLI. The terms themselves are tested in ``test_detail_term.py``, ``test_tint_term.py`` and
``test_coarse_level.py``."""
from __future__ import annotations

import numpy as np
import pytest

from camo_base.errors import CamoError

WEIGHTS = [("detail_match", 8.0), ("tint_match", 4.0), ("coarse_grid", 4)]
#: the value a field takes when not given (the fast preset's): the loss terms off, one coarse cell
DEFAULTS = {"detail_match": 0.0, "tint_match": 0.0, "coarse_grid": 1}


@pytest.mark.parametrize(("field", "value"), WEIGHTS)
def test_option_parsing_and_errors(field, value):
    from optimizer.optimise.spec import RunSpec

    assert getattr(RunSpec.from_options({"scene": "meadow", field: value}).stage1, field) == value
    assert getattr(RunSpec.from_options({"scene": "meadow"}).stage1, field) == DEFAULTS[field]
    for bad in (-1, 1e4, "lots"):
        with pytest.raises(CamoError, match=field.replace("_", ".")) as e:
            RunSpec.from_options({"scene": "meadow", field: bad}).validate()
        assert "\n" not in str(e.value)
    with pytest.raises(CamoError, match="does not use"):  # a method without Stage 1 ignores it: refused
        RunSpec.from_options({"scene": "meadow", "method": "mean", field: value}).validate()


@pytest.mark.parametrize(("field", "value"), WEIGHTS)
def test_cli_rejects_a_negative_weight_in_one_line(field, value, capsys):
    from camo.cli import main

    flag = "--" + field.replace("_", "-")
    try:
        rc = main(["optimize", "meadow", "--out", "/nonexistent/x", flag, "-2"])
    except SystemExit as e:
        rc = e.code
    assert rc not in (0, None)
    err = capsys.readouterr().err.strip().splitlines()
    assert err and flag in err[-1]


def test_training_windows_are_one_window_bounding_every_views_domain():
    """Stage 1's training windows: by default every view gets the bounding box of all views' loss domains (one crop
    window, so one set of kernels: tests/test_projective.py); per view, each domain's own box; full frames for
    ``domain = "frame"``; an empty domain keeps a 1 x 1 window."""
    from optimizer.optimise.stage1 import training_windows

    dom = np.zeros((3, 10, 12), np.float32)
    dom[0, 2:5, 3:7] = 1.0
    dom[1, 6:9, 1:4] = 0.5
    assert training_windows(dom, "object+shadow") == [(1, 2, 7, 9)] * 3  # (x0, y0, x1, y1), end exclusive
    assert training_windows(dom, "object+shadow", shared=False) == [(3, 2, 7, 5), (1, 6, 4, 9), (0, 0, 1, 1)]
    assert training_windows(dom, "frame") is None
    assert training_windows(np.zeros((2, 4, 4)), "object+shadow") == [(0, 0, 1, 1)] * 2
