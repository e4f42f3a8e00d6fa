"""Stress tests: hard cases must stay numerically stable (loss, Stage 1, BSDF corners, meshes, bounds).

Every test names its hard case and the behaviour it expects in its docstring. Scenes are tiny (24-32 px,
2 views, a few hundred vertices, 32 px maps, 1-20 iterations) so the whole module runs in about a minute
on 2 CPU cores (most of it Dr.Jit compiling kernels for each new mesh). Tests that print ``STRESS ...`` lines report measured numbers (``pytest -s``).

Extends (does not repeat) tests/test_loss.py, tests/test_appearance.py, tests/test_mesh.py and
tests/test_optimize_cli.py; metric stress tests are in tests/test_stress_metrics.py and fault injection
(kill/resume, corrupt inputs) in tests/test_stress_faults.py.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from optimizer import backend

backend.init()
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from optimizer.optimise import loss as L  # noqa: E402
from optimizer.rendering.appearance import AppearanceConfig, clamp_projections, initial_values  # noqa: E402
from optimizer.scenes.cameras import cameras  # noqa: E402
from optimizer.scenes.environments import Environment, get_environment, plain_diffuse  # noqa: E402
from optimizer.scenes.mesh import prepare_mesh  # noqa: E402
from optimizer.rendering.planner import plan  # noqa: E402
from optimizer.scenes.primitives import make_primitive  # noqa: E402
from optimizer.scenes.scenepack import EnvironmentSpec, parse_pack  # noqa: E402
from optimizer.optimise.stage1 import Stage1, Stage1Config  # noqa: E402

W709 = np.array(L.REC709)
#: chroma per channel of a non-negative colour is <= 1 / W_c, so E_c|x~_o - x~_b| <= mean_c(1 / W_c)
CHROMA_MAX = float(np.mean(1.0 / W709))


def f(x) -> float:
    return float(x[0])


def report(name: str, **numbers) -> None:
    """Print measured numbers (visible with ``pytest -s``)."""
    print(f"STRESS {name}: " + ", ".join(f"{k}={v}" for k, v in numbers.items()))


def grad_of(fn, obj_np, *args, **kw):
    t = mi.TensorXf(np.asarray(obj_np, dtype=np.float32))
    dr.enable_grad(t)
    out = fn(t, *args, **kw)
    dr.backward(out)
    return f(out), np.asarray(dr.grad(t).numpy(), dtype=np.float64)


# =============================================================================================
# shared tiny scenes


@pytest.fixture(scope="module")
def teapot():
    """The paper's Fig. 7 object, prepared at ~400 vertices (cached in $CAMO_CACHE)."""
    return prepare_mesh(make_primitive("teapot"), target_vertices=400)


@pytest.fixture(scope="module")
def box():
    return prepare_mesh(make_primitive("utility_box"), target_vertices=300)


def tiny_pack(primitive="teapot", *, views=2, elevation=25.0, resolution=32, size=1.0, **material):
    mat = {"albedo": 0.5, "transmittance": 0.0}
    mat.update(material)
    return parse_pack({
        "object": {"primitive": primitive, "size": size, "target_vertices": 400},
        "environment": {"builtin": "gravel"},
        "cameras": {"views": views, "elevation": elevation, "radius": 4.0 * size},
        "render": {"resolution": resolution},
        "material": mat,
    })


def stage1(pack, env, prepared, app, *, iterations=2, loss="gated", spp=4, target_spp=16, seed=0, initial=None,
           targets=None, domain="object+shadow"):
    cfg = Stage1Config(iterations=iterations, spp=spp, target_spp=target_spp, seed=seed, loss=loss, domain=domain)
    return Stage1(pack, env, prepared, cameras(pack), plan(pack, env, app.planner_params()), cfg, app,
                  initial=initial).prepare(targets=targets)


def assert_step_sane(rec: dict) -> None:
    """A Stage 1 step record: finite losses, a non-negative integer count of dropped gradient entries."""
    for k in ("loss", "loss_photo", "loss_disp"):
        assert math.isfinite(rec[k]) and rec[k] >= 0, (k, rec)
    assert isinstance(rec["nonfinite_grads"], int) and rec["nonfinite_grads"] >= 0


def assert_values_in_range(s: Stage1) -> None:
    """Every parameter finite and inside its projection's range."""
    v = s.current_values()
    for k in ("albedo", "metallic", "roughness", "transmittance"):
        assert np.isfinite(v[k]).all() and v[k].min() >= 0.0 and v[k].max() <= 1.0, k
    assert np.isfinite(v["displacement"]).all() and np.abs(v["displacement"]).max() <= 1.0
    lim = s.app.translation_fraction * s.pack.object.size
    assert np.isfinite(v["translation"]).all() and np.abs(v["translation"][:2]).max() <= lim * (1 + 1e-6)
    assert v["translation"][2] == 0.0
    assert np.isfinite(v["rotation"]).all() and abs(float(v["rotation"][0])) <= math.pi + 1e-6
    assert np.isfinite(s.world_positions()).all()


# =============================================================================================
# Loss numerics: what tests/test_loss.py does not already pin down


def _pair_with_gap(hue_o, hue_b, dy):
    """One pixel pair (1, 1, 3): bg of colour ``hue_b`` at Y = 0.5, obj of colour ``hue_o`` with Y = 0.5 + dy."""
    o = np.asarray(hue_o, np.float64)
    b = np.asarray(hue_b, np.float64)
    b = b * 0.5 / (b @ W709)
    o = o * (0.5 + dy) / (o @ W709)
    return o.reshape(1, 1, 3), b.reshape(1, 1, 3)


colour = hnp.arrays(np.float64, 3, elements=st.floats(0.01, 1.0))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(hue_o=colour, hue_b=colour, log_dy=st.floats(-8.0, 8.0))
def test_gate_follows_eq9_for_gaps_from_1e_minus8_to_1e8(hue_o, hue_b, log_dy):
    """Hard case: one pixel whose luminance gap dY spans 1e-8 .. 1e8 radiance units, any two hues.

    Expected (Eq. 9): the chromaticity term is exactly g(dY) = 1 / (1 + e^dY) times the ungated one
    (0.5 as dY -> 0, muted for large dY), the luminance term is alpha * dY, and the Dr.Jit gradient is
    finite; once g underflows float32 (dY > ~104) the gradient is the pure luminance gradient alpha * W709.
    """
    dy = 10.0**log_dy
    obj, bg = _pair_with_gap(hue_o, hue_b, dy)
    obj32, bg32 = obj.astype(np.float32), bg.astype(np.float32)
    t = L.gated_loss_terms(mi.TensorXf(obj32), mi.TensorXf(bg32)).as_floats()
    ref = L.gated_loss_terms_np(obj32, bg32)
    dy32 = abs(float(obj32[0, 0].astype(np.float64) @ W709) - float(bg32[0, 0].astype(np.float64) @ W709))
    g = L.gate_np(dy32)
    assert all(math.isfinite(v) for v in t.values())
    assert ref["chroma"] == pytest.approx(g * ref["chroma_ungated"], rel=1e-12, abs=1e-300)
    assert t["chroma"] == pytest.approx(g * t["chroma_ungated"], rel=2e-5, abs=1e-30)
    assert t["chroma"] <= 0.5 * t["chroma_ungated"] * (1 + 1e-6)
    assert t["luminance"] == pytest.approx(dy32, rel=1e-5, abs=2e-7)
    assert 0.0 <= t["chroma_ungated"] <= CHROMA_MAX * (1 + 1e-6)
    _, grad = grad_of(L.gated_loss, obj32, bg32)
    assert np.all(np.isfinite(grad))
    if dy > 110.0:  # e^-dY is 0 in float32: no chromaticity gradient at all
        np.testing.assert_allclose(grad[0, 0], W709, rtol=1e-6)


radiance = st.one_of(
    st.just(0.0),
    st.integers(-8, 8).map(lambda e: float(10.0**e)),
    st.floats(float(np.float32(1e-8)), 1e8, width=32),
)


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    obj=hnp.arrays(np.float32, (3, 4, 3), elements=radiance),
    bg=hnp.arrays(np.float32, (3, 4, 3), elements=radiance),
    w=hnp.arrays(np.float32, (3, 4), elements=st.sampled_from([0.0, 0.25, 1.0, 3.0])),
    poison=st.sampled_from([None, np.nan, np.inf, -np.inf]),
    alpha=st.sampled_from([0.0, 1.0, 3.0]),
)
def test_gated_gradient_is_bounded_by_one_over_eps_for_any_radiance(obj, bg, w, poison, alpha):
    """Hard case: radiance anywhere in {0} U [1e-8, 1e8] (12 orders apart within one image), soft pixel
    weights (a loss domain), optionally a NaN/Inf pixel.

    Expected: the loss is finite and non-negative, its chromaticity term never exceeds
    0.5 * mean_c(1 / W_c) (gate <= 0.5, chroma of a non-negative colour <= 1 / W_c), and the gradient is
    not just finite but bounded: |dL/dx| <= (alpha + 2 + 1 / eps) * w_p / sum(w) per entry (the chroma
    term's slope is O(1 / eps), never O(1 / Y)); non-finite pixels get exactly 0.
    """
    eps = L.DEFAULT_EPS
    if poison is not None:
        obj = obj.copy()
        obj[1, 1, 2] = poison
    wsum = float(w[np.isfinite(obj).all(-1)].sum())
    terms = L.gated_loss_terms(mi.TensorXf(obj), mi.TensorXf(bg), w, alpha=alpha).as_floats()
    assert all(math.isfinite(v) for v in terms.values())
    assert terms["total"] >= 0 and 0.0 <= terms["chroma"] <= 0.5 * CHROMA_MAX * (1 + 1e-5)
    _, g = grad_of(L.gated_loss, obj, bg, w, alpha=alpha)
    assert np.all(np.isfinite(g))
    if poison is not None:
        assert np.all(g[1, 1] == 0.0)
    if wsum > 0:
        bound = (alpha + 2.0 + 1.0 / eps) * w[..., None] / wsum
        assert np.all(np.abs(g) <= bound * (1 + 1e-4) + 1e-30)
    else:
        assert terms["total"] == 0.0 and np.all(g == 0)


def _rect_scene(radiance: float):
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": {
            "type": "perspective", "fov": 40,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 8, "height": 6, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": 4},
        },
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": radiance}},
        "rect": {"type": "rectangle",
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.45, 0.3]}}},
    })


@pytest.mark.parametrize("exposure", [0.0, 1e-8, 1e-3, 1.0, 1e3, 1e8, 1e38])
def test_loss_through_a_real_render_at_any_exposure(exposure):
    """Hard case: a Mitsuba render (prb) at exposures 0 (zero luminance), 1e-8 .. 1e8 and 1e38 (the
    renderer overflows: every pixel NaN) against a fixed dull background (Y ~ 0.02).

    Expected for both losses: the loss equals the float64 NumPy reference, loss and gradient w.r.t. the
    BSDF reflectance are finite; at 1e8 the gate is shut (chroma term exactly 0); when the render is all
    NaN every pixel is counted as non-finite and excluded: loss 0, gradient exactly 0.
    """
    scene = _rect_scene(exposure)
    params = mi.traverse(scene)
    key = "rect.bsdf.reflectance.value"
    bg = np.full((6, 8, 3), 0.02, np.float32)
    bg[..., 2] = 0.03
    for name in ("gated", "mse"):
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, seed=1, seed_grad=2)
        fn = L.make_loss(name)
        value = fn(img, bg)
        dr.backward(value)
        g = np.array(dr.grad(params[key])).ravel()
        dr.set_grad(params[key], 0.0)
        img_np = img.numpy()
        assert math.isfinite(f(value)) and np.all(np.isfinite(g)), (name, exposure)
        assert f(value) == pytest.approx(fn.numpy(img_np, bg), rel=1e-5, abs=1e-12)
        if exposure >= 1e38:
            assert not np.isfinite(img_np).any()
            assert f(value) == 0.0 and np.all(g == 0.0)
            if name == "gated":
                assert L.gated_loss_terms(img, bg).as_floats()["nonfinite"] == 48.0
        if name == "gated" and exposure == 1e8:
            t = L.gated_loss_terms(img, bg).as_floats()
            assert t["chroma"] == 0.0 and t["luminance"] > 1e6
            assert np.all(g > 0)  # darker lowers the gap


# =============================================================================================
# Fig. 7: an object in bright light over a background in deep shadow (ratio >= 1e3)

SKY = 300.0  # radiance of a bright, white sky: a lit albedo-0.5 surface is ~100 radiance units
GROUND = [2e-5, 8e-5, 2e-5]  # a near-black, green ground: its radiance is ~0.02, ~1e-4 of the object's
A0 = (0.6, 0.45, 0.3)  # tan albedo, hue angle 0 in the rg-chromaticity plane


def fig7_environment() -> Environment:
    def build():
        return {"sky": {"type": "constant", "radiance": {"type": "rgb", "value": [SKY] * 3}},
                "ground": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([50, 50, 1]),
                           "bsdf": plain_diffuse(GROUND)}}

    return Environment("fig7", "bright sky, near-black ground", build, ("envmap",))


def hue_deg(rgb) -> np.ndarray:
    """Hue angle (degrees) of linear RGB: direction from white in the rg-chromaticity plane."""
    rgb = np.asarray(rgb, np.float64)
    s = rgb.sum(-1)
    return np.degrees(np.arctan2(rgb[..., 1] / s - 1 / 3, rgb[..., 0] / s - 1 / 3))


def fig7_run(teapot, loss: str, iterations: int = 20) -> dict:
    """Albedo-only Stage 1 on the Fig. 7 scene; returns the measured numbers."""
    pack = tiny_pack(albedo=list(A0))
    app = AppearanceConfig(map_resolution=32, pose=False, displacement=False, bsdf=False)
    s = stage1(pack, fig7_environment(), teapot, app, iterations=iterations, loss=loss)
    obj, bg, cov = s.initial_render, s.targets.background, s.targets.coverage
    inside = cov >= 1.0
    ratio = float((obj[inside] @ W709).mean() / (bg[inside] @ W709).mean())
    a0 = s.current_values()["albedo"].copy()
    recs = [s.step() for _ in range(iterations)]
    a = s.current_values()["albedo"]
    changed = np.any(a != a0, axis=-1)
    per_texel = (hue_deg(a[changed]) - hue_deg(a0[changed]) + 180.0) % 360.0 - 180.0
    return {"stage": s, "records": recs, "ratio": ratio, "changed": int(changed.sum()),
            "hue_drift": float(hue_deg(a[changed].mean(0)) - hue_deg(np.array(A0))),
            "texel_drift": float(np.abs(per_texel).mean()),
            "delta": a[changed].mean(0) - np.array(A0), "albedo": a}


@pytest.fixture(scope="module")
def fig7(teapot):
    return {loss: fig7_run(teapot, loss) for loss in ("gated", "mse")}


def test_fig7_gated_loss_keeps_the_tint_of_a_brightly_lit_object(fig7):
    """Hard case (paper Fig. 7): a teapot under a bright sky over a near-black ground, object/background
    radiance ratio >= 1e3, albedo-only Stage 1 (20 iterations, Adam, lr 1e-2) with the gated loss.

    Expected: everything stays finite and in [0, 1]; the gate is shut on the object (the chromaticity
    term stays < 1 % of the luminance term; measured 6e-4); the luminance term darkens every channel; the
    albedo's hue moves by a few degrees at most (measured ~3 deg; 'hue' = angle of the mean albedo of the
    optimised texels in the rg-chromaticity plane). MSE's numbers are reported beside it (STRESS line).
    """
    g, m = fig7["gated"], fig7["mse"]
    report("fig7", ratio=round(g["ratio"], 1), changed_texels=g["changed"],
           gated_hue_drift_deg=round(g["hue_drift"], 3), gated_mean_texel_drift_deg=round(g["texel_drift"], 3),
           gated_delta_rgb=np.round(g["delta"], 4).tolist(),
           mse_hue_drift_deg=round(m["hue_drift"], 3), mse_mean_texel_drift_deg=round(m["texel_drift"], 3),
           mse_delta_rgb=np.round(m["delta"], 4).tolist(),
           gated_chroma_over_lum=g["records"][-1]["loss_chroma"] / g["records"][-1]["loss_luminance"])
    assert g["ratio"] >= 1e3
    for run in (g, m):
        for rec in run["records"]:
            assert_step_sane(rec)
            assert rec["nonfinite_grads"] == 0
        assert_values_in_range(run["stage"])
        assert run["changed"] > 100
    for rec in g["records"]:
        assert rec["loss_chroma"] < 1e-2 * rec["loss_luminance"]
    assert np.all(g["delta"] < -0.02)
    assert abs(g["hue_drift"]) < 6.0


@pytest.mark.xfail(strict=True, reason="measured: gated drifts ~3 deg (away from the green ground), MSE < 1 deg; "
                   "see the test's docstring and the stress report")
def test_fig7_gated_hue_drift_is_not_larger_than_mse(fig7):
    """The paper's claim in miniature: with the gated loss the albedo keeps its tint at least as well as with
    MSE when the luminance gap is unreducible.

    Measured here (4 spp): gated -3.2 deg, MSE +0.6 deg (16 spp: -2.2 vs -0.1). Under Adam a pure
    luminance gradient (prop. to W709) keeps the hue (0.5 deg measured with the chroma term removed), and
    MSE's gradient is consistent in sign, so both keep it. The gated loss's drift comes from the few pixels
    where the gate is open: contact-shadow and silhouette pixels whose *primal* samples are dark (Y ~ 0.01,
    comparable to the ground) while the decorrelated *adjoint* samples hit the bright object; their chroma
    adjoint ~ g / (Y + eps) ~ 17 multiplies radiance derivatives of ~100, a sign-varying noise that is largest
    relative to W709 in blue (0.07) and smallest in green (0.72), so Adam's per-channel normalisation gives
    blue the smallest steps and the hue turns away from green. Not an arithmetic bug; a property of Eq. 9
    with eps = 1e-2 at radiance ~1e2 and decorrelated primal/adjoint seeds.
    """
    assert abs(fig7["gated"]["hue_drift"]) <= abs(fig7["mse"]["hue_drift"]) + 0.5


# =============================================================================================
# Stage 1 per-view loss with a weight domain, and poisoned targets


def test_stage1_view_loss_with_domain_matches_reference_on_extreme_images(teapot):
    """Hard case: Stage 1's per-view loss (Eq. 9 inside the object+shadow domain) on an image that mixes
    radiance 0, 1e-8, 1e8, NaN and +-Inf pixels.

    Expected: the value equals the float64 reference ``gated_loss_np(img, bg, domain)`` (non-finite pixels
    excluded), the gradient is finite, zero outside the domain and at the non-finite pixels.
    """
    pack = tiny_pack(albedo=list(A0))
    app = AppearanceConfig(map_resolution=32, pose=False, displacement=False, bsdf=False)
    s = stage1(pack, fig7_environment(), teapot, app)
    v = 1
    dom = s.targets.domain[v]
    assert 0 < dom.sum() < dom.size
    rng = np.random.default_rng(0)
    img = (10.0 ** rng.uniform(-8, 8, size=dom.shape + (3,))).astype(np.float32)
    img[0, 0] = 0.0
    ys, xs = np.nonzero(dom)
    img[ys[0], xs[0]] = [np.nan, 1.0, 1.0]
    img[ys[1], xs[1]] = [np.inf, 0.0, 0.0]
    img[ys[2], xs[2]] = [0.0, -np.inf, 0.0]
    t = mi.TensorXf(img)
    dr.enable_grad(t)
    value, terms = s._view_loss(t, v)
    dr.backward(value)
    g = np.asarray(dr.grad(t).numpy())
    ref = L.gated_loss_terms_np(img, s.targets.background[v], dom)
    assert f(value) == pytest.approx(ref["total"], rel=1e-5)
    assert terms.as_floats()["nonfinite"] == ref["nonfinite"] == 3.0
    assert np.all(np.isfinite(g))
    assert np.all(g[dom == 0] == 0)
    for k in range(3):
        assert np.all(g[ys[k], xs[k]] == 0)
    s.cfg = dataclasses.replace(s.cfg, loss="mse")
    mv, _ = s._view_loss(mi.TensorXf(img), v)
    assert f(mv) == pytest.approx(L.mse_loss_np(img, s.targets.background[v], dom), rel=1e-5)


def test_stage1_step_survives_nonfinite_background_targets(teapot):
    """Hard case: background targets with NaN/Inf pixels inside the loss domain (a corrupt target render).

    Expected: the step record is finite, no gradient entry is non-finite (the loss excludes those pixels
    before any arithmetic), the parameters stay finite and in range.
    """
    pack = tiny_pack(albedo=list(A0))
    app = AppearanceConfig(map_resolution=32, pose=False, displacement=False, bsdf=False)
    s = stage1(pack, fig7_environment(), teapot, app)
    for v in range(len(s.cams)):
        bgv = s.targets.background[v].copy()
        ys, xs = np.nonzero(s.targets.domain[v])
        bgv[ys[::3], xs[::3], 0] = np.nan
        bgv[ys[1::3], xs[1::3], 1] = np.inf
        s._bg[v] = mi.TensorXf(bgv)
    for loss in ("gated", "mse"):
        s.cfg = dataclasses.replace(s.cfg, loss=loss)
        rec = s.step()
        assert_step_sane(rec)
        assert rec["nonfinite_grads"] == 0
    assert_values_in_range(s)


# =============================================================================================
# Principled BSDF corners, grazing cameras


@pytest.fixture(scope="module")
def grazing(box):
    """The gravel yard seen from 2 degrees above the object's centre (grazing ground), full BSDF, no geometry;
    the base material sits inside the box (roughness 0.5, transmittance 0.5) so every corner differs from it."""
    pack = tiny_pack("utility_box", elevation=2.0, resolution=24, transmittance=0.5, roughness=0.5, metallic=0.2)
    env = get_environment(EnvironmentSpec(builtin="gravel"))
    app = AppearanceConfig(map_resolution=32, displacement_resolution=16, pose=False, displacement=False)
    base = stage1(pack, env, box, app, target_spp=8)
    return pack, env, app, base.targets


CORNERS = {
    "roughness0": {"roughness": 0.0},
    "roughness1": {"roughness": 1.0},
    "metallic1": {"metallic": 1.0},
    "transmittance1": {"transmittance": 1.0},
    "metallic1+roughness0": {"metallic": 1.0, "roughness": 0.0},
    "transmittance1+roughness0": {"transmittance": 1.0, "roughness": 0.0},
    "metallic1+transmittance1": {"metallic": 1.0, "transmittance": 1.0},
    "all": {"metallic": 1.0, "roughness": 0.0, "transmittance": 1.0, "albedo": 1.0},
    "black": {"albedo": 0.0, "metallic": 0.0, "roughness": 1.0, "transmittance": 0.0},
}


@pytest.mark.parametrize("loss", ["gated", "mse"])  # Eq. 9 (paper preset) and the fast preset's squared error
@pytest.mark.parametrize("corner", sorted(CORNERS))
def test_principled_bsdf_corners_at_grazing_views(grazing, box, corner, loss):
    """Hard case: the principled BSDF at the corners of its parameter box (roughness 0 = the safe minimum
    0.035, metallic 1, transmittance 1, their combinations, a black absorber) seen by cameras 2 degrees
    above the object's centre (the ground at grazing incidence), rendered with prb (max_depth 6) and
    differentiated.

    Expected after two Stage 1 steps: finite loss terms, the dropped-gradient count reported as an int,
    every parameter finite and inside [0, 1] (the projection holds even where a step pushed past a corner),
    and the gradient reached the maps (something moved).
    """
    pack, env, app, targets = grazing
    init = initial_values(app, pack.material)
    for k, val in CORNERS[corner].items():
        init[k] = np.full_like(init[k], val)
    s = stage1(pack, env, box, app, initial=init, targets=targets, loss=loss)
    before = s.current_values()
    recs = [s.step(), s.step()]
    for rec in recs:
        assert_step_sane(rec)
    assert_values_in_range(s)
    after = s.current_values()
    moved = sum(int(np.any(after[k] != before[k])) for k in ("albedo", "metallic", "roughness", "transmittance"))
    assert moved >= 1
    report(f"bsdf-corner {corner} ({loss})", loss=[round(r["loss"], 5) for r in recs],
           nonfinite_grads=[r["nonfinite_grads"] for r in recs], maps_moved=moved)


@pytest.mark.parametrize("loss", ["gated", "mse"])
def test_black_albedo_under_transmission_has_finite_gradients_and_leaves_zero(grazing, box, loss):
    """Hard case: albedo exactly 0 on a transmissive object (a warm start that clipped every texel at 0, or
    ``--init albedo=0``). Mitsuba's principled BSDF tints transmission by ``sqrt(base_color)``, whose slope is
    infinite at 0: before ``ALBEDO_MIN`` such texels got Inf/NaN gradients every step (meadow: ~1700 a step, and
    a NaN rotation gradient every other step), were zeroed by the sanitiser and stayed at 0 for good.

    Expected: no non-finite gradient entry in any step, the albedo starts at ``ALBEDO_MIN`` (not 0) and moves."""
    from optimizer.scenes.bsdf_maps import ALBEDO_MIN

    pack, env, app, targets = grazing
    init = initial_values(app, pack.material)
    init["albedo"] = np.zeros_like(init["albedo"])
    init["transmittance"] = np.full_like(init["transmittance"], 0.75)
    s = stage1(pack, env, box, app, initial=init, targets=targets, loss=loss)
    start = s.current_values()["albedo"]
    assert start.min() == pytest.approx(ALBEDO_MIN)
    recs = [s.step(), s.step()]
    assert [r["nonfinite_grads"] for r in recs] == [0, 0]
    for rec in recs:
        assert_step_sane(rec)
    assert_values_in_range(s)
    a = s.current_values()["albedo"]
    assert a.min() >= ALBEDO_MIN - 1e-9 and np.any(a != start)
    report(f"black albedo, T 0.75 ({loss})", nonfinite_grads=[r["nonfinite_grads"] for r in recs],
           albedo_max=float(a.max()))


def test_nonfinite_gradient_entries_are_counted_dropped_and_never_reach_a_parameter(box):
    """Hard case: NaN, +Inf and -Inf gradient entries (as a NaN-prone BSDF lobe would produce) in the maps
    and in the pose of a Stage 1 step.

    Expected: ``nonfinite_grads`` in the step record counts them exactly (the render's own gradients are
    finite here), the step still happens, the poisoned entries do not move (their gradient is zeroed
    before Adam, whose moments stay finite), and every parameter stays finite.
    """
    pack = tiny_pack("utility_box", elevation=2.0, resolution=24)
    env = get_environment(EnvironmentSpec(builtin="gravel"))
    app = AppearanceConfig(map_resolution=32, displacement_resolution=16, displacement=False, transmittance=False)
    s = stage1(pack, env, box, app, target_spp=8)
    poison = {"albedo": [0, 5, 77], "roughness": [3], "rotation": [0], "translation": [1]}
    values = (float("nan"), float("inf"), float("-inf"))
    original = s.opt.sanitise_grads

    def poisoned_sanitise():
        for name, idx in poison.items():
            x = s.opt[name]
            g = np.array(dr.grad(x), dtype=np.float32).ravel()
            for j, i in enumerate(idx):
                g[i] = values[j % 3]
            dr.set_grad(x, mi.TensorXf(mi.Float(g), tuple(x.shape)) if dr.is_tensor_v(x) else mi.Float(g))
        return original()

    s.opt.sanitise_grads = poisoned_sanitise
    before = {k: np.array(v).ravel().copy() for k, v in s.current_values().items()}
    rec = s.step()
    assert rec["nonfinite_grads"] == sum(len(v) for v in poison.values())
    after = {k: np.array(v).ravel() for k, v in s.current_values().items()}
    for name, idx in poison.items():
        np.testing.assert_array_equal(after[name][idx], before[name][idx])
    assert np.any(after["albedo"] != before["albedo"])  # the other entries did step
    for name in s.opt.values:
        assert np.isfinite(np.array(s.opt.m[name])).all() and np.isfinite(np.array(s.opt.v[name])).all()
    s.opt.sanitise_grads = original
    assert_step_sane(s.step())
    assert_values_in_range(s)


# =============================================================================================
# Pose and displacement at their bounds


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_pose_and_displacement_at_their_clip_bounds(box, sign):
    """Hard case: the pose starts on its clip box (dt = +-5 % of the object size in x and y, theta = +-pi)
    and every displacement texel at its amplitude bound (d = +-1, i.e. 2 % of the size along the normal),
    on a 2-unit object, with the projective integrator (pose and displacement gradients).

    Expected: one Stage 1 step is finite; the projections keep dt inside +-5 % (dz = 0), theta inside
    [-pi, pi], d inside [-1, 1]; the displaced world positions are finite.
    """
    pack = tiny_pack("utility_box", resolution=24, size=2.0)
    env = get_environment(EnvironmentSpec(builtin="gravel"))
    app = AppearanceConfig(map_resolution=32, displacement_resolution=16)
    lim = app.translation_fraction * pack.object.size
    init = initial_values(app, pack.material)
    init["translation"] = np.array([sign * lim, -sign * lim, 0.0], np.float32)
    init["rotation"] = np.array([sign * math.pi], np.float32)
    init["displacement"] = np.full_like(init["displacement"], sign)
    s = stage1(pack, env, box, app, initial=init, target_spp=8)
    assert s.plan.integrator["type"] in ("prb_projective", "direct_projective")
    assert_values_in_range(s)
    rec = s.step()
    assert_step_sane(rec)
    assert rec["loss_disp"] == pytest.approx(1.0, rel=1e-6)  # L_disp = E|d| = 1 at the bound
    assert_values_in_range(s)
    v = s.current_values()
    assert np.abs(v["displacement"]).max() <= 1.0
    report(f"pose-bounds sign={sign:+.0f}", loss=round(rec["loss"], 5), nonfinite=rec["nonfinite_grads"],
           dt=np.round(v["translation"], 5).tolist(), theta=round(float(v["rotation"][0]), 5))


finite32 = st.floats(float(np.float32(-3e38)), float(np.float32(3e38)), width=32, allow_nan=False, allow_infinity=False)
any32 = st.one_of(finite32, st.sampled_from([float("nan"), float("inf"), float("-inf"), 0.0, -0.0]))


@settings(max_examples=80, deadline=None)
@given(x=hnp.arrays(np.float32, 6, elements=any32), size=st.sampled_from([1e-4, 1.0, 2.0, 1e4]))
def test_map_and_offset_projections_stay_in_bounds_for_any_input(x, size):
    """Hard case: the projections applied after every Adam step fed NaN, +-Inf, +-3e38 and denormals.

    Expected: maps land in [0, 1], d in [-1, 1], dt in +-5 % of the size with dz = 0; all finite.
    """
    proj = clamp_projections(AppearanceConfig(), size)
    xs = mi.Float(x)
    for name, lo, hi in (("albedo", 0, 1), ("roughness", 0, 1), ("displacement", -1, 1)):
        y = np.array(proj[name](xs))
        assert np.isfinite(y).all() and y.min() >= lo and y.max() <= hi, name
    t = np.array(proj["translation"](mi.Float(x[:3])))
    lim = np.float32(0.05 * size)
    assert np.isfinite(t).all() and np.abs(t[:2]).max() <= lim and t[2] == 0.0


@settings(max_examples=80, deadline=None)
@given(theta=st.floats(-1e4, 1e4, width=32))
def test_angle_projection_wraps_moderate_angles_into_minus_pi_pi(theta):
    """Hard case: theta anywhere in +-1e4 rad (far beyond what 50 Adam steps of 1e-2 rad reach).

    Expected: the projected angle is in [-pi, pi] and is the same rotation (equal cos and sin).
    """
    proj = clamp_projections(AppearanceConfig(), 1.0)
    y = float(np.array(proj["rotation"](mi.Float([theta])))[0])
    assert -math.pi - 1e-6 <= y <= math.pi + 1e-6
    tol = 4e-7 * max(1.0, abs(theta))  # float32 round-off of theta itself
    assert math.cos(y) == pytest.approx(math.cos(theta), abs=tol + 1e-6)
    assert math.sin(y) == pytest.approx(math.sin(theta), abs=tol + 1e-6)


@pytest.mark.parametrize("theta", [1e20, -1e25, 1e30, 3e38])
def test_angle_projection_keeps_huge_angles_in_bounds(theta):
    """Hard case: a huge rotation (e.g. from a hand-edited or corrupt checkpoint, or an ``initial=`` override).

    Expected (clamp_projections' contract: theta inside [-pi, pi]): the projected angle is finite and in
    [-pi, pi]. BUG (appearance.clamp_projections ``angle``): ``x - 2 pi round(x / 2 pi)`` in float32 loses
    all precision for |x| > ~1e8 and returns e.g. 7.6e22 for x = 1e30.
    """
    proj = clamp_projections(AppearanceConfig(), 1.0)
    y = float(np.array(proj["rotation"](mi.Float([theta])))[0])
    assert math.isfinite(y) and -math.pi - 1e-6 <= y <= math.pi + 1e-6, y


# =============================================================================================
# Meshes: degenerate input through preparation and Stage 1


def _sphere():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    m.apply_translation([0.0, 0.0, 1.0])
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def _zero_area(v, f):
    n = len(v)
    extra_v = np.array([[0.1, 0.1, 1.0], [0.2, 0.2, 1.0], [0.3, 0.3, 1.0]])  # collinear
    extra_f = np.array([[n, n + 1, n + 2], [0, 0, 1], [2, 3, 2], [5, 5, 5]])
    return np.vstack([v, extra_v]), np.vstack([f, extra_f])


def _soup(v, f):
    """Triangle soup: every face has its own three vertices (STL-style duplicates)."""
    return v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)


def _non_manifold(v, f):
    """Two fins on one edge: that edge is then shared by four triangles."""
    a, b = f[0, 0], f[0, 1]
    n = len(v)
    tip = (v[a] + v[b]) / 2 + 0.6 * (v[a] + v[b] - 2 * np.array([0, 0, 1.0])) / 2
    tip2 = tip + np.array([0.0, 0.0, 0.3])
    return np.vstack([v, tip, tip2]), np.vstack([f, [[a, b, n], [b, a, n + 1]]])


def _open(v, f):
    """The top cap removed: a hole with a boundary loop."""
    centroids = v[f].mean(1)
    return v, f[centroids[:, 2] < 1.7]


def _everything(v, f):
    v, f = _non_manifold(*_open(*_zero_area(v, f)))
    return _soup(v, f)


MESH_CASES = {"zero_area": _zero_area, "duplicate_vertices": _soup, "non_manifold": _non_manifold,
              "open_boundary": _open, "everything": _everything}


@pytest.fixture(scope="module")
def mesh_stage_setup():
    """Pose + displacement + albedo (direct_projective: geometry gradients through the prepared mesh)."""
    pack = tiny_pack("utility_box", resolution=24)
    env = get_environment(EnvironmentSpec(builtin="gravel"))
    app = AppearanceConfig(map_resolution=32, displacement_resolution=16, bsdf=False)
    return pack, env, app


@pytest.mark.parametrize("case", sorted(MESH_CASES))
def test_degenerate_meshes_prepare_and_optimise(case, tmp_path, mesh_stage_setup):
    """Hard case: meshes with zero-area faces, duplicate vertices (a triangle soup), non-manifold edges,
    an open boundary, and all of these at once, through ``prepare_mesh`` and two Stage 1 steps with pose,
    displacement and albedo (projective integrator: geometry gradients through the prepared mesh).

    Expected: preparation reports what it found and repaired (degenerate faces dropped, vertices merged,
    boundary / non-manifold edges kept with a warning); the prepared mesh has no degenerate faces and
    unit-length normals; both steps are finite and every parameter stays in range.
    """
    import trimesh

    v, fc = MESH_CASES[case](*_sphere())
    prep = prepare_mesh(trimesh.Trimesh(v, fc, process=False), target_vertices=300, cache_dir=tmp_path,
                        use_cache=False)
    rep = prep.report
    if case in ("zero_area", "everything"):
        assert rep["degenerate_faces"] >= (4 if case == "zero_area" else 3)  # "everything" cut one of them away
    if case in ("duplicate_vertices", "everything"):
        assert rep["merged_vertices"] > 0
    if case in ("non_manifold", "everything"):
        assert rep["non_manifold_edges"] >= 1 and any("non-manifold" in w for w in rep["warnings"])
    if case in ("open_boundary", "everything"):
        assert rep["boundary_edges"] > 0 and any("open" in w for w in rep["warnings"])
    tri = prep.vertices[prep.faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area2.min() > 0
    assert np.isfinite(prep.normals).all()
    np.testing.assert_allclose(np.linalg.norm(prep.normals, axis=1), 1.0, atol=1e-5)
    pack, env, app = mesh_stage_setup
    s = stage1(pack, env, prep, app, target_spp=8)
    recs = [s.step(), s.step()]
    for rec in recs:
        assert_step_sane(rec)
    assert_values_in_range(s)
    report(f"mesh {case}", welded=prep.n_welded, uv=prep.n_uv, degenerate=rep["degenerate_faces"],
           merged=rep["merged_vertices"], boundary=rep["boundary_edges"], non_manifold=rep["non_manifold_edges"],
           loss=[round(r["loss"], 5) for r in recs], nonfinite=[r["nonfinite_grads"] for r in recs])


def _scaled_preps(tmp_path):
    import trimesh

    v, fc = _sphere()
    return {scale: prepare_mesh(trimesh.Trimesh(v * scale, fc, process=False), target_vertices=300,
                                cache_dir=tmp_path, use_cache=False) for scale in (1.0, 1e-4, 1e4)}


def test_mesh_scale_is_irrelevant_to_the_optimiser(tmp_path, mesh_stage_setup):
    """Hard case: the same mesh at 1e-4 and 1e4 times its size (coordinates ~1e-4 .. 1e4).

    Expected: normalisation maps all of them to the same surface (largest side 1 on z = 0, same area and
    volume to 1e-9, same vertex count), and Stage 1 (two steps, pose + displacement + albedo) from the
    tiny and the huge one is finite and in range with losses within 5 % of the unit-size run (Monte Carlo
    noise and tessellation; the exact-equality property is pinned by the next test).
    """
    import trimesh

    preps = _scaled_preps(tmp_path)
    ref = trimesh.Trimesh(preps[1.0].vertices, preps[1.0].faces, process=False)
    pack, env, app = mesh_stage_setup
    losses = {}
    for scale, prep in preps.items():
        m = trimesh.Trimesh(prep.vertices, prep.faces, process=False)
        np.testing.assert_allclose(np.ptp(prep.vertices, axis=0).max(), 1.0, rtol=1e-6)
        assert abs(float(prep.vertices[:, 2].min())) < 1e-6
        assert prep.n_welded == preps[1.0].n_welded
        assert m.area == pytest.approx(ref.area, rel=1e-9) and m.volume == pytest.approx(ref.volume, rel=1e-9)
        s = stage1(pack, env, prep, app, target_spp=8)
        recs = [s.step(), s.step()]
        for rec in recs:
            assert_step_sane(rec)
        assert_values_in_range(s)
        losses[scale] = [r["loss"] for r in recs]
    for scale in (1e-4, 1e4):
        assert losses[scale] == pytest.approx(losses[1.0], rel=0.05)
    report("mesh scale", losses={k: [round(x, 5) for x in v] for k, v in losses.items()})


def test_mesh_preparation_is_exactly_scale_invariant(tmp_path):
    """Hard case: the same icosphere at 1, 1e-4 and 1e4 (after normalisation the vertices differ by 1 ulp).

    Expected: the prepared meshes are the same mesh (same faces, vertices and UVs up to round-off), so
    the optimiser cannot tell the input's units apart. BUG (optimizer/scenes/mesh/remesh.py ``_split_to_count``):
    longest-edge refinement sorts edges by float length and cuts the list at the vertex budget; an
    icosphere has many equal-length edges, so 1-ulp differences decide which are split and the three
    inputs get three different tessellations (553 / 541 / 540 UV vertices, vertices up to 0.08 apart).
    """
    preps = _scaled_preps(tmp_path)
    for scale in (1e-4, 1e4):
        np.testing.assert_array_equal(preps[scale].faces, preps[1.0].faces)
        np.testing.assert_allclose(preps[scale].vertices, preps[1.0].vertices, rtol=0, atol=1e-6)
