"""optimizer.rendering.denoise: Open Image Denoise with first-hit albedo and normal features, against known images
and a high-spp reference."""

from __future__ import annotations

import numpy as np
import pytest


def _noisy(truth: np.ndarray, spp: int, rng) -> np.ndarray:
    """A Monte Carlo estimate of ``truth`` at ``spp``: the mean of ``spp`` exponential samples per pixel
    (variance truth^2 / spp: a heavy-ish tail, like a path tracer's)."""
    return (truth * rng.gamma(spp, 1.0 / spp, truth.shape)).astype(np.float32)


def test_known_image_with_exact_features_is_restored_within_a_fifth_of_its_noise():
    """A piecewise-constant image (four albedo patches under constant light) with its exact albedo and normal: the
    denoised estimate at 16 spp is within 0.2 of the input's noise (RMS) of the truth (measured 0.15), and its mean within 1 %."""
    from optimizer.rendering.denoise import denoise

    rng = np.random.default_rng(0)
    albedo = np.zeros((48, 48, 3), np.float32)
    albedo[:24, :24] = [0.8, 0.2, 0.1]
    albedo[:24, 24:] = [0.1, 0.6, 0.2]
    albedo[24:, :24] = [0.2, 0.3, 0.9]
    albedo[24:, 24:] = [0.5, 0.5, 0.5]
    normal = np.zeros_like(albedo)
    normal[..., 2] = 1.0
    truth = albedo * 1.5  # linear HDR radiance
    noisy = _noisy(truth, 16, rng)
    out = denoise(noisy, albedo, normal)
    noise = np.sqrt(np.mean((noisy - truth) ** 2))
    err = np.sqrt(np.mean((out - truth) ** 2))
    assert err < 0.2 * noise, (err, noise)
    assert abs(out.mean() / truth.mean() - 1) < 0.01
    # the patches' edges are kept: no patch bleeds into its neighbour by more than 2 % of the step
    assert np.all(np.abs(out[20:28, 4] - truth[20:28, 4]) < 0.02 * 1.5 + 3 * noise / 4)


def test_views_are_denoised_one_by_one_and_inputs_are_checked():
    from optimizer.rendering.denoise import denoise, denoise_variant

    rng = np.random.default_rng(1)
    truth = np.full((2, 16, 16, 3), 0.3, np.float32)
    noisy = _noisy(truth, 8, rng)
    both = denoise(noisy)
    np.testing.assert_array_equal(both[1], denoise(noisy[1]))  # a pure function of the view's own pixels
    with pytest.raises(ValueError, match="needs the albedo"):
        denoise(noisy, None, truth)
    with pytest.raises(ValueError, match="shape"):
        denoise(noisy, truth[:1])
    with pytest.raises(ValueError, match="non-finite"):
        denoise(np.where(truth > 0, np.nan, truth))
    with pytest.raises(ValueError, match="unknown denoiser"):
        denoise_variant(noisy, None, None, "bm3d")
    with pytest.raises(ValueError, match="features"):
        denoise_variant(noisy, None, None, "oidn")


def _sunlit(mi, dark, tiles: int):
    """A checkered diffuse ground (``dark``: the second tile's colour; ``tiles`` per unit length / 20) under the sun
    and sky (the built-in scenes' light), and a sphere mesh factory ``(albedo, transmittance) -> mesh``."""
    import trimesh

    from optimizer.rendering import scene as scn

    def elements():
        return {"ground": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(20),
                           "bsdf": {"type": "diffuse", "reflectance": {
                               "type": "checkerboard", "color0": {"type": "rgb", "value": [0.6, 0.5, 0.3]},
                               "color1": {"type": "rgb", "value": list(dark)},
                               "to_uv": mi.ScalarTransform4f().scale([tiles, tiles, 1])}}},
                "sun": {"type": "sunsky", "sun_direction": [0.5, -0.3, 0.6]}}

    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    v = (np.asarray(m.vertices) + [0, 0, 0.5]).astype(np.float32)

    def sphere(albedo, transmittance):
        return scn.object_mesh(v, np.asarray(m.faces), None, scn.principled(
            {"albedo": list(albedo), "metallic": 0.0, "roughness": 0.5, "transmittance": transmittance}))

    return elements, sphere


def _glass_sphere_in_sun(mi):
    """The firefly case (tests/test_noise.py): a rough transmissive sphere under the sun on a textured ground, two
    48-px cameras, an unbiased path tracer; returns ``(env, mesh_fn, cams, integrator, pack)``, where the pack (meadow)
    only keys the background cache by its environment spec."""
    from optimizer.scenes import builtin_scenes
    from optimizer.scenes.cameras import Camera
    from optimizer.scenes.environments import Environment

    build, sphere = _sunlit(mi, (0.3, 0.35, 0.25), 60)

    def mesh():
        return sphere((0.8, 0.8, 0.8), 0.9)

    env = Environment("glass", "glass", build, ("sun", "sky"))
    cams = [Camera((2.5, -2.5, 1.5), (0.0, 0.0, 0.4), 45.0, 48, 48),
            Camera((-2.0, -3.0, 1.2), (0.0, 0.0, 0.4), 45.0, 48, 48)]
    return env, mesh, cams, {"type": "path", "max_depth": 8, "rr_depth": 5}, builtin_scenes.get("meadow")


def test_see_through_features_against_known_cases(mi_backend):
    """The see-through albedo and normal (optimizer.rendering.denoise.see_through_features) of a sphere on a
    checkered ground, 32 px: an opaque sphere's equal the first-hit features of Mitsuba's ``aov`` integrator (today's
    feature; both at 256 spp, mean |difference| < 0.01, measured 0.002: the samples differ at edges); a fully
    transmissive, white sphere of index 1.0001 gives the object-free scene's features (mean < 0.002; per pixel
    within 2/16 of the checker's step: a stratum may cross a tile's edge); and a sphere of transmittance t, colour c
    and index 1.0001 gives, where it covers the pixel, the two-interface blend
    ``(1 - t) c + t sqrt(c) ((1 - t) c + t sqrt(c) ground)`` of the ground's feature behind it."""
    mi, _ = mi_backend
    from optimizer.rendering import scene as scn
    from optimizer.rendering.denoise import render_features, see_through_features
    from optimizer.rendering.render import coverage_and_depth
    from optimizer.scenes.cameras import Camera

    elements, sphere = _sunlit(mi, (0.2, 0.3, 0.2), 40)
    cams = [Camera((2.5, -2.5, 1.5), (0.0, 0.0, 0.4), 45.0, 32, 32)]

    def ball(albedo, t, eta):
        m = sphere(albedo, t)
        params = mi.traverse(m.bsdf())
        params["eta"] = eta
        params.update()
        return m

    opaque = ball((0.7, 0.4, 0.3), 0.0, 1.5)
    a_s, n_s = see_through_features(elements(), opaque, cams, 256)
    a_f, n_f = render_features(elements(), opaque, cams, 256, 3)
    assert a_s.shape == n_s.shape == (1, 32, 32, 3)
    assert np.abs(a_s - a_f).mean() < 0.01 and np.abs(n_s - n_f).mean() < 0.01
    a0, n0 = see_through_features(elements(), None, cams, 16)
    clear = ball((1.0, 1.0, 1.0), 1.0, 1.0001)
    a1, n1 = see_through_features(elements(), clear, cams, 16)
    assert np.abs(a1 - a0).mean() < 0.002 and np.abs(a1 - a0).max() <= 2 / 16 * 0.4 + 1e-4
    assert np.abs(n1 - n0).max() < 1e-3
    c, t = np.array([0.7, 0.4, 0.3], np.float32), 0.6
    a2, _ = see_through_features(elements(), ball(tuple(c), t, 1.0001), cams, 16)
    covered = coverage_and_depth(scn.build_scene(elements(), opaque), cams[0], opaque)[0] >= 1.0
    assert covered.sum() > 20
    expect = (1 - t) * c + t * np.sqrt(c) * ((1 - t) * c + t * np.sqrt(c) * a0[0][covered])
    np.testing.assert_allclose(a2[0][covered], expect, atol=0.02)
    assert not np.allclose(a2[0][covered], a_f[0][covered], atol=0.05)  # not the first-hit colour


def test_see_through_features_traced_only_where_a_ray_meets_the_object_equal_the_full_pass(mi_backend):
    """Given the object-free features of the same cameras, spp and seed, see_through_features traces only the pixels
    with a ray that meets the object's bounding box and takes the rest from them: the result equals the full pass
    (every ray keeps its jitter and random stream; float rounding only), and
    a sphere out of sight leaves the object-free features as they are."""
    mi, _ = mi_backend
    from optimizer.rendering import scene as scn
    from optimizer.rendering.denoise import see_through_features
    from optimizer.rendering.region import box_pixels as _box_pixels
    from optimizer.scenes.cameras import Camera

    elements, sphere = _sunlit(mi, (0.2, 0.3, 0.2), 40)
    cams = [Camera((2.5, -2.5, 1.5), (0.0, 0.0, 0.4), 45.0, 40, 32), Camera((-2.0, -3.0, 1.2), (0.0, 0.0, 0.4), 45.0, 40, 32)]
    obj = sphere((0.7, 0.6, 0.5), 0.8)
    for spp, seed in ((9, 4), (16, 7)):
        without = see_through_features(elements(), None, cams, spp, seed)
        full = see_through_features(elements(), obj, cams, spp, seed)
        part = see_through_features(elements(), obj, cams, spp, seed, scene=scn.build_scene(elements(), obj),
                                    without=without)
        for a, b in zip(part, full):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
        assert np.abs(full[0] - without[0]).max() > 0.1  # the object changes them
    hidden = [Camera((2.5, -2.5, 1.5), (6.0, -6.0, 0.4), 30.0, 16, 16)]  # looking away from the sphere
    w = see_through_features(elements(), None, hidden, 4, 1)
    p = see_through_features(elements(), obj, hidden, 4, 1, without=w)
    np.testing.assert_array_equal(p[0], w[0])
    # the traced pixels: a part of the frame that holds every pixel the object changes; a box behind the camera: all
    box = [p.size / (c.width * c.height) for c, p in zip(cams, _box_pixels(obj, cams))]
    assert all(0.05 < b < 0.8 for b in box), box
    behind = [Camera((0.0, 0.0, 0.5), (0.0, 5.0, 0.5), 60.0, 16, 16)]  # inside the sphere's box
    assert _box_pixels(obj, behind) == [None]


def test_see_through_features_keep_the_texture_seen_through_a_transmissive_object(mi_backend):
    """A rough see-through sphere (transmittance 0.9, roughness 0.3, index 1.5) on a checkered ground under the sun,
    48 px: its 16-spp render denoised with see-through features keeps more of the refracted checker than with
    first-hit features, against a 1024-spp reference (detail ratio in the sphere's mask, 1 = the reference's
    texture; measured 0.68-0.77 against 0.46-0.51 over two seeds). Its mean there stays within 8 % of the 16-spp
    render's (measured -5.5 %, as with first-hit features: the denoiser takes the sun's glints on the sphere, rare
    at 16 spp, for fireflies; the 16-spp render itself is 9 % below the reference's mean there, for the same
    glints)."""
    mi, _ = mi_backend
    import trimesh

    from camo_base.imaging import linear_to_srgb
    from evaluation.metrics.detail_ratio import detail_ratio
    from optimizer.rendering import scene as scn
    from optimizer.rendering.denoise import denoise_variant, variant_features
    from optimizer.rendering.render import coverage_and_depth, render_shaded
    from optimizer.scenes.cameras import Camera

    elements, _ = _sunlit(mi, (0.2, 0.3, 0.2), 40)
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    v = (np.asarray(m.vertices) + [0, 0, 0.5]).astype(np.float32)

    def mesh():
        return scn.object_mesh(v, np.asarray(m.faces), None, scn.principled(
            {"albedo": [0.8, 0.8, 0.8], "metallic": 0.0, "roughness": 0.3, "transmittance": 0.9}))

    cams = [Camera((2.5, -2.5, 1.5), (0.0, 0.0, 0.4), 45.0, 48, 48)]
    integ = {"type": "path", "max_depth": 8, "rr_depth": 5}
    ref = render_shaded(elements(), mesh(), cams, integ, 1024, 7)
    obj = mesh()
    mask = coverage_and_depth(scn.build_scene(elements(), obj), cams[0], obj)[0] >= 0.5
    img = render_shaded(elements(), mesh(), cams, integ, 16, 1)

    def srgb(x):
        return np.clip(linear_to_srgb(np.clip(x, 0, None)), 0, 1).astype(np.float32)

    detail, mean = {}, {}
    for d in ("oidn-raw", "oidn-through"):
        out = denoise_variant(img, *variant_features(d, elements(), mesh(), cams, 16, 1), d)
        detail[d] = float(detail_ratio(srgb(out[0]), srgb(ref[0]), mask))
        mean[d] = float(out[0][mask].mean() / img[0][mask].mean())
    print("detail ratio in the mask", detail, "mean / the 16-spp render's", mean)
    assert detail["oidn-through"] > detail["oidn-raw"] + 0.1, detail
    assert abs(detail["oidn-through"] - 1) < abs(detail["oidn-raw"] - 1), detail
    assert abs(mean["oidn-through"] - 1) < 0.08 and abs(mean["oidn-through"] - mean["oidn-raw"]) < 0.02, mean


def test_variant_features_choose_the_kind(mi_backend):
    mi, _ = mi_backend
    from optimizer.rendering.denoise import VARIANTS, variant_features

    assert VARIANTS["oidn-through"].see_through and not VARIANTS["oidn-raw"].see_through
    elements, _ = _sunlit(mi, (0.2, 0.3, 0.2), 40)
    from optimizer.scenes.cameras import Camera

    cams = [Camera((2.5, -2.5, 1.5), (0.0, 0.0, 0.4), 45.0, 8, 8)]
    assert variant_features("oidn-color", elements(), None, cams, 4) == (None, None)
    a, n = variant_features("oidn-through", elements(), None, cams, 4)
    assert a.shape == n.shape == (1, 8, 8, 3)
    with pytest.raises(ValueError, match="unknown denoiser"):
        variant_features("bm3d", elements(), None, cams, 4)


def test_a_denoised_render_is_closer_to_the_high_spp_reference_than_the_render(mi_backend):
    """A textured diffuse ground and a sphere under the sun (the built-in scenes' light), 48 px: the 16-spp render
    denoised with its features (16 spp) against a 1024-spp reference: its error (8-bit sRGB RMS) at most 0.6 x the
    16-spp render's, and the mean radiance over the frame and over the sphere within 2 % of the reference's (the
    denoiser redistributes energy, it does not create or lose it)."""
    mi, _ = mi_backend
    from camo_base.imaging import linear_to_srgb
    from optimizer.rendering import scene as scn
    from optimizer.rendering.denoise import denoise, render_features
    from optimizer.rendering.render import coverage_and_depth, render_shaded
    from optimizer.scenes.cameras import Camera

    elements, sphere = _sunlit(mi, (0.2, 0.3, 0.2), 40)
    mesh = sphere((0.7, 0.4, 0.3), 0.0)
    cams = [Camera((2.5, -2.5, 1.5), (0.0, 0.0, 0.4), 45.0, 48, 48)]
    integ = {"type": "path", "max_depth": 6, "rr_depth": 5}
    ref = render_shaded(elements(), mesh, cams, integ, 1024, 7)
    img = render_shaded(elements(), mesh, cams, integ, 16, 1)
    albedo, normal = render_features(elements(), mesh, cams, 16, 1)
    assert albedo.shape == img.shape and 0 <= albedo.min() and albedo.max() <= 1
    out = denoise(img, albedo, normal)

    def rms(a, b):
        e = lambda x: linear_to_srgb(np.clip(x, 0, None)).astype(np.float64) * 255  # noqa: E731
        return float(np.sqrt(np.mean((e(a) - e(b)) ** 2)))

    e_img, e_out = rms(img, ref), rms(out, ref)
    print("16 spp", e_img, "denoised", e_out)
    assert e_out < 0.6 * e_img, (e_out, e_img)
    sphere = coverage_and_depth(scn.build_scene(elements(), mesh), cams[0], mesh)[0] >= 0.5
    assert sphere.mean() > 0.03
    for sel in (np.ones_like(sphere), sphere):
        assert abs(out[0][sel].mean() / ref[0][sel].mean() - 1) < 0.02


def test_evaluation_renders_are_denoised_alike_and_the_object_is_no_noisier_than_the_background(mi_backend):
    """The evaluation path with the plan's denoiser (evaluation.views.ViewRenderer: noise matching, then the
    denoiser on both renders): a rough transmissive object under the sun (the case whose fireflies gave the object
    away, tests/test_noise.py) on a textured ground, 64 spp, 48 px, two seeds. The object and its 2-pixel rim are
    then no noisier than the background's same pixels (ratio < 1.15, measured 0.97; without either: 1.8) and have no
    more fireflies than the background; the denoised mean over the object stays within 5 % of the undenoised one;
    a render with the object cannot be denoised unlike its background. (The denoiser alone leaves it 1.4x noisier
    here, and on an untextured ground, which it smooths to almost no noise, 3-5x even after matching:
    docs/results/planner.md.)"""
    mi, _ = mi_backend
    from evaluation.views import ViewRenderer
    from optimizer.rendering.planner import DENOISER as den
    from optimizer.rendering.noise import fireflies, noise_rms
    from optimizer.rendering.region import dilate_px
    env, mesh, cams, integ, pack = _glass_sphere_in_sun(mi)
    out = {}
    for d, matched in (("", False), (den, True)):
        renders = []
        for seed in (0, 1):
            r = ViewRenderer(64, seed, noise_match=matched)
            bg = r.background(pack, env, cams, integ, d)
            o = r.with_object(env, mesh, cams, integ, bg, 0.5 / 255)
            assert bg.denoise == o.denoise == d and (bg.raw is not None) == bool(d)
            assert (o.noise is not None) == matched
            renders.append((bg.image, o))
        out[d] = renders
    near = np.stack([dilate_px(k, 2) for k in out[""][0][1].mask])
    ratio = {d: noise_rms(rs[0][1].image, rs[1][1].image, near) / noise_rms(rs[0][0], rs[1][0], near)
             for d, rs in out.items()}
    print("noise ratio near the object, plain / matched + denoised (%s):" % den, ratio)
    assert ratio[""] > 1.3 and ratio[den] < 1.15, ratio
    (b0, o0), (b1, o1) = out[den]
    assert fireflies(o0.image, o1.image, near) <= fireflies(b0, b1, near) + 1.0
    sel = out[""][0][1].mask
    plain = np.mean([o.image[sel].mean() for _, o in out[""]])
    mean_den = np.mean([o.image[sel].mean() for _, o in out[den]])
    assert abs(mean_den / plain - 1) < 0.05, (mean_den, plain)
    r = ViewRenderer(64, 0)
    with pytest.raises(ValueError, match="denoised as its background"):
        r.with_object(env, mesh, cams, integ, r.background(pack, env, cams, integ, ""), None, denoise=den)


def test_the_denoiser_is_opt_in_everywhere_the_evaluation_renders_are_made(capsys):
    """Off by default (it smooths the ground seen through a see-through object: docs/evaluation.md) in the planner,
    ``camo evaluate``'s settings, the evaluation plan and the study stimuli; ``--denoise`` alone turns on the default
    denoiser (oidn-raw), ``--denoise oidn-through`` the see-through one, in both CLIs and a grid's ``[evaluate]``
    (``denoise = true`` / a name); an unknown variant is a one-line error (and ``--no-denoise`` is no flag)."""
    import argparse
    import inspect

    from evaluation.settings import EvalSettings, SettingError
    from evaluation.views import evaluation_plan
    from optimizer.rendering.denoise import VARIANTS
    from optimizer.rendering.planner import DENOISER, DENOISER_BIASES, DENOISERS, PlannerSettings
    from study_site import cli as study_cli
    from study_site.render_stimuli import render_stimuli

    assert DENOISER == "oidn-raw" and set(DENOISERS) == set(DENOISER_BIASES) == {"oidn-raw", "oidn-through"}
    assert set(DENOISERS) <= set(VARIANTS)
    assert PlannerSettings().denoise == "" and EvalSettings().denoise == ""
    assert inspect.signature(evaluation_plan).parameters["denoise"].default == ""
    assert inspect.signature(render_stimuli).parameters["denoise"].default == ""
    assert EvalSettings.from_options({}).denoise == ""
    assert EvalSettings.from_options({"denoise": True}).denoise == "oidn-raw"  # a grid's `denoise = true`
    assert EvalSettings.from_options({"denoise": False}).denoise == ""
    assert EvalSettings.from_options({"denoise": "oidn-through"}).denoise == "oidn-through"
    with pytest.raises(SettingError, match=r"denoise must be one of oidn-raw, oidn-through, got 'bm3d'"):
        EvalSettings.from_options({"denoise": "bm3d"})
    with pytest.raises(SettingError, match="denoise must be one of"):
        EvalSettings(denoise="oidn-color").validate()  # a variant without a measured bias on the object
    with pytest.raises(ValueError, match="unknown denoiser 'bm3d'"):
        PlannerSettings(denoise="bm3d")
    # the other switches still turn their fields off
    assert EvalSettings.from_options({"no_noise_match": True, "denoise": True}).noise_match is False
    with pytest.raises(SettingError, match="no_denoise"):
        EvalSettings.from_options({"no_denoise": True})
    ap = argparse.ArgumentParser()
    study_cli.register(ap.add_subparsers(dest="cmd"))
    base = ["study", "build-stimuli", "EVAL", "--out", "OUT"]
    assert ap.parse_args(base).denoise == "" and ap.parse_args(base + ["--denoise"]).denoise == "oidn-raw"
    assert ap.parse_args(base + ["--denoise", "oidn-through"]).denoise == "oidn-through"
    assert ap.parse_args(base + ["--denoise=oidn-through"]).denoise == "oidn-through"
    with pytest.raises(SystemExit) as exc:
        ap.parse_args(base + ["--denoise", "bm3d"])
    assert exc.value.code != 0
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--denoise" in err and "invalid choice: 'bm3d'" in err and "oidn-through" in err


def test_the_object_gets_the_samples_that_leave_it_no_noisier_than_its_denoised_surroundings(mi_backend):
    """With the see-through denoiser (oidn-through) after noise matching, a rough transmissive sphere under the sun
    on a textured ground stays noisier than the denoised background in the same pixels (the denoiser smooths the
    background more than the object). The evaluation's pilot (evaluation.views.object_spp_pilot, its own seeds)
    measures that and gives the object and its rim k x the spp; measured on two other seeds, the object is then no
    noisier than its surroundings, and the extra samples lie on the object and its rim only."""
    mi, _ = mi_backend
    from evaluation.views import OBJECT_MARGIN, ViewRenderer, denoised_noise_ratio, object_pixels, object_spp_pilot
    from optimizer.rendering.planner import Plan
    env, mesh, cams, integ, pack = _glass_sphere_in_sun(mi)
    plan = Plan(integ, True, 8, "", [], region_search=True, denoise="oidn-through")
    pilot = object_spp_pilot(pack, env, cams, plan, 64, seed=0, mesh_fn=mesh)
    print(pilot["why"])
    assert pilot["ratio"] > 1.1 and pilot["factor"] > 1, pilot
    rs = [ViewRenderer(64, s, noise_match=True) for s in (0, 1)]  # the evaluation's own streams
    after = denoised_noise_ratio(pack, env, mesh, cams, plan, 64, 0, pilot["factor"], True, rs)[2]
    print(f"denoised noise ratio near the object at x{pilot['factor']} (other seeds):", after)
    assert after <= 1.05, after  # measured 0.82 at x8 (x1: 1.43 on these seeds, 1.56 on the pilot's)
    # the extra samples: only where the object or its rim is, and k x there
    bg = rs[0].background(pack, env, cams, integ, "oidn-through")
    o = rs[0].with_object(env, mesh, cams, integ, bg, 0.5 / 255, object_spp=pilot["factor"])
    o1 = rs[0].with_object(env, mesh, cams, integ, bg, 0.5 / 255)
    px = object_pixels(o.coverage, o.region, OBJECT_MARGIN)
    assert px.any() and not px.all()
    np.testing.assert_array_equal(o.noise.factor, o1.noise.factor * np.where(px, pilot["factor"], 1))


def test_the_object_region_at_a_low_spp_gets_the_stated_samples_and_agrees_with_the_whole_frame(mi_backend):
    """The evaluation render at a low spp with the object's samples allocated to it (issue 28: the object and its
    rim at k x a 4-spp render, ``bench/bench_planner.py --evaluate-as oidn-through:8:max``): with
    ``object_combine="max"`` each pixel of the object and its rim gets the larger of noise matching's factor and k,
    every other pixel matching's alone (so the samples sit where stated: 4 k spp on the object); with
    ``region_min_spp=0`` only the region the object can change is rendered, and that render agrees with the whole
    frame's within the noise (its pixels outside the region are the background's, drawn by the same random
    numbers): RMS difference below a third of the whole frame's seed-to-seed noise (measured 0.02 against 13.6 /255,
    before a denoiser); product and max give the same image where both factors are 1."""
    mi, _ = mi_backend
    from evaluation.views import OBJECT_MARGIN, ViewRenderer, object_pixels
    from optimizer.rendering.noise import noise_rms
    env, mesh, cams, integ, pack = _glass_sphere_in_sun(mi)
    k, spp = 8, 4
    r = ViewRenderer(spp, 0, noise_match=True)
    bg = r.background(pack, env, cams, integ)
    plain = r.with_object(env, mesh, cams, integ, bg, 0.5 / 255)  # whole frames below REGION_MIN_SPP
    assert plain.region is None and plain.noise is not None
    o = r.with_object(env, mesh, cams, integ, bg, 0.5 / 255, object_spp=k, object_combine="max")
    px = object_pixels(o.coverage, None, OBJECT_MARGIN)
    assert 0.02 < px.mean() < 0.6
    np.testing.assert_array_equal(o.noise.factor, np.maximum(plain.noise.factor, np.where(px, k, 1)))
    assert (o.noise.factor[px] >= k).all() and (o.noise.factor[~px] == plain.noise.factor[~px]).all()
    prod = r.with_object(env, mesh, cams, integ, bg, 0.5 / 255, object_spp=k)
    assert o.noise.extra_samples < prod.noise.extra_samples  # the larger, not the product
    same = (o.noise.factor == 1) & (prod.noise.factor == 1)
    # the same samples where both factors are 1; equal up to the LLVM backend's multi-threaded film accumulation,
    # whose summation order moved 9 of 11,097 values by <= 1.5e-8 inside the full test run (2026-11-28)
    np.testing.assert_allclose(o.image[same], prod.image[same], rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="combine"):
        r.with_object(env, mesh, cams, integ, bg, 0.5 / 255, object_spp=k, object_combine="sum")
    # only the region, at this low spp: the same image as the whole frame's, within the noise
    reg = r.with_object(env, mesh, cams, integ, bg, 0.5 / 255, object_spp=k, object_combine="max", region_min_spp=0)
    assert reg.region is not None and 0 < reg.region.mean() < 1
    assert (reg.noise.factor[px & reg.region] >= k).all()
    r1 = ViewRenderer(spp, 1, noise_match=True)
    o1 = r1.with_object(env, mesh, cams, integ, r1.background(pack, env, cams, integ), 0.5 / 255, object_spp=k,
                        object_combine="max")
    every = np.ones(o.mask.shape, bool)
    noise, diff = noise_rms(o.image, o1.image, every), noise_rms(reg.image, o.image, every)
    print(f"region vs whole frame: {diff:.2f}/255; whole frame seed to seed: {noise:.2f}/255")
    assert noise > 0.5 and diff < noise / 3, (diff, noise)


def test_the_objects_features_at_more_spp_are_less_noisy_and_the_rest_the_backgrounds(mi_backend):
    """``ViewRenderer.with_object(object_feature_spp=N)``: the see-through features of the render with the object at
    N spp where rays can meet the object's box, the background's (at the render's spp) everywhere else: outside
    the box they are the background's exactly; on the object their seed-to-seed noise at 16 spp is below 0.7 of
    that at 4 spp (1/sqrt 4 = 0.5 for independent strata; measured 0.49)."""
    mi, _ = mi_backend
    from evaluation.views import ViewRenderer
    from optimizer.rendering.region import box_pixels as _box_pixels
    env, mesh, cams, integ, pack = _glass_sphere_in_sun(mi)
    feats = {}
    for seed in (0, 1):
        r = ViewRenderer(4, seed)
        bg = r.background(pack, env, cams, integ, "oidn-through")
        img = r.with_object(env, mesh, cams, integ, bg).image
        for fspp in (None, 16):
            _, _, f = r._denoised(env, mesh(), cams, img, "oidn-through", without=bg.features, feature_spp=fspp)
            feats[(seed, fspp)] = f
        box = np.zeros(img.shape[:3], bool)
        for v, p in enumerate(_box_pixels(mesh(), cams)):
            box[v].flat[p] = True
        assert 0 < box.mean() < 1
        for a, b in zip(feats[(seed, 16)], bg.features):
            np.testing.assert_array_equal(a[~box], b[~box])
    cov = ViewRenderer(4, 0).with_object(env, mesh, cams, integ).coverage >= 0.5
    spread = {f: float(np.sqrt(np.mean((feats[(0, f)][0] - feats[(1, f)][0])[cov] ** 2))) for f in (None, 16)}
    print("see-through albedo seed-to-seed RMS on the object, 4 vs 16 spp:", spread)
    assert spread[None] > 0 and spread[16] < 0.7 * spread[None], spread
