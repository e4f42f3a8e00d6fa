"""bench/bench_giveaways.py: the contact sheets (where they go, which arms they show)."""

from __future__ import annotations

import numpy as np
from PIL import Image


def test_contact_sheet_finds_arms_in_later_evaluations(tmp_path, bench_module):
    """bench_giveaways.contact_sheet: an arm evaluated later (``eval_NAME/SCENE``) is a column beside the first
    evaluation's arms, the background first and Mean last; one row per view, zoomed 3x."""
    bg_ = bench_module("bench_giveaways")
    img = np.zeros((8, 10, 3), np.uint8)
    for ev, run in (("eval", "today"), ("eval", "mean"), ("eval_later", "r5")):
        d = tmp_path / ev / "meadow" / "renders" / f"meadow-{run}"
        d.mkdir(parents=True)
        for v in range(2):
            for kind in ("bg", "obj"):
                Image.fromarray(img).save(d / f"view_{v:02d}_{kind}.png")
    dest = bg_.contact_sheet(tmp_path / "eval" / "meadow", "meadow", ["today", "r5", "missing"], tmp_path / "s.png")
    w, h = Image.open(dest).size
    assert (w, h) == (4 * (30 + 4) + 4, 22 + 2 * (24 + 4) + 4)  # background, today, r5, Mean; 2 views
    assert bg_.sheet_path(tmp_path, "caustic", "meadow", True) == tmp_path / "giveaways_caustic_meadow.png"
