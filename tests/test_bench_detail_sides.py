"""bench/detail_sides.py: the detail ratio's two sides read from a `camo evaluate` folder's saved renders."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image


def _write_eval(tmp_path, body: np.ndarray, ground: np.ndarray) -> None:
    """One run, two views: a 16 x 16 grey frame with an 8 x 8 body; renders.json as `camo evaluate` writes it."""
    recs = []
    for v in range(2):
        d = tmp_path / "renders" / "r0"
        d.mkdir(parents=True, exist_ok=True)
        bg = np.full((16, 16, 3), 128, np.uint8)
        bg[4:12, 4:12] = ground
        obj = bg.copy()
        obj[4:12, 4:12] = body
        mask = np.zeros((16, 16), np.uint8)
        mask[4:12, 4:12] = 255
        for name, img in (("obj", obj), ("bg", bg), ("mask", mask)):
            Image.fromarray(img).save(d / f"view_{v:02d}_{name}.png")
        recs.append({"run": "r0", "view": v, "image": f"renders/r0/view_{v:02d}_obj.png",
                     "background": f"renders/r0/view_{v:02d}_bg.png", "mask": f"renders/r0/view_{v:02d}_mask.png"})
    (tmp_path / "renders.json").write_text(json.dumps(recs))


def test_sides_are_the_laplacian_energies_of_each_render(tmp_path, bench_module):
    ds = bench_module("detail_sides")
    checker = (np.indices((8, 8)).sum(0) % 2 * 255).astype(np.uint8)[..., None].repeat(3, -1)
    _write_eval(tmp_path, body=checker, ground=np.full((8, 8, 3), 128, np.uint8))
    (ex, ey, n), = ds.sides(tmp_path).values()
    # interior of the 8 x 8 mask: the 6 x 6 pixels; a 0/1 checkerboard's 8-neighbour |Laplacian| is 4 x 255 there
    assert n == 2 and ex == pytest.approx(4 * 255.0, rel=1e-4) and ey == pytest.approx(0.0, abs=1e-3)
    assert ds.sides(tmp_path, {"other"}) == {}


def test_a_folder_that_is_not_an_evaluation_is_refused(tmp_path, bench_module):
    ds = bench_module("detail_sides")
    with pytest.raises(SystemExit, match="no renders.json"):
        ds.sides(tmp_path)
