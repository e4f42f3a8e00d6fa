"""evaluation.views: the evaluation setting chosen per scene by a pilot (issue 28) -- the choice on controlled
inputs (figures the pilot measured on room and meadow, 4 views at 96 px, 2 pilot views, 64 spp) and the pilot on a
tiny scene."""

from __future__ import annotations

import numpy as np
import pytest

from evaluation.views import EvaluationSetting, choose_setting


def _c(label: str, seconds: float, error255: float, ratio: float) -> dict:
    return {"setting": {"label": label}, "seconds": seconds, "error": error255 / 255, "ratio": ratio}


#: room at 4 spp (pilot of 2026-11-27): full tracing's 64-spp error 2.12/255
ROOM = [_c("oidn-through:16:max:f16@4", 1.02, 2.61, 0.92), _c("oidn-through:16:max:f32:b16@4", 1.56, 1.93, 1.16),
        _c("oidn-through:32:max:f16:b16@4", 1.84, 1.88, 0.97), _c("oidn-through:32:max:f32:b16@4", 1.73, 1.86, 0.95),
        _c("oidn-through:8:b16@4", 2.16, 1.82, 0.81)]
#: meadow at 4 spp: full tracing's 2.88/255; every candidate either too noisy near the object or above the error
MEADOW = [_c("oidn-through:16:max:f16@4", 1.36, 3.11, 1.17), _c("oidn-through:16:max:f16:b16@4", 1.29, 2.36, 1.44),
          _c("oidn-through:32:max:f32:b16@4", 2.14, 2.29, 1.15), _c("oidn-through:8:b16@4", 1.10, 2.38, 1.66)]


def test_the_cheapest_setting_that_is_as_accurate_as_full_tracing_and_noise_safe_is_chosen():
    """Room: the fastest candidate (16:max:f16, 1.02 s) is above full tracing's error and the next (16:max:f32:b16)
    is too noisy near the object (1.16), so 32:max:f32:b16 (1.73 s, 1.86/255, ratio 0.95) is chosen over the
    slower safe ones; meadow: none qualifies -> None (the evaluation keeps its default)."""
    assert choose_setting(ROOM, 2.12 / 255)["setting"]["label"] == "oidn-through:32:max:f32:b16@4"
    assert choose_setting(MEADOW, 2.88 / 255) is None
    # a looser error target lets the fastest through; a stricter noise bound leaves only the product rule
    assert choose_setting(ROOM, 2.7 / 255)["setting"]["label"] == "oidn-through:16:max:f16@4"
    assert choose_setting(ROOM, 2.12 / 255, ratio_max=0.9)["setting"]["label"] == "oidn-through:8:b16@4"
    # equal seconds: the lower error
    tie = [_c("a", 1.0, 2.0, 0.9), _c("b", 1.0, 1.5, 0.9)]
    assert choose_setting(tie, 2.1 / 255)["setting"]["label"] == "b"


#: the pilot's figures with the cost model (2 views at 96 px, 64 spp, load 6-9; this session): room, full tracing's
#: error 2.12/255. (label, modelled CPU s, error /255, noise ratio)
ROOM_MODEL = [_c("oidn-through:8:max:f16@4", 0.95, 2.70, 1.08), _c("oidn-through:16:max:f16@4", 1.32, 2.61, 0.92),
              _c("oidn-through:16:max:f16:b8@4", 1.32, 2.15, 0.98), _c("oidn-through:16:max:f16:b16@4", 1.32, 1.95, 1.19),
              _c("oidn-through:32:max:f32:b16@4", 2.26, 1.86, 0.95), _c("oidn-through:8:b16@4", 2.65, 1.82, 0.81),
              _c("oidn-through:8:max:f16@6", 1.35, 2.54, 0.98), _c("oidn-through:16:max:f16@6", 1.93, 2.47, 0.85),
              _c("oidn-through:8:max:f16@8", 1.47, 2.03, 1.17), _c("oidn-through:16:max:f16@8", 2.14, 1.93, 0.94),
              _c("oidn-through:8@8", 4.49, 1.87, 0.63)]
#: room's cost model at 4 spp (CPU s per path sample of the frame / of the object's further samples, features, fixed)
ROOM_MODEL_4 = {"frame": 2.28e-6, "object": 4.55e-6, "features": {"4": 0.196, "16": 0.135, "32": 0.324},
                "fixed": 0.177, "pixels": 18432}


def test_with_the_cost_model_a_later_level_is_measured_while_it_can_be_cheaper():
    """Room: at 4 spp the cheapest candidate that qualifies is 32:max:f32:b16 (2.26 s); an 8-spp frame alone would
    cost 2.28e-6 x 18432 x 8 + 0.18 = 0.51 s, so 6 and 8 spp are measured, and 16:max:f16@8 (2.14 s, 1.93/255, 0.94)
    wins over the 4-spp one; after it a 64-spp level (2.87 s) could not be cheaper. The modelled seconds are the
    samples times the rates plus features and fixed costs."""
    from evaluation.views import level_may_be_cheaper, modelled_seconds

    at4 = [c for c in ROOM_MODEL if c["setting"]["label"].endswith("@4")]
    assert choose_setting(at4, 2.12 / 255)["setting"]["label"] == "oidn-through:32:max:f32:b16@4"
    assert level_may_be_cheaper(ROOM_MODEL_4, 18432, 8, 2.26)
    assert choose_setting(ROOM_MODEL, 2.12 / 255)["setting"]["label"] == "oidn-through:16:max:f16@8"
    assert not level_may_be_cheaper(ROOM_MODEL_4, 18432, 64, 2.14)
    # 16:max:f16@4: every pixel at 4 spp, 2.51 frames of further samples on the object, features at 16 spp
    m = modelled_seconds(ROOM_MODEL_4, 4, 18432, 2.51, 16)
    assert m == pytest.approx(2.28e-6 * 18432 * 4 + 4.55e-6 * 2.51 * 18432 * 4 + 0.135 + 0.177)
    assert 1.2 < m < 1.4  # the pilot's 1.32 s (its model's unrounded rates)


def test_setting_label_and_bad_feature_spp():
    assert EvaluationSetting("oidn-through", 16, "max", 16, 4, 16).label == "oidn-through:16:max:f16:b16@4"
    assert EvaluationSetting("", 1, "product", None, 64).label == "off:1@64"
    from evaluation.views import ViewRenderer

    with pytest.raises(ValueError, match="feature_spp"):
        ViewRenderer(4, feature_spp=0)


@pytest.mark.slow
def test_the_pilot_measures_each_candidate_against_full_tracing_and_chooses_by_the_rule(mi_backend):
    """On the glass sphere in the sun (tests/test_denoise.py, 2 views at 48 px) at 32 spp: full tracing's error at 32
    spp is measured (> 0); the candidates at 4 spp are each measured (seconds, error, noise ratio); the background's
    features at 32 spp instead of 4 lower the denoised frame's error (the denoiser's features are its noisiest input
    at 4 spp); the choice is :func:`choose_setting` of the level's candidates, and a later level is measured only if
    no candidate of the earlier one qualified."""
    mi, _ = mi_backend
    from evaluation.views import evaluation_setting_pilot
    from optimizer.rendering.planner import Plan
    from tests.test_denoise import _glass_sphere_in_sun

    env, mesh, cams, integ, pack = _glass_sphere_in_sun(mi)
    plan = Plan(integ, True, 8, "", [], region_search=True)
    # levels given at an evaluation spp of 64: 8 and 16 -> 4 and 8 spp at 32
    cands = ((8, ((8, "max", 8, None), (8, "max", 8, 32))), (16, ((8, "max", 16, None),)))
    p = evaluation_setting_pilot(pack, env, cams, plan, 32, 0, "oidn-through", mesh, views=2, candidates=cands)
    print(p["why"])
    assert p["target_error"] > 0 and p["full_seconds"] > 0 and p["cost"] == "model"
    first = [c for c in p["candidates"] if c["setting"]["spp"] == 4]
    assert len(first) == 2 and all(c["seconds"] > 0 and c["error"] > 0 and c["ratio"] > 0 for c in first)
    by = {c["setting"]["background_feature_spp"]: c for c in first}
    assert by[32]["error"] < by[None]["error"], (by[32]["error"], by[None]["error"])
    model = p["cost_models"]["4"]
    assert model["frame"] > 0 and model["object"] > 0 and model["fixed"] > 0 and set(model["features"]) == {"8"}
    # the background's features do not change what the with-object render traces (noise matching reads the raw
    # background's groups, the object's features are at 8 spp in both): the same samples, the same modelled price
    assert by[32]["seconds"] == pytest.approx(by[None]["seconds"], rel=0.05)
    best = choose_setting(first, p["target_error"])
    from evaluation.views import level_may_be_cheaper

    measured_8 = len(p["candidates"]) == 3
    assert measured_8 == (best is None or level_may_be_cheaper(model, 2 * 48 * 48, 8, best["seconds"]))
    chosen = choose_setting(p["candidates"], p["target_error"])
    assert (p["setting"] is None) == (chosen is None)
    if chosen is not None:
        assert p["setting"].label == chosen["setting"]["label"]
    assert np.isfinite([c["error"] for c in p["candidates"]]).all()
    with pytest.raises(Exception, match="candidates"):
        evaluation_setting_pilot(pack, env, cams, plan, 32, 0, "oidn-through", mesh, views=2, candidates="fine")


def test_bad_setting_options_are_refused_in_one_line(capsys):
    """``--setting`` takes ``auto`` only, needs the planner and noise matching in ``camo evaluate`` and the
    evaluation's pilot in ``camo plan``."""
    from camo.cli import main
    from camo_base.errors import SettingError
    from evaluation.settings import EvalSettings

    for bad, why in ((EvalSettings(setting="fast"), "setting"), (EvalSettings(setting="auto", planner=False),
                                                                  "no_planner"),
                     (EvalSettings(setting="auto", noise_match=False), "no_noise_match")):
        with pytest.raises(SettingError, match=why):
            bad.validate()
    assert EvalSettings(setting="auto").validate().setting == "auto"
    assert main(["plan", "room", "--setting", "auto", "--no-pilot"]) == 2
    assert main(["plan", "room", "--setting", "auto"]) == 2  # --purpose optimize
    assert main(["plan", "room", "--purpose", "evaluate", "--setting", "fast"]) == 2
    err = capsys.readouterr().err
    assert "--setting auto: only with --purpose evaluate" in err and "invalid choice: 'fast'" in err
