"""The budgeted projective integrators (optimizer/rendering/projective.py): N primary-silhouette samples per view give
the same gradient as Mitsuba's ``W * H * sppp`` samples, checked against finite differences.

Scene: a square area light (a 2-triangle mesh) in front of a black background, seen by a 32^2 camera
whose film samples its border (box filter: border 0, as camo's training films; Gaussian: border 2, so the
sampled area is larger than the crop). The
loss weights the image by a horizontal ramp; translating the square in x changes it only through the
square's outline (a constant emitter has no interior derivative), so the whole gradient is the
primary-silhouette term.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

RES = 32


def _square_obj(tmp: Path) -> Path:
    p = tmp / "square.obj"
    p.write_text("v -0.5 -0.5 0\nv 0.5 -0.5 0\nv 0.5 0.5 0\nv -0.5 0.5 0\nf 1 2 3\nf 1 3 4\n")
    return p


def _scene(mi, integrator: dict, obj: Path, rfilter: str = "box"):
    return mi.load_dict({
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": mi.ScalarTransform4f().look_at([0.2, -0.1, 2.5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": RES, "height": RES, "sample_border": True,
                            "rfilter": {"type": rfilter}},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "square": {"type": "obj", "filename": str(obj), "face_normals": True,
                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 0.8, 0.6]}}},
    })


def _ramp(mi):
    x = np.linspace(0.0, 1.0, RES, dtype=np.float32)
    return mi.TensorXf(np.repeat(np.broadcast_to(x[None, :, None], (RES, RES, 1)), 3, axis=2).copy())


def _loss_and_grad(mi, dr, scene, ramp, seed: int) -> tuple[float, float]:
    params = mi.traverse(scene)
    key = "square.vertex_positions"
    base = dr.detach(params[key])
    tx = mi.Float(0.0)
    dr.enable_grad(tx)
    shift = np.zeros(dr.width(base), np.float32)
    shift[0::3] = 1.0  # x of every vertex
    shift = mi.Float(shift)
    params[key] = base + shift * tx
    params.update()
    img = mi.render(scene, params, spp=0, seed=seed, seed_grad=seed + 7919)
    loss = dr.sum((img * ramp).array)
    dr.backward(loss)
    g = float(dr.grad(tx)[0])
    params[key] = base
    params.update()
    return float(loss[0]), g


def _fd(mi, dr, obj: Path, ramp, rfilter: str, h: float = 0.05) -> float:
    """Central difference of the loss (same seed both sides, 1024 spp: the noise cancels)."""
    vals = []
    for sign in (1.0, -1.0):
        sc = _scene(mi, {"type": "direct"}, obj, rfilter)
        params = mi.traverse(sc)
        v = np.asarray(params["square.vertex_positions"]).copy()
        v[0::3] += sign * h
        params["square.vertex_positions"] = mi.Float(v)
        params.update()
        img = mi.render(sc, spp=1024, seed=11)
        vals.append(float(dr.sum((img * ramp).array)[0]))
    return (vals[0] - vals[1]) / (2 * h)


@pytest.mark.parametrize("base,rfilter", [("prb_projective", "box"), ("direct_projective", "box"),
                                          ("prb_projective", "gaussian")])
def test_budgeted_silhouette_gradient_matches_finite_differences_and_mitsuba(mi_backend, tmp_path, base, rfilter):
    mi, dr = mi_backend
    from optimizer.rendering.projective import NAMES

    obj = _square_obj(tmp_path)
    ramp = _ramp(mi)
    fd = _fd(mi, dr, obj, ramp, rfilter)
    assert fd > 1.0  # moving right brightens the right-weighted image

    common = {"max_depth": 2, "sppc": 4, "sppp": 4, "sppi": 0}
    seeds = range(1, 49)
    budget = _scene(mi, dict(common, type=NAMES[base], silhouette_samples=2048), obj, rfilter)
    g_budget = np.array([_loss_and_grad(mi, dr, budget, ramp, s)[1] for s in seeds])
    # ours: 2048 samples instead of 32^2 * 4, unbiased with or without a filter border. Both estimators sit
    # ~2.5 % below the finite difference in this scene (0.977 +- 0.004 ours, 0.969 +- 0.008 Mitsuba's at
    # sppp = 1, over 150 seeds), hence 5 %.
    assert abs(g_budget.mean() - fd) < 0.05 * fd, (g_budget.mean(), fd)
    if rfilter == "box":  # Mitsuba's own pass agrees (with a Gaussian border it is (36/32)^2 too large)
        mitsuba = _scene(mi, dict(common, type=base), obj, rfilter)
        g_mitsuba = np.array([_loss_and_grad(mi, dr, mitsuba, ramp, s)[1] for s in seeds])
        assert abs(g_mitsuba.mean() - fd) < 0.05 * fd, (g_mitsuba.mean(), fd)
        assert abs(g_budget.mean() - g_mitsuba.mean()) < 0.04 * fd
    assert np.all(np.isfinite(g_budget)) and g_budget.std() < 0.15 * fd  # each estimate is usable on its own
    assert len(set(g_budget.round(6))) == len(g_budget)  # the seed reaches the budgeted stream


def test_silhouette_pass_launches_the_budget(mi_backend, tmp_path):
    """The silhouette kernels run N samples, not the film's (W + 2 * border) * (H + 2 * border) * sppp."""
    mi, dr = mi_backend
    from optimizer.rendering.projective import NAMES

    obj = _square_obj(tmp_path)
    ramp = _ramp(mi)
    sc = _scene(mi, {"type": NAMES["prb_projective"], "max_depth": 2, "sppc": 4, "sppp": 1, "sppi": 0,
                     "silhouette_samples": 300}, obj)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        _loss_and_grad(mi, dr, sc, ramp, 3)
        dr.sync_thread()
        sizes = {k.get("size") for k in dr.kernel_history()}
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert 300 in sizes


def test_equivalent_spp():
    from optimizer.rendering.projective import equivalent_spp

    assert equivalent_spp(36, 36, 36 * 36 * 4) == pytest.approx(4.0)  # N = Mitsuba's count: its own weight
    assert equivalent_spp(132, 132, 1024) == pytest.approx(1024 / 132**2)
    with pytest.raises(ValueError):
        equivalent_spp(8, 8, 0)


def test_silhouette_view_subset_is_the_weighted_sum_of_the_chosen_views(mi_backend, tmp_path):
    """silhouette_views: the chosen views' silhouette terms times their weight, the others none. With a
    constant emitter the whole gradient is the silhouette term, so the subset's gradient must equal the
    weighted sum of the per-view gradients (same seeds: same samples)."""
    mi, dr = mi_backend
    from optimizer.rendering.projective import NAMES, silhouette_view_weights

    obj = _square_obj(tmp_path)
    ramp = _ramp(mi)
    origins = ([0.2, -0.1, 2.5], [-0.6, 0.3, 2.4], [0.5, 0.5, 2.2], [-0.3, -0.6, 2.6])
    sensors = {f"cam{i}": {"type": "perspective", "fov": 45,
                           "to_world": mi.ScalarTransform4f().look_at(o, [0, 0, 0], [0, 1, 0]),
                           "film": {"type": "hdrfilm", "width": RES, "height": RES, "sample_border": True,
                                    "rfilter": {"type": "box"}},
                           "sampler": {"type": "independent", "sample_count": 4}} for i, o in enumerate(origins)}
    scene = mi.load_dict({"type": "scene", **sensors,
                          "integrator": {"type": NAMES["prb_projective"], "max_depth": 2, "sppc": 4, "sppp": 1,
                                         "sppi": 0, "silhouette_samples": 512},
                          "square": {"type": "obj", "filename": str(obj), "face_normals": True,
                                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 0.8, 0.6]}}}})
    integ = scene.integrator()
    params = mi.traverse(scene)
    key = "square.vertex_positions"
    base = dr.detach(params[key])
    shift = np.zeros(dr.width(base), np.float32)
    shift[0::3] = 1.0

    def grad(views: list[int]) -> float:
        tx = mi.Float(0.0)
        dr.enable_grad(tx)
        params[key] = base + mi.Float(shift) * tx
        params.update()
        loss = mi.Float(0.0)
        for v in views:
            img = mi.render(scene, params, sensor=v, spp=0, seed=10 + v, seed_grad=100 + v)
            loss += dr.sum((img * ramp).array)
        dr.backward(loss)
        return float(dr.grad(tx)[0])

    ids = [s.id() for s in scene.sensors()]
    integ.silhouette_views = None
    per_view = [grad([v]) for v in range(4)]
    assert all(abs(g) > 1.0 for g in per_view)
    weights = silhouette_view_weights(ids, 2, iteration=3, seed=0)
    assert len(weights) == 2 and set(weights.values()) == {2.0}
    integ.silhouette_views = weights
    subset = grad([0, 1, 2, 3])
    expected = sum(weights.get(ids[v], 0.0) * per_view[v] for v in range(4))
    assert subset == pytest.approx(expected, rel=1e-4)
    # over all iterations' subsets the weights average to one per view
    counts = np.zeros(4)
    for it in range(400):
        for k, w in silhouette_view_weights(ids, 2, it, 0).items():
            counts[ids.index(k)] += w
    np.testing.assert_allclose(counts / 400, 1.0, atol=0.12)
    assert silhouette_view_weights(ids, 1, 0, 0) is None
    assert silhouette_view_weights(ids, 2, 5, 7) == silhouette_view_weights(ids, 2, 5, 7)


def test_views_sharing_a_crop_window_share_their_kernels(mi_backend, tmp_path):
    """Mitsuba bakes a film's crop window into its kernels as literals: two views with one window (Stage 1's
    shared training window, optimizer.optimise.stage1.training_windows) run the second view's render and silhouette
    pass on the first's kernels, while a view with another window compiles its own (issue 28: ~5 CPU s per view on
    meadow). Kernels are told apart by hash, so the test does not depend on what earlier tests left in the cache."""
    mi, dr = mi_backend
    from optimizer.rendering.projective import NAMES

    obj = _square_obj(tmp_path)
    crops = ((6, 5, 26, 27), (6, 5, 26, 27), (4, 9, 22, 30))
    origins = ([0.2, -0.1, 2.5], [-0.6, 0.3, 2.4], [0.5, 0.5, 2.2])
    sensors = {}
    for i, (o, (x0, y0, x1, y1)) in enumerate(zip(origins, crops)):
        sensors[f"cam{i}"] = {"type": "perspective", "fov": 45,
                              "to_world": mi.ScalarTransform4f().look_at(o, [0, 0, 0], [0, 1, 0]),
                              "film": {"type": "hdrfilm", "width": RES, "height": RES, "sample_border": True,
                                       "rfilter": {"type": "box"}, "crop_offset_x": x0, "crop_offset_y": y0,
                                       "crop_width": x1 - x0, "crop_height": y1 - y0},
                              "sampler": {"type": "independent", "sample_count": 4}}
    scene = mi.load_dict({"type": "scene", **sensors,
                          "integrator": {"type": NAMES["prb_projective"], "max_depth": 2, "sppc": 4, "sppp": 1,
                                         "sppi": 0, "silhouette_samples": 256},
                          "square": {"type": "obj", "filename": str(obj), "face_normals": True,
                                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 0.8, 0.6]}}}})
    params = mi.traverse(scene)
    key = "square.vertex_positions"
    base = dr.detach(params[key])
    shift = mi.Float(np.tile(np.float32([1.0, 0.0, 0.0]), dr.width(base) // 3))

    def step(view: int) -> tuple[dict, float]:
        """({hash: operation count} of the JIT kernels launched, x-gradient) of one render and backward pass of
        ``view``."""
        tx = mi.Float(0.0)
        dr.enable_grad(tx)
        params[key] = base + shift * tx
        params.update()
        dr.eval()
        dr.sync_thread()
        dr.kernel_history_clear()
        img = mi.render(scene, params, sensor=view, spp=0, seed=10 + view, seed_grad=100 + view)
        w = dr.width(img.array) // 3
        dr.backward(dr.sum(img.array * mi.Float(np.linspace(0, 1, w * 3, dtype=np.float32))))
        g = float(dr.grad(tx)[0])
        dr.sync_thread()
        return {k["hash"]: k["operation_count"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}, g

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        step(0)  # (whatever earlier work is still pending runs here)
        first, g0 = step(0)
        same, g1 = step(1)
        other, _ = step(2)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    new_same = {h: n for h, n in same.items() if h not in first}
    new_other = {h: n for h, n in other.items() if h not in first}
    assert g0 != 0.0 and g1 != 0.0 and g0 != g1  # both views see the square, from different poses
    assert max(first.values()) >= 1000  # the render and silhouette kernels (1,000-4,000 operations)
    # the second view of the window reuses them; what it adds is small: Mitsuba's silhouette precomputation
    # (``precompute_silhouette(ScalarPoint3f viewpoint)``) bakes the viewpoint into a ~150-operation kernel
    assert new_same and max(new_same.values()) < 500
    assert max(new_other.values()) >= 1000  # another window: its own render and silhouette kernels
