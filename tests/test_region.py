"""optimizer.rendering.region: the pixels an object can change, and region renders exact against the full frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest


def _env(mi, elevation_deg: float, kind: str = "directional"):
    """A grey ground lit by a compact light ``elevation_deg`` above the horizon and a dim sky."""
    el = np.radians(elevation_deg)
    towards = [float(np.cos(el)), 0.0, float(np.sin(el))]

    def build():
        out = {"ground": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(40),
                          "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.45, 0.42, 0.38]}}},
               "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.15, 0.18, 0.25]}}}
        if kind == "directional":
            out["sun"] = {"type": "directional", "direction": [-c for c in towards],
                          "irradiance": {"type": "rgb", "value": [3.0, 2.8, 2.5]}}
        return out

    return build, towards


def _box(mi, centre=(0.0, 0.0, 0.35), half=(0.25, 0.25, 0.35)):
    import trimesh

    from optimizer.rendering import scene as scn

    m = trimesh.creation.box(extents=[2 * h for h in half])
    v = np.asarray(m.vertices) + np.asarray(centre)
    return scn.object_mesh(v.astype(np.float32), np.asarray(m.faces), None,
                           {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.2, 0.2]}}, smooth=False)


def _cams(w=48, h=36):
    from optimizer.scenes.cameras import Camera

    # one camera looking along the shadow (it falls towards -x), one from the side
    return [Camera((3.5, 0.8, 2.2), (-1.5, 0.0, 0.0), 55.0, w, h), Camera((-1.0, -4.5, 2.5), (-1.2, 0.0, 0.0), 60.0, w, h)]


def test_a_long_shadow_under_a_low_sun_stays_inside_the_region(mi_backend):
    """Sun 8 degrees above the horizon: the shadow of a 0.7-high box is ~5 units long. The region holds every pixel
    whose converged change (with vs without the object, common random numbers, 512 spp) exceeds the threshold, and
    the region render composited on the background equals the full-frame render there and within the threshold
    elsewhere."""
    mi, _ = mi_backend
    from camo_base.imaging import linear_to_srgb
    from optimizer.rendering import scene as scn
    from optimizer.rendering.region import THRESHOLD
    from optimizer.rendering.render import coverage_and_depth, render_shaded, render_with_region
    from scipy.ndimage import uniform_filter

    build, towards = _env(mi, 8.0)
    cams = _cams()
    mesh = _box(mi)
    integ = {"type": "path", "max_depth": 6, "rr_depth": 5}
    spp = 512
    sc = scn.build_scene(build(), mesh)
    cov = np.stack([coverage_and_depth(sc, c, mesh)[0] for c in cams])
    bg = render_shaded(build(), None, cams, integ, spp, 3)
    full = render_shaded(build(), mesh, cams, integ, spp, 3)
    part, reg = render_with_region(build, mesh, cams, integ, spp, 3, bg, cov)
    assert len(reg.lights) == 1 and float(np.dot(reg.lights[0], towards)) > 0.9999  # the sun: the one compact light
    enc = lambda x: linear_to_srgb(np.clip(x, 0, None)).astype(np.float64)  # noqa: E731
    change = np.stack([uniform_filter(np.abs(enc(full[v]) - enc(bg[v])).max(-1), 3) for v in range(len(cams))])
    shadowed = change > 2 * THRESHOLD
    assert shadowed.mean() > 0.1  # a long shadow indeed
    assert not (shadowed & ~reg.masks).any(), int((shadowed & ~reg.masks).sum())
    assert max(reg.bound_share) > 0.1  # the geometric bound alone reaches far along the shadow
    np.testing.assert_array_equal(part[reg.masks], full[reg.masks])  # exact where rendered
    outside = np.stack([uniform_filter(np.abs(enc(part[v]) - enc(full[v])).max(-1), 3) for v in range(len(cams))])
    assert outside.max() <= 2 * THRESHOLD, float(outside.max() * 255)
    assert reg.share[0] < 0.95  # and it is a region: the sky and the far ground are left out


def test_a_region_grows_where_its_border_still_changes(mi_backend):
    """Without compact lights (an even sky) the start is the object alone; the soft shadow around it makes the
    border change, and the region grows until it no longer does."""
    mi, _ = mi_backend
    from optimizer.rendering import scene as scn
    from optimizer.rendering.region import THRESHOLD, border, change
    from optimizer.rendering.render import coverage_and_depth, render_shaded, render_with_region

    build, _ = _env(mi, 30.0, kind="sky")
    cams = _cams()
    mesh = _box(mi)
    integ = {"type": "path", "max_depth": 6, "rr_depth": 5}
    sc = scn.build_scene(build(), mesh)
    cov = np.stack([coverage_and_depth(sc, c, mesh)[0] for c in cams])
    bg = render_shaded(build(), None, cams, integ, 256, 5)
    img, reg = render_with_region(build, mesh, cams, integ, 256, 5, bg, cov)
    assert reg.lights == [] and reg.steps >= 2
    assert reg.share[0] > (cov[0] > 0).mean() + 0.05  # grown beyond the object
    for v in range(len(cams)):
        edge = border(reg.masks[v])
        assert not (edge & (change(img[v], bg[v], reg.masks[v]) > THRESHOLD)).any()


def test_no_compact_light_under_an_even_sky(mi_backend):
    mi, _ = mi_backend
    from optimizer.rendering import scene as scn
    from optimizer.rendering.region import compact_lights

    build, _ = _env(mi, 30.0, kind="sky")
    assert len(compact_lights(scn.build_scene(build()), np.zeros(3))) == 0
    build, towards = _env(mi, 30.0)
    d = compact_lights(scn.build_scene(build()), np.zeros(3))
    assert len(d) == 1 and float(d[0] @ np.asarray(towards)) > 0.9999


def test_masks_resize_conservatively():
    from optimizer.rendering.region import bbox, fill_hull, resize_all, resize_any

    m = np.zeros((4, 6), bool)
    m[1, 2] = True
    up = resize_any(m, (8, 12))
    assert up.sum() == 4 and up[2:4, 4:6].all()
    down = resize_any(up, (4, 6))
    np.testing.assert_array_equal(down, m)
    assert not resize_all(m, (2, 3)).any() and resize_all(np.ones((4, 6), bool), (3, 5)).all()
    assert bbox(up) == (4, 2, 6, 4) and bbox(np.zeros((3, 3), bool)) is None
    tri = fill_hull(np.array([[1.0, 1.0], [9.0, 1.0], [1.0, 9.0], [np.nan, 0.0]]), (10, 10))
    assert tri[2, 2] and not tri[8, 8] and tri.sum() > 25


@pytest.mark.parametrize("radius", [1, 2, 5, 17])
def test_dilation_by_a_disc_matches_scipys_structure(radius):
    """The distance-transform dilation is the binary dilation by the disc ``x^2 + y^2 <= r^2``, pixel for pixel."""
    from scipy.ndimage import binary_dilation

    from optimizer.rendering.region import dilate_px

    m = np.random.default_rng(radius).random((40, 57)) < 0.01
    m[0, 0] = m[-1, 30] = True  # next to the frame's edges
    yy, xx = np.mgrid[-radius: radius + 1, -radius: radius + 1]
    np.testing.assert_array_equal(dilate_px(m, radius), binary_dilation(m, structure=(xx**2 + yy**2) <= radius**2))
    assert not dilate_px(np.zeros((5, 5), bool), 3).any() and dilate_px(m, 0).sum() == m.sum()


def test_change_sees_a_mean_effect_not_noise():
    """Zero-mean noise of +-8/255 (sRGB) does not read as a change; a 2/255 darkening does, at its full size."""
    from camo_base.imaging import linear_to_srgb, srgb_to_linear

    from optimizer.rendering.region import change

    bg_srgb = np.full((12, 12, 3), 0.5)
    checker = np.where((np.add.outer(np.arange(12), np.arange(12)) % 2)[..., None] == 0, 8.0, -8.0) / 255
    rendered = np.ones((12, 12), bool)
    bg = srgb_to_linear(bg_srgb)
    noisy = change(srgb_to_linear(bg_srgb + checker), bg, rendered)
    assert noisy[1:-1, 1:-1].max() < 1.0 / 255  # a 3 x 3 box holds 5 of one sign and 4 of the other: 8/9/255
    shadow = change(srgb_to_linear(bg_srgb - 2.0 / 255), bg, rendered)
    np.testing.assert_allclose(shadow, 2.0 / 255, atol=1e-4)
    assert np.allclose(linear_to_srgb(bg), bg_srgb, atol=1e-6)
