"""``camo study build-stimuli`` (render mode) end to end on a real run: a mean-colour run of the built-in
gravel scene trained at 32 px is evaluated, then re-rendered at 64 px with the object at drawn positions.

Checks: the stimulus size does not follow the training resolution; the object's measured mask centroid lies
where the placement was drawn; the recorded placement (bbox, area share, centre hit) matches the mask; the
background render of the same camera and seed equals the stimulus wherever the object's paths do not reach
(common random numbers); a leaking practice set is refused before anything is rendered."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from camo.cli import main
from camo_base.errors import CamoError

# (mean takes no Stage 1 / Stage 2 flags: --iterations, --spp, --stages ... would be refused)
TINY = ["--method", "mean", "--views", "2", "--resolution", "32", "--map-resolution", "32",
        "--target-vertices", "1500", "--target-spp", "4", "--quiet", "--threads", "1"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("study_render")
    run, ev, stim = root / "gravel_mean", root / "eval", root / "stim"
    assert main(["optimize", "gravel", "--out", str(run), *TINY]) == 0
    assert main(["evaluate", str(run), "--out", str(ev), "--views", "2", "--spp", "2", "--resolution", "32",
                 "--metrics", "psnr", "--quiet", "--threads", "1"]) == 0
    assert main(["study", "build-stimuli", str(ev), "--out", str(stim), "--size", "64", "--views", "6", "--spp", "4",
                 "--synthetic-practice", "3", "--threads", "1", "--observer-trials", "0"]) == 0
    return root, ev, stim, json.loads((stim / "manifest.json").read_text())


def test_rendered_at_study_size_with_recorded_placement(built):
    _, _, stim, man = built
    formal = [s for s in man["stimuli"] if not s["practice"]]
    assert man["mode"] == "render" and man["size"] == 64 and len(formal) >= 5  # a view may hide the object
    assert len([s for s in man["stimuli"] if s["practice"]]) == 3
    for s in formal:
        img = np.asarray(Image.open(stim / "images" / f"{s['id']}.png"))
        mask = np.asarray(Image.open(stim / "masks" / f"{s['id']}.png")) > 127
        assert img.shape == (64, 64, 3) and (s["width"], s["height"]) == (64, 64)
        ys, xs = np.nonzero(mask)
        assert s["bbox"] == [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]
        assert s["area_share"] == pytest.approx(mask.mean()) and s["centre_hit"] == bool(mask[32, 32])
        # the object (its centre point, not the mask centroid) was aimed at the drawn NDC position
        assert s["centroid_x"] == pytest.approx((1 + s["draw_px"]) / 2, abs=0.08)
        assert s["centroid_y"] == pytest.approx((1 - s["draw_py"]) / 2, abs=0.08)
    xs = [s["centroid_x"] for s in formal]
    assert max(xs) - min(xs) > 0.2  # not all at the centre


def test_background_shares_camera_and_seed(built):
    import hashlib

    _, _, stim, man = built
    s = next(s for s in man["stimuli"] if not s["practice"])
    name = hashlib.sha256(f"{s['scene']}:{s['view']}".encode()).hexdigest()[:16]
    bg = np.asarray(Image.open(stim / "backgrounds" / f"{name}.png")).astype(int)
    img = np.asarray(Image.open(stim / "images" / f"{s['id']}.png")).astype(int)
    mask = np.asarray(Image.open(stim / "masks" / f"{s['id']}.png")) > 127
    same = np.all(bg == img, axis=-1)
    assert not same[mask].any() or same[mask].mean() < 0.5  # the object differs
    assert same[~mask].mean() > 0.5  # most other pixels are bit-identical: same camera and sampler seed


def test_leaking_practice_refused_before_rendering(built, tmp_path):
    from study_site.render_stimuli import render_stimuli

    _, ev, _, _ = built
    with pytest.raises(CamoError, match=r"practice scene\(s\) gravel also appear"):
        render_stimuli([ev], tmp_path / "o", practice_dirs=[ev], size=64, views=1, spp=1)
    assert not (tmp_path / "o").exists()
    with pytest.raises(CamoError, match=r"^size must be an integer in \[32, 4096\], got 8$"):
        render_stimuli([ev], tmp_path / "o", size=8)


def test_an_asset_is_rendered_again_on_the_runs_framings(built, tmp_path):
    """An evaluation of an asset (the run's own result.glb, placed in the run's scene) builds without --copy: the
    asset is rendered on the same drawn framings as the run, and since it is the run's result its masks and images
    are the run's (the GLB's 8-bit maps of a one-colour result: a few 8-bit levels at most)."""
    root, _, _, _ = built
    run = root / "gravel_mean"
    ev, st = tmp_path / "ev", tmp_path / "st"
    assert main(["evaluate", str(run), "--asset", str(run / "result.glb"), "--scene", str(run), "--method", "theirs",
                 "--out", str(ev), "--views", "2", "--spp", "2", "--resolution", "32", "--metrics", "psnr",
                 "--quiet", "--threads", "1"]) == 0
    # --no-noise-match: noise matching gives a pixel extra samples from its neighbours' noise at 4 spp, which two
    # results one 8-bit albedo level apart may estimate either side of a step (a few pixels then differ by noise)
    assert main(["study", "build-stimuli", str(ev), "--out", str(st), "--size", "64", "--views", "3", "--spp", "4",
                 "--synthetic-practice", "0", "--threads", "1", "--no-noise-match", "--observer-trials", "0"]) == 0
    man = json.loads((st / "manifest.json").read_text())
    assert man["mode"] == "render" and {s["method"] for s in man["stimuli"]} == {"mean", "theirs"}
    theirs = [s for s in man["stimuli"] if s["method"] == "theirs"]
    ours = {s["view"]: s for s in man["stimuli"] if s["method"] == "mean"}
    assert len(theirs) == len(ours) >= 2
    for s in theirs:
        o = ours[s["view"]]
        assert s["source_kind"] == "asset" and s["source_run"] == str((run / "result.glb").resolve())
        assert (s["draw_px"], s["draw_py"], s["fov"]) == (o["draw_px"], o["draw_py"], o["fov"])
        mask_a, mask_o = (np.asarray(Image.open(st / "masks" / f"{x['id']}.png")) > 127 for x in (s, o))
        assert (mask_a == mask_o).mean() > 0.999 and s["bbox"] == o["bbox"]
        img_a, img_o = (np.asarray(Image.open(st / "images" / f"{x['id']}.png")).astype(int) for x in (s, o))
        assert np.abs(img_a - img_o).max() <= 3, np.abs(img_a - img_o).max()  # measured: 1 (8-bit albedo)


def test_triplets_need_copy_with_one_line(built, tmp_path, capsys):
    """Given 2D images cannot be rendered on a new framing: build-stimuli says so in one line (exit 2, nothing
    written) and builds them with --copy, the given images unchanged."""
    import shutil

    _, ev, _, _ = built
    tri = tmp_path / "tri"
    tri.mkdir()
    src = next((ev / "renders").iterdir())
    for v in (0, 1):
        for kind in ("obj", "bg", "mask"):
            shutil.copy(src / f"view_{v:02d}_{kind}.png", tri / f"v{v}_{kind}.png")
    ev2, st = tmp_path / "ev", tmp_path / "st"
    assert main(["evaluate", "--triplets", str(tri), "--scene", "gravel", "--method", "2D", "--out", str(ev2),
                 "--metrics", "psnr", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["study", "build-stimuli", str(ev2), "--out", str(st), "--size", "64"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("camo: error:") and "triplets" in err[0] and "--copy" in err[0], err
    assert not st.exists()
    assert main(["study", "build-stimuli", str(ev2), "--out", str(st), "--copy", "--synthetic-practice", "0"]) == 0
    man = json.loads((st / "manifest.json").read_text())
    assert man["mode"] == "copy" and len(man["stimuli"]) == 2
    for s in man["stimuli"]:
        given = np.asarray(Image.open(tri / f"v{s['view']}_obj.png").convert("RGB"))
        np.testing.assert_array_equal(np.asarray(Image.open(st / "images" / f"{s['id']}.png")), given)
    # a copied set has no object-free render and no cameras: `camo study surfaces` refuses it in one line
    before = sorted(p.relative_to(st) for p in st.rglob("*"))
    capsys.readouterr()
    assert main(["study", "surfaces", str(st)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("camo: error:") and "not a rendered set" in err[0], err
    assert sorted(p.relative_to(st) for p in st.rglob("*")) == before  # nothing written


def test_inputs_framed_differently_are_refused_with_one_line():
    """One framing per scene and view (the methods are compared on the same framings and share one object-free
    render per view, the observer's background): inputs of one scene whose cameras differ (runs made with other
    --views / --resolution) are refused before anything is rendered; the same cameras, or other scenes, pass."""
    from study_site.render_stimuli import check_same_framing

    a = [{"origin": [4.0, 0.0, 1.5], "target": [0.0, 0.0, 0.3], "fov": 60.0},
         {"origin": [0.0, 4.0, 1.5], "target": [0.0, 0.0, 0.3], "fov": 58.0}]
    moved = [dict(a[0]), dict(a[1], origin=[0.2, 3.9, 1.6])]
    wider = [dict(a[0], fov=61.0), dict(a[1])]
    check_same_framing([("gravel", "ours", a), ("gravel", "mean", [dict(x) for x in a]), ("meadow", "mean", moved)])
    for other in (moved, wider):
        with pytest.raises(CamoError, match=r"^scene gravel: mean and ours are framed differently in view \d") as e:
            check_same_framing([("gravel", "ours", a), ("gravel", "mean", other)])
        assert "\n" not in str(e.value)
    with pytest.raises(CamoError, match=r"^scene gravel: mean has 1 views and ours 2"):
        check_same_framing([("gravel", "ours", a), ("gravel", "mean", a[:1])])


def test_backgrounds_carry_their_surfaces_and_old_sets_get_them_back(built, tmp_path):
    """build-stimuli writes the object-free view's normals beside each formal background (the observer's
    surfaces: gravel's ground faces up); `camo study surfaces` renders them again from the manifest's cameras --
    for a set built before they were written -- to the same values (float16); the observer's prediction records
    how many stimuli's normals it used (``surfaces=geometry``; none by default)."""
    import shutil

    from study_site.stimuli import background_path, load_normals, surface_path

    _, _, stim, man = built
    formal = [s for s in man["stimuli"] if not s["practice"]]
    old = tmp_path / "old"
    shutil.copytree(stim, old)
    for s in formal:
        n = load_normals(surface_path(stim, s["scene"], s["view"]), (64, 64))
        assert n is not None and background_path(stim, s["scene"], s["view"]).is_file()
        seen = np.linalg.norm(n, axis=-1) > 0.5
        assert seen[-1].all() and (n[seen][:, 2] > 0.9).mean() > 0.99  # the ground faces up
        surface_path(old, s["scene"], s["view"]).unlink(missing_ok=True)
    assert main(["study", "surfaces", str(old), "--threads", "1"]) == 0
    for s in formal:
        a = load_normals(surface_path(stim, s["scene"], s["view"]), (64, 64))
        b = load_normals(surface_path(old, s["scene"], s["view"]), (64, 64))
        np.testing.assert_allclose(b, a, atol=2e-3)
    assert main(["study", "predict", str(old), "--trials", "5", "--quiet", "--observer", "surfaces=geometry"]) == 0
    cfg = json.loads((old / "predicted_config.json").read_text())
    assert cfg["stimuli_with_surfaces"] == cfg["stimuli_with_background"] == len(formal)
    assert main(["study", "predict", str(old), "--trials", "5", "--quiet"]) == 0  # the default reads no normals
    assert json.loads((old / "predicted_config.json").read_text())["stimuli_with_surfaces"] == 0
