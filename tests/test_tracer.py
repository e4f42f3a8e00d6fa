"""optimizer.rendering.tracer: Mitsuba's path estimator over chosen pixels, with per-pixel random streams."""

from __future__ import annotations

import numpy as np
import pytest


def _scene(mi, integrator=None, sensors=None, with_glass=True, light="area"):
    d = {
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(4),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.4]}}},
        "wall": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 2, 1]).rotate([1, 0, 0], 90).scale(3),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.3, 0.6, 0.3]}}},
    }
    if light == "area":
        d["lamp"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0.5, -0.5, 3]).rotate([1, 0, 0], 180)
                     .scale(0.6), "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [9.0, 8.0, 7.0]}}}
        d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.05, 0.06, 0.08]}}
    else:
        d["sun"] = {"type": "sunsky", "sun_direction": [0.4, -0.3, 0.6]}
    if with_glass:
        d["object"] = {"type": "sphere", "center": [0, 0, 0.6], "radius": 0.5,
                       "bsdf": {"type": "principled", "base_color": {"type": "rgb", "value": [0.8, 0.7, 0.6]},
                                "roughness": 0.3, "spec_trans": 0.8}}
    if integrator:
        d["integrator"] = integrator
    for i, s in enumerate(sensors or []):
        d[f"sensor_{i}"] = s
    return mi.load_dict(d)


def _cams(n=2, w=24, h=20):
    from optimizer.scenes.cameras import Camera

    return [Camera((3.0 * np.cos(a), -3.0 * np.sin(a) - 1.0, 1.8), (0.0, 0.0, 0.5), 50.0, w, h)
            for a in np.linspace(0.3, 1.2, n)]


@pytest.mark.parametrize("light", ["area", "sunsky"])
def test_same_estimator_as_mitsuba_path(mi_backend, light):
    """Per pixel, the tracer's mean and Mitsuba's path (depth 6, Russian roulette from 3) agree within their Monte
    Carlo errors (t statistics from 6 independent renders of each), and their noise is the same."""
    mi, _ = mi_backend
    from optimizer.rendering import scene as scn
    from optimizer.rendering.tracer import render_views

    cams = _cams(1)
    c = cams[0]
    spp, n = 64, 6
    sc = _scene(mi, {"type": "path", "max_depth": 6, "rr_depth": 3}, [scn.batch(cams, spp)], light=light)
    ours = np.stack([render_views(sc, 1, c.width, c.height, spp, s, 6, 3)[0] for s in range(n)]).astype(np.float64)
    theirs = np.stack([np.asarray(mi.render(sc, spp=spp, seed=100 + s)) for s in range(n)]).astype(np.float64)
    se2 = ours.var(0, ddof=1) / n + theirs.var(0, ddof=1) / n
    diff = ours.mean(0) - theirs.mean(0)
    t = diff / np.sqrt(np.maximum(se2, 1e-10))
    assert np.mean(np.abs(t) > 4.5) < 0.01, float(np.mean(np.abs(t) > 4.5))
    assert abs(float(diff.mean())) < 4 * float(np.sqrt(se2.sum())) / diff.size + 1e-5
    # the noise: the median per-pixel variance (the mean is dominated by a few fireflies of the sun through glass)
    ratio = float(np.median(ours.var(0, ddof=1)) / np.median(theirs.var(0, ddof=1)))
    assert 0.8 < ratio < 1.25, ratio


def test_a_subset_of_pixels_is_exactly_those_pixels_of_the_full_frame(mi_backend):
    """The random streams are keyed by the pixel: rendering some pixels gives bit for bit what the full frame has
    there, whatever else is rendered, and a render with and without the object shares them."""
    mi, _ = mi_backend
    from optimizer.rendering import scene as scn
    from optimizer.rendering.tracer import render_views

    cams = _cams(2)
    w, h = cams[0].width, cams[0].height
    sc = _scene(mi, sensors=[scn.batch(cams, 8)])
    full = render_views(sc, 2, w, h, 8, 5, 6)
    rng = np.random.default_rng(0)
    masks = rng.random((2, h, w)) < 0.3
    part = render_views(sc, 2, w, h, 8, 5, 6, masks=masks, fill=np.full_like(full, -1.0))
    np.testing.assert_array_equal(part[masks], full[masks])
    assert np.all(part[~masks] == -1.0)
    again = render_views(sc, 2, w, h, 8, 5, 6)
    np.testing.assert_array_equal(again, full)  # deterministic (a fixed-order block sum, no atomics)
    other = render_views(sc, 2, w, h, 8, 6, 6)
    assert not np.array_equal(other, full)
    # common random numbers: without the object, pixels whose paths never meet it are identical
    bare = render_views(_scene(mi, sensors=[scn.batch(cams, 8)], with_glass=False), 2, w, h, 8, 5, 6)
    same = np.all(bare == full, axis=-1)
    assert same.mean() > 0.2


def test_record_splits_every_pixel_by_depth_exactly(mi_backend):
    """A render at max_depth M equals the recorded m1 + ... + mM of the full-depth render with the same seed
    (the same samples), the partial sums' squares give the variance, and the categories stay within the total."""
    mi, _ = mi_backend
    from optimizer.rendering import scene as scn
    from optimizer.rendering.tracer import LUMA, record_names, render_views

    cams = _cams(1, 16, 12)
    w, h = cams[0].width, cams[0].height
    sc = _scene(mi, sensors=[scn.batch(cams, 16)])
    K = 8
    img, rec = render_views(sc, 1, w, h, 16, 3, K, K, record=True)  # no Russian roulette: depths truncate exactly
    names = record_names(K, len(sc.emitters()))
    ix = {n: i for i, n in enumerate(names)}
    y = img[0] @ np.asarray(LUMA, np.float32)
    m = rec[0][..., [ix[f"m{i}"] for i in range(1, K + 1)]]
    np.testing.assert_allclose(m.sum(-1), y, rtol=1e-4, atol=1e-6)
    for M in (2, 3, 5):
        short = render_views(sc, 1, w, h, 16, 3, M, K)[0] @ np.asarray(LUMA, np.float32)
        np.testing.assert_allclose(m[..., :M].sum(-1), short, rtol=1e-4, atol=1e-6)
    assert np.all(m[..., 0] >= 0) and np.all(rec[0][..., ix["n0"]] == 1.0)
    var = rec[0][..., ix[f"q{K}"]] - y ** 2
    assert np.all(var > -1e-4)
    e = sum(rec[0][..., ix[n]] for n in names if n.startswith("e"))
    np.testing.assert_allclose(e, y, rtol=1e-4, atol=1e-6)  # every contribution belongs to one emitter
    for cat in ("via", "via_t", "seen_t"):
        assert np.all(rec[0][..., ix[cat]] <= y + 1e-5)
    assert rec[0][..., ix["seen_t"]].max() > 0  # the glass sphere is seen through


def test_sobol_samples_are_stratified_progressive_and_uniform(mi_backend):
    """The ``sobol`` sampler's 2D pairs: any aligned 2^m run of a pixel's samples has one sample in each of the 2^m
    elementary rectangles of every shape (a (0, m, 2)-net), sample s is the same whatever else is drawn, and over
    pixels every sample is uniform (unbiased) and the pairs are uncorrelated."""
    mi, _ = mi_backend
    from optimizer.rendering.tracer import sobol01, sobol_samples

    # the unscrambled sequence is Sobol's: Mitsuba's own radical inverse and sobol_2
    import drjit as dr

    i = dr.arange(mi.UInt32, 64)
    x, y = sobol01(i)
    np.testing.assert_allclose(np.asarray(x, np.float64) / 2**32, np.asarray(mi.radical_inverse_2(i, mi.UInt32(0))))
    np.testing.assert_allclose(np.asarray(y, np.float64) / 2**32, np.asarray(mi.sobol_2(i, mi.UInt32(0))))
    P, S = 500, 32
    pix = mi.UInt32(np.repeat(np.arange(P), S).astype(np.uint32))
    smp = mi.UInt32(np.tile(np.arange(S), P).astype(np.uint32))
    pairs = [(np.asarray(p.x).reshape(P, S), np.asarray(p.y).reshape(P, S)) for p in sobol_samples(pix, smp, 11, 3)]
    for a, b in pairs:
        assert a.min() >= 0 and a.max() < 1 and b.min() >= 0 and b.max() < 1
        for m, start in ((4, 0), (4, 16), (5, 0), (3, 8)):
            n = 2 ** m
            for kx in range(m + 1):  # rectangles 2^-kx x 2^-(m - kx)
                cell = (a[:, start:start + n] * 2 ** kx).astype(int) * 2 ** (m - kx) + \
                       (b[:, start:start + n] * 2 ** (m - kx)).astype(int)
                assert all(len(set(c)) == n for c in cell), (m, start, kx)
        # uniform over pixels: each sample index's mean over 500 pixels ~ 0.5 (sd 0.29 / sqrt 500 = 0.013)
        assert np.abs(a.mean(0) - 0.5).max() < 0.06 and np.abs(b.mean(0) - 0.5).max() < 0.06
    # the pairs are decorrelated: the camera pair's x against the emitter pair's x, per sample over pixels
    r = np.corrcoef(pairs[0][0].ravel(), pairs[1][0].ravel())[0, 1]
    assert abs(r) < 0.03, r
    # ... and within each pixel (32 samples): |r| of independent draws averages ~0.14; without the index shuffle
    # pair 1's x was a fixed function of pair 0's (|r| ~ 0.75 per pixel, of random sign)
    per = [abs(np.corrcoef(pairs[0][0][p], pairs[j][0][p])[0, 1]) for p in range(P) for j in (1, 2)]
    assert np.mean(per) < 0.2, np.mean(per)
    # progressive: the first 8 samples drawn alone are the first 8 of the 32
    few = sobol_samples(mi.UInt32(np.repeat(np.arange(P), 8).astype(np.uint32)),
                        mi.UInt32(np.tile(np.arange(8), P).astype(np.uint32)), 11, 1)[0]
    np.testing.assert_array_equal(np.asarray(few.x).reshape(P, 8), pairs[0][0][:, :8])


def test_sobol_sampler_unbiased_exact_on_subsets_and_less_noisy(mi_backend):
    """``render_views(sampler="sobol")``: the same mean as the independent sampler (t statistics over 8 seeds),
    a subset of pixels is bit for bit the full frame's, and at 16 spp its per-pixel variance over seeds is lower
    (the pixel footprint, the first emitter and BSDF samples stratified)."""
    mi, _ = mi_backend
    from optimizer.rendering import scene as scn
    from optimizer.rendering.tracer import render_views

    cams = _cams(1)
    c = cams[0]
    spp, n = 16, 8
    sc = _scene(mi, sensors=[scn.batch(cams, spp)], light="sunsky")
    ind = np.stack([render_views(sc, 1, c.width, c.height, spp, s, 6, 5)[0] for s in range(n)]).astype(np.float64)
    sob = np.stack([render_views(sc, 1, c.width, c.height, spp, s, 6, 5, sampler="sobol")[0]
                    for s in range(n)]).astype(np.float64)
    se2 = ind.var(0, ddof=1) / n + sob.var(0, ddof=1) / n
    t = (ind.mean(0) - sob.mean(0)) / np.sqrt(np.maximum(se2, 1e-10))
    assert np.mean(np.abs(t) > 4.5) < 0.01, float(np.mean(np.abs(t) > 4.5))
    ratio = float(np.median(sob.var(0, ddof=1)) / np.median(ind.var(0, ddof=1)))
    assert ratio < 0.8, ratio
    full = render_views(sc, 1, c.width, c.height, spp, 3, 6, 5, sampler="sobol")
    masks = np.random.default_rng(1).random((1, c.height, c.width)) < 0.3
    part = render_views(sc, 1, c.width, c.height, spp, 3, 6, 5, masks=masks, fill=np.zeros_like(full),
                        sampler="sobol")
    np.testing.assert_array_equal(part[masks], full[masks])
    with pytest.raises(ValueError, match="sampler"):
        render_views(sc, 1, c.width, c.height, spp, 3, 6, 5, sampler="halton")
