"""The interactive viewer's pieces without a browser: the panorama convention (ours -> three.js), camera attributes
(ours -> ``<model-viewer>``), Radiance files, the pinned JavaScript and its manifest entry, and the page's claims.
The browser side is tests/test_viewer_browser.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from camo.cli import main


def _threejs_uv(d_gltf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """three.js's equirectUv (src/renderers/shaders/ShaderChunk/common.glsl.js) of glTF/three directions, as image
    coordinates: u = atan(z, x) / 2pi + 1/2 (columns), and rows from the top (flipY: v = 1 is the first row)."""
    u = np.arctan2(d_gltf[..., 2], d_gltf[..., 0]) / (2 * np.pi) + 0.5
    v = np.arcsin(np.clip(d_gltf[..., 1], -1, 1)) / np.pi + 0.5
    return u, 1.0 - v


def test_panorama_turned_into_threejs_convention_looks_the_same_way():
    from evaluation.viewer import to_gltf, to_threejs_equirect
    from optimizer.scenes.panorama import equirect_directions

    h, w = 32, 64
    dirs = equirect_directions(w, h)  # ours: the world direction of every pixel
    ours = dirs.copy()  # a panorama whose pixels hold their own world direction
    three = to_threejs_equirect(ours)
    rng = np.random.default_rng(0)
    for _ in range(200):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        u, v = _threejs_uv(np.array(to_gltf(d)))
        col, row = int(u * w) % w, min(int(v * h), h - 1)
        assert np.dot(three[row, col], d) > math.cos(math.radians(8)), (d, three[row, col])
    with pytest.raises(ValueError):
        to_threejs_equirect(np.zeros((5, 10, 3)))


def test_camera_attributes_put_model_viewer_where_our_camera_is():
    from evaluation.viewer import camera_attributes, to_gltf

    rng = np.random.default_rng(1)
    for _ in range(20):
        target = rng.normal(size=3)
        origin = target + rng.normal(size=3) * 3
        a = camera_attributes(tuple(origin), tuple(target), 30.0)
        theta, phi, r = (float(x.rstrip("degm")) for x in a["camera-orbit"].split())
        t = np.array([float(x.rstrip("m")) for x in a["camera-target"].split()])
        th, ph = math.radians(theta), math.radians(phi)
        # three.js Spherical -> Vector3 (what SmoothControls does): (r sin(phi) sin(theta), r cos(phi), r sin(phi) cos(theta))
        pos = t + r * np.array([math.sin(ph) * math.sin(th), math.cos(ph), math.sin(ph) * math.cos(th)])
        assert np.allclose(pos, to_gltf(origin), atol=1e-4) and np.allclose(t, to_gltf(target), atol=1e-5)
    # a square viewer keeps the horizontal fov; a wide one gets the narrower vertical fov
    assert camera_attributes((0, -4, 1), (0, 0, 0), 30.0)["field-of-view"] == "30.0000deg"
    vf = float(camera_attributes((0, -4, 1), (0, 0, 0), 60.0, aspect=2.0)["field-of-view"].rstrip("deg"))
    assert vf == pytest.approx(math.degrees(2 * math.atan(math.tan(math.radians(30)) / 2)), abs=1e-3)


def test_radiance_files_round_trip_as_radiance(tmp_path):
    """load_hdr_image reads .hdr as radiance (imageio's opencv plugin tone-mapped it to 8 bit before)."""
    from camo_base.imaging import load_hdr_image
    from evaluation.viewer import write_hdr

    rng = np.random.default_rng(2)
    img = (rng.random((16, 32, 3)) ** 4 * 5000).astype(np.float32)
    img[3, 4] = [0.01, 0.02, 0.03]
    write_hdr(tmp_path / "a.hdr", img)
    back = load_hdr_image(tmp_path / "a.hdr")
    assert back.dtype == np.float32 and back.shape == img.shape
    rel = np.abs(back - img) / np.maximum(img.max(-1, keepdims=True), 1e-6)
    assert rel.max() < 0.01  # RGBE keeps 8 bits of mantissa per channel relative to the largest
    assert back.max() > 1000


def test_viewer_javascript_is_pinned_and_checked(tmp_path, monkeypatch):
    from evaluation.viewer import MANIFEST, VIEWER_JS, viewer_script
    from optimizer.scenes.data.manifest import load_manifest

    a = load_manifest(MANIFEST).get("model-viewer")
    assert a.kind == "script" and a.registry == "npm" and a.package == "@google/model-viewer"
    assert a.version == "4.4.0" and a.licence == "Apache-2.0" and a.pinned and a.filename == VIEWER_JS
    assert a.member == "package/dist/model-viewer-umd.min.js" and a.member_sha256 == a.sha256
    bogus = tmp_path / VIEWER_JS
    bogus.write_text("console.log('not the pinned file');")
    monkeypatch.setenv("CAMO_VIEWER_JS", str(bogus))
    assert viewer_script() is None  # a file that does not match the pin is not used
    monkeypatch.setenv("CAMO_VIEWER_JS", str(tmp_path / "absent.js"))
    assert viewer_script() is None


def test_script_entries_must_be_plain_js_and_stay_out_of_packs(tmp_path, capsys):
    from camo_base.errors import CamoError
    from optimizer.scenes.data.manifest import load_manifest

    m = tmp_path / "m.toml"
    entry = ('[[asset]]\nname = "x"\nkind = "script"\nregistry = "npm"\npackage = "@google/model-viewer"\n'
             'version = "4.4.0"\nintegrity = "sha512-' + "A" * 86 + '=="\nmember = "package/x.js"\n'
             'filename = "{fn}"\nsha256 = "TO-BE-PINNED"\nsize = "TO-BE-PINNED"\nlicence = "MIT"\n{extra}'
             '[asset.source]\ndataset = "d"\nhomepage = "h"\n')
    m.write_text(entry.format(fn="x.css", extra=""))
    with pytest.raises(CamoError, match="script"):
        load_manifest(m)
    m.write_text(entry.format(fn="x.js", extra='decode = "js-data-uri"\n'))
    with pytest.raises(CamoError, match="script"):
        load_manifest(m)
    m.write_text(entry.format(fn="x.js", extra=""))
    assert load_manifest(m).get("x").kind == "script"
    rc = main(["data", "pack", str(m), "x", "--dest", str(tmp_path), "--out", str(tmp_path / "p.toml")])
    err = capsys.readouterr().err
    assert rc == 2 and "is a script" in err and not (tmp_path / "p.toml").exists()


def test_page_states_what_the_rasteriser_approximates_and_links_the_reference():
    from evaluation.viewer import RASTER_LIMITS, limits_html

    text = limits_html([("videos/t.mp4", "turntable")])
    for name in ("Refraction", "Shadows", "Interreflection", "Environment"):
        assert name in dict(RASTER_LIMITS) and f"<b>{name}</b>" in text
    assert 'href="videos/t.mp4"' in text and "rasteriser" in text and "path-traced" in text


def test_report_without_the_viewer_javascript_says_how_to_get_it(tmp_path, monkeypatch):
    from evaluation import viewer

    monkeypatch.setattr(viewer, "viewer_script", lambda: None)
    sec = viewer.report_section([], tmp_path)
    assert sec.bundle is None and viewer.FETCH_COMMAND in " ".join(sec.md)


def test_bad_view_and_report_input_is_one_line(tmp_path, capsys):
    def one_line(rc):
        err = capsys.readouterr().err.strip()
        assert rc == 2 and err.startswith("camo: error: ") and "\n" not in err, err
        return err

    assert "run directory not found" in one_line(main(["view", str(tmp_path / "nope"), "--no-serve"]))
    assert "--port" in one_line(main(["view", str(tmp_path / "nope"), "--port", "70000"]))
    assert not (tmp_path / "nope").exists()
    ev = tmp_path / "eval"
    ev.mkdir()
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "report.html").write_text("earlier")
    err = one_line(main(["report", str(ev), "--out", str(rep), "--video", str(tmp_path / "missing.mp4")]))
    assert "missing.mp4" in err and (rep / "report.html").read_text() == "earlier"
    err = one_line(main(["report", str(ev), "--out", str(rep), "--env-width", "30"]))
    assert "--env-width" in err and (rep / "report.html").read_text() == "earlier"
