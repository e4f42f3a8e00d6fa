"""One registry per concept, and the worked examples of CONTRIBUTING.md ("Adding a baseline / a metric / a BSDF map").

Each example adds one thing the way CONTRIBUTING.md says -- a baseline module, a metric module, a BSDF map record --
in a fresh interpreter (the module is found as if its file were in the package: its folder is added to the package's
search path before the registry is read; the map record is added to the registry before anything reads it) and
checks that it is seen everywhere: the command-line help, the run spec's validation, a run, the evaluation's
columns, the report and the docs' generated tables. No other file is edited for any of them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The worked example of "Adding a baseline" (CONTRIBUTING.md): one module in optimizer/optimise/baselines/.
BASELINE_MODULE = '''
"""A grey object: albedo = the mean background colour of all views (a worked example)."""

import dataclasses

import numpy as np

from optimizer.optimise.baselines.common import BaselineOptions, Setup, painted_values, to_albedo
from optimizer.optimise.method import Method


@dataclasses.dataclass
class GreyOptions(BaselineOptions):
    brightness: float = 1.0  # a factor on the mean colour


def compute(setup: Setup, opts: GreyOptions, progress: bool):
    mean = setup.targets.background.reshape(-1, 3).mean(0) * opts.brightness
    r = setup.app.map_resolution
    albedo = np.broadcast_to(to_albedo(setup, mean, opts.albedo_mode), (r, r, 3))
    return painted_values(setup, albedo), [], {"mean_colour": [float(x) for x in mean]}


METHODS = (Method("grey", "mean background colour everywhere (a worked example)", options=GreyOptions,
                  compute=compute),)
'''

#: The worked example of "Adding a metric": one module in evaluation/metrics/ (a weight-free metric).
METRIC_MODULE = '''
"""Mean absolute difference of the sRGB values (a worked example)."""

import torch

from evaluation.metrics._common import ImageLike, Metric, plain, prepare_pair


def mean_abs(x: ImageLike, y: ImageLike) -> torch.Tensor:
    """Mean |x - y| per image pair ``(N,)``, sRGB in [0, 1]; 0 for identical images."""
    x, y = prepare_pair(x, y, "mad", min_size=1)
    return (x - y).abs().mean(dim=(1, 2, 3))


METRICS = (Metric("mad", plain(mean_abs), False, "1", "[0, 1]", "mean absolute sRGB difference", "MAD"),)
'''

#: The worked example of "Adding a BSDF map": one record in optimizer/scenes/bsdf_maps.py's MAPS.
MAP_RECORD = '''
from optimizer.scenes import bsdf_maps as B

B.MAPS["clearcoat"] = B.BsdfMap(
    "clearcoat", 1, 0.0, "clearcoat", "clear-coat layer weight", switches=("bsdf",),
    gltf=B.GltfSlot("clearcoatTexture", 0, "clearcoat", "KHR_materials_clearcoat", "clearcoatFactor", default=0.0),
    mtl="Pc", absent=0.0)
'''

TINY = ["--views", "3", "--resolution", "24", "--map-resolution", "32", "--target-vertices", "1500",
        "--target-spp", "8", "--quiet", "--threads", "1"]
TINY_OURS = [*TINY, "--iterations", "2", "--displacement-resolution", "16", "--spp", "2", "--stages", "1",
             "--holdout-views", "0", "--pose-search", "0", "--warm-start", "off"]


def _in_package(package: str, folder: Path) -> str:
    """Code that makes ``folder`` part of ``package`` (as if its files were in the package's directory)."""
    return textwrap.dedent(f'''
        import importlib.abc, importlib.machinery, sys

        class _Extend(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path, target=None):
                if name != {package!r}:
                    return None
                spec = importlib.machinery.PathFinder.find_spec(name, path)
                spec.submodule_search_locations.append({str(folder)!r})
                return spec

        sys.meta_path.insert(0, _Extend())
    ''')


#: A helper of the example scripts: the help text of a command, on one line.
HELP_OF = textwrap.dedent('''
    def help_of(*argv):
        import contextlib, io
        from camo.cli import main

        text = io.StringIO()
        with contextlib.redirect_stdout(text):
            main([*argv, "--help"])
        return " ".join(text.getvalue().split())
''')


def _run(tmp_path: Path, setup: str, body: str) -> dict:
    """Run ``setup`` then ``body`` in a fresh interpreter; ``body`` fills the dict ``out`` (returned)."""
    script = tmp_path / "example.py"
    script.write_text(f"import json, sys\nsys.path.insert(0, {str(ROOT)!r})\n{setup}\n{HELP_OF}\nout = {{}}\n"
                      f"{textwrap.dedent(body)}\nprint('RESULT ' + json.dumps(out))\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=900,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def test_the_docs_tables_are_generated_from_the_registries():
    from camo.docs import update

    assert update(check=True) == [], "run `python -m camo.docs` (a registry changed, its docs tables did not)"


def test_the_method_labels_name_registered_methods():
    """Table II's labels (optimizer.assets.conditions, below the optimiser) and the method registry cannot drift."""
    from optimizer.assets.conditions import METHOD_LABELS
    from optimizer.optimise.methods import METHOD_NAMES

    assert set(METHOD_LABELS) <= set(METHOD_NAMES)


def test_worked_example_a_new_baseline_is_one_module(tmp_path):
    folder = tmp_path / "baselines"
    folder.mkdir()
    (folder / "grey.py").write_text(BASELINE_MODULE)
    run, ev = tmp_path / "run", tmp_path / "eval"
    out = _run(tmp_path, _in_package("optimizer.optimise.baselines", folder), f'''
        from camo.cli import main
        from camo.docs import methods_table
        from camo_base.errors import CamoError
        from optimizer.optimise.spec import RunSpec

        out["help"] = help_of("optimize")
        out["docs"] = methods_table()
        try:
            RunSpec.from_options({{"scene": "gravel", "method": "grey", "iterations": 3}})
        except CamoError as exc:
            out["refused"] = str(exc)
        out["optimize"] = main(["optimize", "gravel", "--method", "grey", "--out", {str(run)!r}, *{TINY!r}])
        out["evaluate"] = main(["evaluate", {str(run)!r}, "--out", {str(ev)!r}, "--metrics", "psnr", "--spp", "4",
                                "--views", "2", "--quiet"])
    ''')
    assert "grey: mean background colour everywhere (a worked example)" in out["help"]
    assert "| `grey` | grey | mean background colour everywhere" in out["docs"]
    assert "iterations does not apply to method grey" in out["refused"]
    assert out["optimize"] == 0 and out["evaluate"] == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["method"] == "grey"
    cfg = (run / "config.toml").read_text()
    assert 'method = "grey"' in cfg and "brightness = 1.0" in cfg and "mean_colour" in cfg
    assert "| grey |" in (ev / "report.md").read_text()  # its Table II row (labelled by its name)


def test_worked_example_a_new_metric_is_one_module(tmp_path):
    folder = tmp_path / "metrics"
    folder.mkdir()
    (folder / "mad.py").write_text(METRIC_MODULE)
    run, ev = tmp_path / "run", tmp_path / "eval"
    out = _run(tmp_path, _in_package("evaluation.metrics", folder), f'''
        from camo.cli import main
        from camo.docs import metrics_table
        from camo_base.tables import read_parquet
        from evaluation.metrics import METRICS, WEIGHT_FREE, compute_metrics
        import numpy as np

        out["help"] = help_of("evaluate")
        out["docs"] = metrics_table()
        out["weight_free"] = list(WEIGHT_FREE)
        a = np.zeros((8, 8, 3), np.float32)
        out["value"] = compute_metrics(a, a + 0.25, ["mad"])["mad"]
        out["optimize"] = main(["optimize", "gravel", "--method", "transparent", "--out", {str(run)!r}, *{TINY!r}])
        out["evaluate"] = main(["evaluate", {str(run)!r}, "--out", {str(ev)!r}, "--spp", "4", "--views", "2",
                                "--resolution", "64", "--quiet"])  # (the default metrics)
        df = read_parquet({str(ev / "metrics.parquet")!r})
        out["columns"] = list(df.columns)
        out["mad"] = float(df.loc[df["region"] == "crop", "mad"].mean())
    ''')
    assert "mad" in out["help"] and "mad" in out["weight_free"]
    assert "| `mad` | lower | 1 | [0, 1] | mean absolute sRGB difference | no |" in out["docs"]
    assert out["value"] == pytest.approx(0.25)
    assert out["optimize"] == 0 and out["evaluate"] == 0
    assert {"mad", "seconds_mad"} <= set(out["columns"]) and 0 < out["mad"] < 1
    report = (ev / "report.md").read_text()
    assert "MAD↓" in report  # a Table II column


def test_worked_example_a_new_bsdf_map_is_one_record(tmp_path):
    run, ev = tmp_path / "run", tmp_path / "eval"
    out = _run(tmp_path, MAP_RECORD, f'''
        from camo.cli import main
        from camo.docs import maps_table
        from optimizer.assets.asset import load_asset
        from optimizer.assets.rundir import open_run
        from optimizer.optimise.spec import RunSpec

        out["help"] = help_of("optimize")
        out["docs"] = maps_table()
        spec = RunSpec.from_options({{"scene": "gravel", "init": "clearcoat=0.3"}})
        out["pack"] = spec.pack.material.clearcoat
        out["optimize"] = main(["optimize", "gravel", "--out", {str(run)!r}, *{TINY_OURS!r}, "--init", "clearcoat=0.3"])
        asset = open_run({str(run)!r}).asset()
        out["run_map"] = float(asset.maps["clearcoat"].mean())
        glb = load_asset({str(run / "result.glb")!r})
        out["glb_map"] = float(glb.maps["clearcoat"].mean())
        obj = load_asset({str(run / "result.obj")!r})
        out["obj_map"] = float(obj.maps["clearcoat"].mean())
        out["evaluate"] = main(["evaluate", {str(run)!r}, "--out", {str(ev)!r}, "--metrics", "psnr", "--spp", "4",
                                "--views", "2", "--quiet"])
    ''')
    assert "clearcoat" in out["help"] and "| `clearcoat` | 1 | 0 | `clearcoat` | bsdf on |" in out["docs"]
    assert out["pack"] == 0.3 and out["optimize"] == 0 and out["evaluate"] == 0
    assert (run / "maps" / "clearcoat.npy").is_file() and (run / "result_clearcoat.png").is_file()
    assert abs(out["run_map"] - 0.3) < 0.1  # it starts at 0.3 and is optimised (two steps)
    assert out["glb_map"] == pytest.approx(out["run_map"], abs=2 / 255)
    assert out["obj_map"] == pytest.approx(out["run_map"], abs=2 / 255)
    glb_json = (run / "result.glb").read_bytes()
    assert b"KHR_materials_clearcoat" in glb_json and b"clearcoatTexture" in glb_json
    assert "Pc 1" in (run / "result.mtl").read_text()
