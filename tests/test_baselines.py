"""Baselines (optimizer.optimise.baselines): texel projection and visibility, the Owens 2014 models, GANmouflage
training, and the run directory of every method through ``camo optimize --method NAME``.

Scenes are tiny (4 views, 32-40 px, ~1,500 vertices, 64^2 maps)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from camo.cli import main

# Two LLVM threads, not one: with a DrJit thread count of 1, loading an EXR texture (mi.Bitmap, hence
# mi.load_file of a run's scene.xml) deadlocks in Mitsuba 3.9 / DrJit 1.5.
TINY = ["--views", "4", "--resolution", "32", "--map-resolution", "64", "--target-vertices", "1500",
        "--target-spp", "16", "--quiet", "--threads", "2"]
METHODS = ("transparent", "mean", "random", "greedy", "diffusion2d", "ganmouflage")

# An occluder between camera 0 (on the +x axis, 20 deg elevation) and the lower -y half of the object.
OCC_CENTRE = (1.6, -0.35, 0.5)
OCC_HALF = (0.1, 0.35, 0.5)


def tiny_setup(env=None, resolution=(40, 40)):
    from optimizer.optimise.baselines import common
    from optimizer.optimise.spec import RunSpec, SppSettings
    from optimizer.rendering.appearance import AppearanceConfig
    from optimizer.scenes.builtin_scenes import resolve_scene

    pack = resolve_scene("gravel")
    pack.object = dataclasses.replace(pack.object, target_vertices=1500)
    pack.cameras = dataclasses.replace(pack.cameras, views=4)
    pack.render = dataclasses.replace(pack.render, resolution=resolution)
    spec = RunSpec(scene="gravel", pack=pack, method="mean", spp=SppSettings(target=16),
                   appearance=AppearanceConfig(map_resolution=64))
    return common.setup(spec.validate(), env=env)


@pytest.fixture(scope="module")
def st(mi_backend):
    return tiny_setup()


@pytest.fixture(scope="module")
def occluded(mi_backend):
    from optimizer.scenes.environments import ENVIRONMENTS, Environment, box, plain_diffuse

    _, gravel, emitters, _, _ = ENVIRONMENTS["gravel"]

    def build():
        out = gravel()
        out["occluder"] = box(list(OCC_CENTRE), list(OCC_HALF), plain_diffuse([0.2, 0.2, 0.2]))
        return out

    env = Environment("gravel+occluder", "test", build, emitters, nearby_geometry=True, occluders=True)
    s = tiny_setup(env)
    surf = s.texel_surface()
    return s, surf, s.observe(surf, 0.01)


def per_view_constant_images(st, colours):
    cam = st.cams[0]
    return np.stack([np.broadcast_to(np.asarray(c, np.float32), (cam.height, cam.width, 3)) for c in colours])


# --- projection ------------------------------------------------------------------------------------


def test_projection_matches_mitsuba_camera_rays(mi_backend):
    """A pixel-centre ray's hit point projects back onto that pixel centre (non-square image)."""
    from optimizer.rendering import scene as scn
    from optimizer.rendering import projection
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment
    from optimizer.rendering.render import camera_rays
    from optimizer.scenes.builtin_scenes import resolve_scene

    pack = resolve_scene("gravel")
    sc = scn.build_scene(get_environment(pack.environment).build())
    for cam in cameras(pack, (48, 32))[:2]:
        si = sc.ray_intersect(camera_rays(cam, 1))
        ok = np.asarray(si.is_valid(), bool)
        p = np.stack([np.asarray(si.p[k], np.float64) for k in range(3)], 1)[ok]
        x, y, _ = projection.project(p, cam)
        idx = np.flatnonzero(ok)
        assert ok.mean() > 0.5
        np.testing.assert_allclose(x, idx % cam.width + 0.5, atol=5e-3)
        np.testing.assert_allclose(y, idx // cam.width + 0.5, atol=5e-3)


def test_rasterised_texels_sit_at_their_uv_on_the_surface(st):
    from optimizer.rendering import projection

    g = st.geometry
    surf = st.texel_surface()
    R = surf.resolution
    uv = np.einsum("nk,nkc->nc", surf.bary.astype(np.float64), g.uvs[g.faces[surf.face]].astype(np.float64))
    np.testing.assert_allclose(uv[:, 0] * R - 0.5, surf.cols, atol=1e-3)
    np.testing.assert_allclose(uv[:, 1] * R - 0.5, surf.rows, atol=1e-3)
    np.testing.assert_allclose(surf.points, projection.barycentric_points(st.positions, g.faces, surf.face, surf.bary),
                               atol=1e-6)
    assert len(np.unique(surf.index)) == len(surf) > 0.3 * R * R
    # outward normals: points lie on the side of the object the normal points away from
    centre = st.positions.mean(0)
    assert np.mean(np.einsum("ij,ij->i", surf.normals, surf.points - centre) > 0) > 0.95
    np.testing.assert_allclose(np.linalg.norm(surf.normals, axis=1), 1.0, atol=1e-5)


def test_mean_of_a_constant_background_is_that_colour(st):
    """Synthetic constant background: every texel (seen, unseen after fill, and the padding) gets it."""
    from optimizer.optimise.baselines import common, owens2014
    from optimizer.rendering import projection

    surf = st.texel_surface()
    obs = st.observe(surf, 0.01)
    c = np.array([0.21, 0.47, 0.13], np.float32)
    imgs = per_view_constant_images(st, [c] * len(st.cams))
    alb = common.observed_albedo(st, obs, imgs, "photo")
    col, assigned = owens2014.mean_colours(obs.visible, alb)
    assert assigned.mean() > 0.5
    np.testing.assert_allclose(col[assigned], np.broadcast_to(c, col[assigned].shape), atol=1e-6)
    m = projection.bake(surf, col, assigned)
    np.testing.assert_allclose(m, np.broadcast_to(c, m.shape), atol=1e-6)
    # global white level: the same colour divided by W
    g = common.observed_albedo(st, obs, imgs, "global")
    np.testing.assert_allclose(g[obs.visible], np.clip(c / st.white_level(), 0, 1)[None].repeat(obs.visible.sum(), 0),
                               rtol=1e-5)


def test_random_and_greedy_only_use_colours_of_views_that_see_the_texel(st):
    from optimizer.optimise.baselines import owens2014

    surf = st.texel_surface()
    obs = st.observe(surf, 0.01)
    colours = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], np.float32)[: len(st.cams)]
    alb = obs.sample(per_view_constant_images(st, colours))
    for seed in (0, 1):
        order = owens2014.random_order(len(st.cams), seed)
        col, assigned, src = owens2014.fill_in_order(obs.visible, alb, order)
        assert sorted(order) == list(range(len(st.cams)))
        n = np.flatnonzero(assigned)
        np.testing.assert_array_equal(col[n], colours[src[n]])
        assert obs.visible[src[n], n].all()
        # first view in the order that sees the texel
        rank = np.array([order.index(v) for v in range(len(st.cams))])
        first = np.argmin(np.where(obs.visible, rank[:, None], 99), 0)
        np.testing.assert_array_equal(src[n], first[n])
    src, used = owens2014.greedy_assignment(obs.visible, obs.cos, 70.0, seed=0)
    n = np.flatnonzero(src >= 0)
    assert obs.visible[src[n], n].all() and len(n) == obs.visible.any(0).sum()
    assert len(set(used)) == len(used)


def test_greedy_is_owens_set_cover():
    """Hand-made case: stable texels first, the view covering most still-open texels is taken first."""
    from optimizer.optimise.baselines.owens2014 import greedy_assignment

    vis = np.array([[1, 1, 1, 0, 0, 1],
                    [0, 1, 1, 1, 1, 0],
                    [0, 0, 0, 1, 1, 0]], bool)
    cos = np.array([[1.0, 1.0, 1.0, 0.0, 0.0, 0.1],
                    [0.0, 1.0, 1.0, 1.0, 1.0, 0.0],
                    [0.0, 0.0, 0.0, 1.0, 0.2, 0.0]])
    src, used = greedy_assignment(vis, cos, 70.0, seed=0)
    # view 1 covers 4 stable texels (1, 2, 3, 4), then view 0 covers texel 0; texel 5 is stable
    # nowhere (cos 0.1 < cos 70), so any view that sees it (view 0) may paint it; view 2 adds nothing.
    assert used[:2] == [1, 0]
    np.testing.assert_array_equal(src, [0, 1, 1, 1, 1, 0])


def test_bake_fills_unseen_texels_and_pads_the_atlas():
    from optimizer.rendering.projection import TexelSurface, bake

    R = 8
    idx = np.array([0, 1, 2, 9, 10, 11])  # two rows of a small chart
    pts = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0]], np.float32)
    z = np.zeros((6, 3), np.float32)
    surf = TexelSurface(R, idx, np.zeros(6, int), z, pts, z, z)
    col = np.array([[0.1] * 3, [0.2] * 3, [0.3] * 3, [0.4] * 3, [0.5] * 3, [0.6] * 3], np.float32)
    assigned = np.array([1, 1, 1, 1, 0, 0], bool)
    m = bake(surf, col, assigned).reshape(-1, 3)
    np.testing.assert_allclose(m[[0, 1, 2, 9]], col[:4])
    np.testing.assert_allclose(m[10], col[1])  # nearest seen texel in 3D: (1, 0, 0)
    np.testing.assert_allclose(m[11], col[2])
    np.testing.assert_allclose(m[63], m[11])  # padding: nearest on-chart texel in the atlas


# --- occlusion -----------------------------------------------------------------------------------------


def _segment_hits_box(o, p, centre, half):
    """Does the open segment o -> p (minus its last 1 %) cross the axis-aligned box?"""
    d = p - o
    lo = (np.asarray(centre) - half - o) / np.where(d == 0, 1e-12, d)
    hi = (np.asarray(centre) + half - o) / np.where(d == 0, 1e-12, d)
    tmin = np.minimum(lo, hi).max(1)
    tmax = np.maximum(lo, hi).min(1)
    return (tmax >= tmin) & (tmax > 0) & (tmin < 0.99)


def test_occluded_texels_are_never_coloured_from_the_blocked_view(occluded):
    from optimizer.optimise.baselines import owens2014
    from optimizer.rendering import projection

    s, surf, obs = occluded
    cam = s.cams[0]
    o = np.asarray(cam.origin, np.float64)
    blocked = _segment_hits_box(o, surf.points.astype(np.float64), OCC_CENTRE, np.asarray(OCC_HALF))
    x, y, z = projection.project(surf.points, cam)
    facing = np.einsum("ij,ij->i", surf.normals, o - surf.points) > 0.2 * np.linalg.norm(o - surf.points, axis=1)
    hidden = blocked & facing & projection.in_frame(x, y, z, cam)
    assert hidden.sum() > 30  # the occluder hides a real part of the object from view 0
    assert not obs.visible[0, hidden].any()
    assert obs.visible[0, facing & ~blocked].mean() > 0.8  # ... and only that part
    colours = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 1, 1]], np.float32)  # red only in view 0
    alb = obs.sample(per_view_constant_images(s, colours))
    for seed in range(4):  # view 0 comes first in some of these orders
        col, assigned, src = owens2014.fill_in_order(obs.visible, alb, owens2014.random_order(4, seed))
        assert not (src[hidden] == 0).any()
        assert not np.all(col[hidden & assigned] == colours[0], axis=1).any()
    src, _ = owens2014.greedy_assignment(obs.visible, obs.cos, 70.0, seed=0)
    assert not (src[hidden] == 0).any()
    mean, assigned = owens2014.mean_colours(obs.visible, alb)
    sel = hidden & assigned
    assert sel.any() and (mean[sel, 0] == 0).all()
    expect = (obs.visible[1:, sel, None] * colours[1:, None]).sum(0) / obs.visible[1:, sel].sum(0)[:, None]
    np.testing.assert_allclose(mean[sel], expect, atol=1e-6)


# --- GANmouflage -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("embedder", ["cips_learnable", "fixed_sincos"])
def test_ganmouflage_generator_loss_goes_down(st, embedder):
    import torch

    from optimizer.optimise.baselines.ganmouflage import GanmouflageConfig, Trainer

    cfg = GanmouflageConfig(iterations=30, hidden_1=64, hidden_2=32, crop_size=64, encoder_channels=(8, 16, 16),
                            disc_channels=16, lr_warmup=3, threads=1, embedder=embedder)
    threads = torch.get_num_threads()
    tr = Trainer(st, cfg, seed=0)
    mask = st.targets.coverage > 0.5
    bg = tr.bg.numpy().transpose(0, 2, 3, 1)
    err0 = np.abs(tr.render_all() - bg)[mask].mean()
    hist = [tr.step() for _ in range(cfg.iterations)]
    err1 = np.abs(tr.render_all() - bg)[mask].mean()
    photo = [h["loss_photo"] for h in hist]
    assert all(np.isfinite(h["loss"]) and np.isfinite(h["loss_d"]) for h in hist)
    assert np.mean(photo[-5:]) < 0.7 * np.mean(photo[:5]), photo
    assert err1 < 0.7 * err0, (err0, err1)
    colours = tr.bake_colours(st.texel_surface())
    torch.set_num_threads(threads)
    assert colours.shape[1] == 3 and np.isfinite(colours).all() and colours.min() >= 0 and colours.max() <= 1


def test_ganmouflage_embedders_follow_the_authors_decoder():
    """fixed_sincos: NeRF encoding with 10 octaves (63 inputs); cips_learnable: Linear(3, 128) drawn from
    U(+-sqrt(9/3)) with zero bias, then sin. The fast preset uses the latter, the paper preset the former."""
    import torch

    from optimizer.optimise.baselines.ganmouflage import GanmouflageConfig, build_networks, positional_encoding

    assert GanmouflageConfig.paper().embedder == "fixed_sincos" and GanmouflageConfig().embedder == "cips_learnable"
    x = torch.tensor([[0.25, -0.5, 0.125]])
    pe = positional_encoding(x, 10)
    assert pe.shape == (1, 63) and torch.allclose(pe[0, 3 + 6 * 9 + 3:3 + 6 * 9 + 6], torch.cos(512 * x[0]))
    torch.manual_seed(0)
    _, field, _ = build_networks(GanmouflageConfig(embedder="cips_learnable", hidden_1=32, hidden_2=16), z_dim=7)
    w = field.pe.weight.detach()
    assert w.shape == (128, 3) and float(w.abs().max()) <= 3 ** 0.5 and float(w.abs().max()) > 1.5
    assert float(field.pe.bias.abs().max()) == 0.0 and field.first.in_features == 128
    _, field, _ = build_networks(GanmouflageConfig(embedder="fixed_sincos", hidden_1=32, hidden_2=16), z_dim=7)
    assert field.pe is None and field.first.in_features == 63
    with pytest.raises(ValueError, match="embedder"):
        build_networks(GanmouflageConfig(embedder="learned"), z_dim=7)


def test_ganmouflage_crop_is_exact_on_a_linear_ramp_and_differentiable():
    """Bilinear interpolation reproduces a linear image exactly, so kornia's crop-and-resize of a ramp must equal the
    ramp at the window's sample positions ``x0 + (j + 0.5) * ww / size`` (continuous coordinates, pixel centres at
    ``i + 0.5``); every in-window pixel receives gradient."""
    import torch

    from optimizer.optimise.baselines.ganmouflage import crop

    H, W = 48, 64
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float32) + 0.5, torch.arange(W, dtype=torch.float32) + 0.5,
                            indexing="ij")
    img = torch.stack([0.01 * xx, 0.02 * yy, 0.003 * xx - 0.004 * yy + 0.5]).requires_grad_(True)
    for win, size in (((5.25, 7.5, 30.0, 40.0), 16), ((0.0, 0.0, 48.0, 64.0), 32), ((10.0, 3.0, 20.0, 20.0), 40)):
        y0, x0, hh, ww = win
        t = (torch.arange(size, dtype=torch.float32) + 0.5) / size
        ys, xs = torch.meshgrid(y0 + t * hh, x0 + t * ww, indexing="ij")
        expect = torch.stack([0.01 * xs, 0.02 * ys, 0.003 * xs - 0.004 * ys + 0.5])
        got = crop(img, win, size)
        assert got.shape == (3, size, size)
        torch.testing.assert_close(got, expect, atol=2e-5, rtol=0)
    crop(img, (8.0, 8.0, 16.0, 16.0), 32).sum().backward()
    g = img.grad[0]
    assert float(g[8:24, 8:24].min()) > 0 and float(g[:6].abs().max()) == 0.0


def test_filter_bank_perceptual_loss_is_zero_for_equal_images_and_grows_with_difference():
    import torch

    from optimizer.optimise.baselines.ganmouflage import FilterBankFeatures

    g = torch.Generator().manual_seed(0)
    a = torch.rand(1, 3, 32, 32, generator=g)
    fb = FilterBankFeatures().calibrate(a)
    assert float(fb.loss(a, a)) == 0.0
    b = a.clone()
    b[..., 8:24, 8:24] = 0.5
    c = a.clone()
    c[..., 4:28, 4:28] = 0.5
    assert 0 < float(fb.loss(b, a)) < float(fb.loss(c, a))


# --- CLI: every method's run directory -------------------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
def test_run_directory_loads_back(method, tmp_path, mi_backend):
    import tomllib

    import trimesh

    out = tmp_path / method
    extra = ["--iterations", "3"] if method == "ganmouflage" else []
    assert main(["optimize", "gravel", "--method", method, "--out", str(out), *TINY, *extra]) == 0
    for name in ("config.toml", "log.jsonl", "summary.json", "result.glb", "result.obj", "scene.xml", "pose.json",
                 "maps/albedo.npy", "maps/transmittance.npy", "previews/overview.png", "previews/view_03.png",
                 "renders.npz"):
        assert (out / name).is_file(), name
    cfg = tomllib.loads((out / "config.toml").read_text())
    assert cfg["method"] == method and cfg["baseline"]["method"] == method
    assert cfg["spp"] == {"target": 16} and "stage2" not in cfg and set(cfg["stage1"]) == {
        "loss", "alpha", "eps", "domain", "domain_dilate", "shadow_threshold"}  # what a baseline reads, only
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == method and np.isfinite(summary["final_loss_high_spp"])
    log = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    assert len(log) == (3 if method == "ganmouflage" else 0)

    mesh = trimesh.load(out / "result.glb", force="mesh")
    assert len(mesh.faces) > 1000
    assert mesh.visual.material.baseColorTexture.size == (64, 64)
    maps = {k: np.load(out / "maps" / f"{k}.npy") for k in ("albedo", "metallic", "roughness", "transmittance")}
    if method == "transparent":
        assert (maps["transmittance"] == 1).all() and (maps["metallic"] == 0).all()
    else:
        assert (maps["transmittance"] == 0).all() and (maps["metallic"] == 0).all()
        assert np.allclose(maps["roughness"], 1.0)
        assert maps["albedo"].std() > 0 and 0 <= maps["albedo"].min() and maps["albedo"].max() <= 1

    from optimizer import backend

    mi, _ = mi_backend
    backend.set_threads(max(2, backend.info().threads))  # see TINY
    sc = mi.load_file(str(out / "scene.xml"))
    r = np.load(out / "renders.npz")
    img = np.asarray(mi.render(sc, sensor=1, spp=32, seed=5))
    final = r["final"][1]
    assert img.shape == final.shape
    assert abs(img.mean() - final.mean()) < 0.1 * final.mean()


def test_random_albedo_comes_from_the_backgrounds(st):
    """End to end: every on-chart texel of the `random` map equals (global white level) a background colour
    seen by one view at that texel's projection."""
    from optimizer.optimise.baselines import common, owens2014

    s = st
    vals, _, info = owens2014.compute(s, "random")
    surf = s.texel_surface()
    obs = s.observe(surf, 0.01)
    alb = common.observed_albedo(s, obs, s.targets.background, "global")
    got = vals["albedo"].reshape(-1, 3)[surf.index]
    seen = obs.visible.any(0)
    diff = np.abs(alb - got[None]).max(-1)  # (V, N)
    diff = np.where(obs.visible, diff, np.inf).min(0)
    assert (diff[seen] < 1e-5).all()
    lo = alb[obs.visible].min(0) - 1e-6
    hi = alb[obs.visible].max(0) + 1e-6
    assert ((got >= lo) & (got <= hi)).all()


def test_baseline_cli_errors_are_one_line(tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["optimize", "gravel", "--method", "mean", "--out", str(out), "--resume", *TINY]) == 2
    assert main(["optimize", "gravel", "--method", "greedy", "--out", str(out), "--ablate", "pose", *TINY]) == 2
    assert main(["optimize", "gravel", "--method", "nope", "--out", str(out), *TINY]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(e.startswith("camo: error:") for e in err)


def test_baseline_targets_are_bit_identical_to_stage1(tmp_path):
    """Same flags -> the same background targets, coverage, loss domain and depth as `ours` (same render path).
    `ours` turns the object first (the fast preset's turn search): then its coverage and domain follow the turned
    object, and the background targets are still bit-identical."""
    flags = ["--views", "2", "--resolution", "24", "--map-resolution", "32", "--target-vertices", "600",
             "--target-spp", "8", "--quiet", "--threads", "2"]
    ours = ["--iterations", "1", "--stages", "1", "--spp", "1", "--displacement-resolution", "16", "--holdout-views", "0"]
    assert main(["optimize", "gravel", "--out", str(tmp_path / "ours"), *ours, "--pose-search", "0", *flags]) == 0
    assert main(["optimize", "gravel", "--method", "transparent", "--out", str(tmp_path / "tr"), *flags]) == 0
    a, b = np.load(tmp_path / "ours" / "renders.npz"), np.load(tmp_path / "tr" / "renders.npz")
    for k in ("background", "coverage", "domain", "depth"):
        np.testing.assert_array_equal(a[k], b[k])
    assert main(["optimize", "gravel", "--out", str(tmp_path / "turned"), *ours, *flags]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "turned" / "renders.npz")["background"], b["background"])
