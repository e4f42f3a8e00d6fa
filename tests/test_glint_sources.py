"""bench/glint_sources.py: the glint count on known 8-bit renders, and the object/other split of bright pixels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


def make_eval(write_eval_renders, ev: Path) -> None:
    bg = np.full((32, 32, 3), 100, np.uint8)
    bg[0, :8] = 150  # 8 of 1024 pixels: the 99.5th percentile is the 150 level (linear 0.311)
    img = bg.copy()
    img[10:20, 10:20] = 120  # the object: 100 pixels, brighter than the background but not a glint
    img[12, 12:15] = 255  # 3 glints: linear 1.0 > 2 x 0.311
    img[14, 12:14] = 200  # 2 pixels above the percentile but below twice it (linear 0.586 < 0.622)
    mask = np.zeros((32, 32), np.uint8)
    mask[10:20, 10:20] = 255
    write_eval_renders(ev, bg, img, mask, run="box")


def test_glint_pixels_count_only_object_pixels_above_twice_the_percentile(tmp_path, capsys, bench_module,
                                                                         write_eval_renders):
    gs = bench_module("glint_sources")
    ev = tmp_path / "ev"
    make_eval(write_eval_renders, ev)
    recs = json.loads((ev / "renders.json").read_text())
    assert gs.glint_pixels(ev, recs) == (6, 200)  # 3 per view, of 100 object pixels per view
    assert gs.main(["--eval", str(ev)]) == 0
    row = capsys.readouterr().out.splitlines()[-1].split()
    # sparkle: the 3 glints and the 2 moderately bright pixels exceed the 150 level in each view
    assert row[0] == "box" and float(row[1]) == pytest.approx(5.0) and row[2:] == ["6", "/", "200"]


def test_bright_pixels_are_split_into_object_and_other(tmp_path, capsys, bench_module):
    """Two emitting rectangles side by side: only the object's (radiance 5) exceeds the threshold."""
    gs = bench_module("glint_sources")
    (tmp_path / "scene.xml").write_text("""<scene version="3.0.0">
  <shape type="rectangle" id="ground">
    <transform name="to_world"><scale x="1" y="2" z="1"/><translate x="1"/></transform>
    <emitter type="area"><rgb name="radiance" value="0.1"/></emitter>
  </shape>
  <shape type="rectangle" id="object">
    <transform name="to_world"><scale x="1" y="2" z="1"/><translate x="-1"/></transform>
    <emitter type="area"><rgb name="radiance" value="5"/></emitter>
  </shape>
  <sensor type="orthographic">
    <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/>
      <scale x="2" y="2"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
      <rfilter type="box"/></film>
  </sensor>
</scene>""")
    assert gs.main([str(tmp_path), "--spp", "4", "--depths", "1,2", "--threshold", "1"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[2:]]
    # the object is the left half of the 16 x 16 frame (the right half the dim "ground")
    assert rows == [["1", "128", "0"], ["2", "128", "0"]]


def test_bad_input_exits_2(tmp_path, bench_module, write_eval_renders):
    gs = bench_module("glint_sources")
    make_eval(write_eval_renders, tmp_path / "ev")
    for argv in ([], ["--eval", str(tmp_path)], [str(tmp_path)], ["--eval", str(tmp_path / "ev"), "--depths", "a"]):
        with pytest.raises(SystemExit) as e:
            gs.main(argv)
        assert e.value.code == 2
