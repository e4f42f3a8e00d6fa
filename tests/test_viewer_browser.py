"""The interactive viewer in a real headless Chromium (software WebGL): ``camo view`` and ``camo report`` pages.

On ``split`` (bright marble for x < 0, dark asphalt for x > 0: the environment's orientation shows), a Mean run:

* the page loads offline, from disk, requesting nothing but ``file:``/``blob:``/``data:`` URLs (the viewer's
  JavaScript is the pinned copy beside the page), and served by ``camo view``'s server on 127.0.0.1;
* a screenshot of the viewer has a non-empty object region (viewer with the model vs. the same view without it),
  where the path tracer sees the object from that camera (its coverage mask), and that region and its pixels
  change when the camera orbits;
* the viewer's background at the stills' camera is the path-traced background's picture (marble and asphalt on
  the same sides, correlated), so the environment panorama is oriented and placed right;
* clicking a still moves the viewer to that camera.

Set VIEWER_SHOTS_DIR=/some/dir to keep the screenshots.
"""

from __future__ import annotations

import io
import os
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from camo.cli import main

CHROMIUM = "/usr/bin/chromium"
pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"{CHROMIUM} is not installed (Debian package chromium)"),
]
SHOTS = os.environ.get("VIEWER_SHOTS_DIR")
BASE = ["--views", "4", "--resolution", "32", "--map-resolution", "32", "--target-vertices", "1500",
        "--target-spp", "8", "--quiet"]


@pytest.fixture(scope="module")
def page_dir(tmp_path_factory):
    from evaluation.viewer import viewer_script

    if viewer_script() is None:
        pytest.fail("the viewer's JavaScript is missing: camo data fetch data_manifests/viewer.toml --dest data/vendor "
                    "(make test does it)")
    root = tmp_path_factory.mktemp("viewer")
    run = root / "mean"
    assert main(["optimize", "split", "--method", "mean", "--out", str(run), *BASE]) == 0
    out = root / "page"
    assert main(["view", str(run), "--out", str(out), "--no-serve", "--env-width", "256", "--quiet"]) == 0
    return run, out


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM,
                               args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                                     "--ignore-gpu-blocklist", "--disable-background-networking",
                                     "--disable-component-update", "--disable-sync", "--no-first-run"])
        yield b
        b.close()


def _open(browser, url):
    page = browser.new_page(viewport={"width": 1280, "height": 1000})
    page.set_default_timeout(90_000)
    requests, errors = [], []
    page.on("request", lambda r: requests.append(r.url))
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    ids = page.evaluate("() => window.camoViewerReady")
    page.wait_for_timeout(500)
    return page, ids, requests, errors


def _shot(page, selector, name) -> np.ndarray:
    page.wait_for_timeout(700)  # let the damped camera and the renderer settle
    png = page.locator(selector).screenshot()
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        (Path(SHOTS) / f"{name}.png").write_bytes(png)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.float32)


def _set_model(page, mv_id, visible: bool):
    """Show or hide the object (its scene-graph node), keeping camera, environment and shadow settings."""
    page.evaluate("""([id, on]) => { const mv = document.getElementById(id);
        mv.shadowIntensity = on ? 1 : 0;
        const sym = Object.getOwnPropertySymbols(mv).find(s => String(s) === 'Symbol(scene)');
        mv[sym].target.children.forEach(c => { if (!c.isMesh || c.geometry.type !== 'SphereGeometry') c.visible = on; });
        mv[sym].queueRender(); }""", [mv_id, visible])


def _object_region(with_obj: np.ndarray, without: np.ndarray) -> np.ndarray:
    return np.abs(with_obj - without).max(-1) > 12.0


def test_viewer_page_offline_object_region_and_orbit(page_dir, browser):
    run, out = page_dir
    page, ids, requests, errors = _open(browser, (out / "index.html").as_uri())
    try:
        assert len(ids) == 1 and not errors, errors
        assert all(u.split(":", 1)[0] in ("file", "blob", "data") for u in requests), requests
        assert any(u.endswith("/viewer/model-viewer-umd.min.js") for u in requests)
        html = (out / "index.html").read_text()
        assert "http://" not in html.replace("http://127.0.0.1", "") and "https://" not in html
        assert "rasteriser" in html and "Refraction" in html and "Shadows" in html
        sel = f"#{ids[0]}"
        a = _shot(page, sel, "view_a")
        _set_model(page, ids[0], False)
        b = _shot(page, sel, "view_a_without")
        _set_model(page, ids[0], True)
        region = _object_region(a, b)
        h, w = region.shape
        assert region.mean() > 0.01, region.mean()  # the object shows
        ys, xs = np.nonzero(region)
        assert abs(xs.mean() / w - 0.5) < 0.2 and abs(ys.mean() / h - 0.5) < 0.25  # at the centre it is aimed at
        # where the path tracer sees it: the run's coverage mask of view 0 (the viewer opens at still 0's camera)
        cov = np.load(run / "renders.npz")["coverage"][0] >= 0.5
        small = np.asarray(Image.fromarray(region.astype(np.uint8) * 255).resize(cov.shape[::-1], Image.Resampling.BOX),
                           np.float32) / 255 > 0.5
        iou_pt = (small & cov).sum() / (small | cov).sum()
        print(f"viewer silhouette vs path-traced coverage at view 0: IoU {iou_pt:.2f}")
        assert iou_pt > 0.75, iou_pt  # 0.91 measured (32 px mask)
        # orbit by 90 degrees: the object seen from another side
        page.evaluate(f"""() => {{ const mv = document.querySelector('{sel}'); const o = mv.getCameraOrbit();
            mv.cameraOrbit = `${{o.theta * 180 / Math.PI + 90}}deg ${{o.phi * 180 / Math.PI}}deg ${{o.radius}}m`;
            mv.jumpCameraToGoal(); }}""")
        c = _shot(page, sel, "view_b")
        _set_model(page, ids[0], False)
        d = _shot(page, sel, "view_b_without")
        _set_model(page, ids[0], True)
        region2 = _object_region(c, d)
        assert region2.mean() > 0.01
        union = region | region2
        iou = (region & region2).sum() / union.sum()
        assert iou < 0.9, iou  # a 90-degree turn changes the silhouette ...
        assert np.abs(a - c)[union].mean() > 10  # ... and what is seen inside it
        assert np.abs(b - d).mean() > 5  # the background turned too

        # the environment is placed and turned right: the viewer's background at still 0's camera against the
        # run's path-traced background of that view
        ref = np.load(run / "renders.npz")["background"][0]
        from camo_base.imaging import linear_to_srgb

        ref = linear_to_srgb(ref).mean(-1) * 255
        page.evaluate("() => document.querySelector('.camo-still img').click()")
        _set_model(page, ids[0], False)
        bg = _shot(page, sel, "still0_without")
        _set_model(page, ids[0], True)
        small = np.asarray(Image.fromarray(bg.astype(np.uint8)).resize(ref.shape[::-1], Image.Resampling.BOX),
                           np.float32).mean(-1)
        lower = slice(ref.shape[0] // 2, None)  # the ground: marble on one side, asphalt on the other
        cols = ref.shape[1] // 2
        sign_ref = np.sign(ref[lower, :cols].mean() - ref[lower, cols:].mean())
        sign_view = np.sign(small[lower, :cols].mean() - small[lower, cols:].mean())
        assert sign_ref != 0 and sign_ref == sign_view
        corr = np.corrcoef(ref[lower].ravel(), small[lower].ravel())[0, 1]
        assert corr > 0.5, corr
    finally:
        page.close()


def test_viewer_page_is_served_by_camo_view(page_dir, browser):
    from evaluation.viewer import make_server

    _, out = page_dir
    srv = make_server(out, 0)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    try:
        page, ids, requests, errors = _open(browser, f"http://127.0.0.1:{srv.server_port}/index.html")
        assert len(ids) == 1 and not errors
        hosts = {u.split("/")[2] for u in requests if u.startswith("http")}
        assert hosts == {f"127.0.0.1:{srv.server_port}"}
        page.close()
    finally:
        srv.shutdown()
        srv.server_close()
        th.join(5)


def test_report_shows_a_viewer_per_result(page_dir, browser, tmp_path):
    run, _ = page_dir
    ev = tmp_path / "eval"
    assert main(["evaluate", str(run), "--out", str(ev), "--spp", "4", "--views", "2", "--quiet",
                 "--metrics", "psnr"]) == 0
    rep = tmp_path / "report"
    assert main(["report", str(ev), "--out", str(rep), "--env-width", "256"]) == 0
    page, ids, requests, errors = _open(browser, (rep / "report.html").as_uri())
    try:
        assert len(ids) == 1 and not errors
        assert all(u.split(":", 1)[0] in ("file", "blob", "data") for u in requests)
        assert page.locator(".camo-still img").count() == 2  # the evaluation's two views
        img = _shot(page, f"#{ids[0]}", "report_viewer")
        assert img.std() > 5  # a picture, not an empty canvas
    finally:
        page.close()
