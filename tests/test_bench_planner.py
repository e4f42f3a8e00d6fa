"""bench/bench_planner.py: the ``--evaluate-as`` settings (denoiser, the object's factor, how it is rendered, at
which levels) and the equal-error reading from a curve measured at one level."""

from __future__ import annotations

import math

import pytest


def test_evaluate_as_settings_parse_and_bad_ones_are_refused(bench_module):
    bp = bench_module("bench_planner")
    assert bp.parse_evaluate_as("off:1") == ("", 1, {"region": False, "combine": "product", "feature_spp": None,
                                                     "bg_feature_spp": None, "levels": None, "sampler": None})
    d, k, o = bp.parse_evaluate_as("oidn-through:16:max:f16:region@4/8")
    assert (d, k, o) == ("oidn-through", 16, {"region": True, "combine": "max", "feature_spp": 16,
                                              "bg_feature_spp": None, "levels": (4, 8), "sampler": None})
    # the evaluation render with another sampler than the plan's (camo evaluate --sampler)
    assert bp.parse_evaluate_as("off:1:sobol@16/64")[2]["sampler"] == "sobol"
    assert bp.parse_evaluate_as("off:1:independent")[2]["sampler"] == "independent"
    assert bp.eval_integrator({"type": "path", "max_depth": 6}, "sobol") == {"type": "path", "max_depth": 6,
                                                                             "sampler": "sobol"}
    assert bp.eval_integrator({"type": "path", "sampler": "sobol"}, "independent") == {"type": "path"}
    assert bp.eval_integrator({"type": "path"}, None) == {"type": "path"}
    assert bp.parse_evaluate_as("oidn-through:32:max:f32:b16@4")[2]["bg_feature_spp"] == 16
    # the whole setting chosen per scene by the evaluation's setting pilot
    assert bp.parse_evaluate_as("auto")[:2] == ("oidn-through", "setting")
    assert bp.parse_evaluate_as("auto:oidn-raw")[:2] == ("oidn-raw", "setting")
    # today's pilot (cost model, 6-spp level) and the previous one kept to measure against
    assert {k: bp.parse_evaluate_as("auto")[2][k] for k in ("candidates", "cost")} == {"candidates": "default",
                                                                                      "cost": "model"}
    assert {k: bp.parse_evaluate_as("auto:oidn-through:coarse")[2][k] for k in ("candidates", "cost")} == {
        "candidates": "coarse", "cost": "measured"}
    assert bp.parse_evaluate_as("oidn-through:auto")[1] == "auto"
    assert bp.measured_at((d, k, o), 4) and not bp.measured_at((d, k, o), 64)
    assert bp.measured_at(bp.parse_evaluate_as("off:1"), 64)
    for bad, why in (("bm3d:1", "denoiser"), ("oidn-through:0", "FACTOR"), ("off:1:sum", "option"),
                     ("off:1:f0", "option"), ("off:1:halton", "option"), ("off:1:b0", "option"), ("off:1@4/x", "levels"),
                     ("auto:bm3d", "denoiser"), ("auto:oidn-through:fine", "candidate set")):
        with pytest.raises(ValueError, match=why):
            bp.parse_evaluate_as(bad)


def test_cli_refuses_levels_not_measured(bench_module, monkeypatch, capsys):
    bp = bench_module("bench_planner")
    monkeypatch.setattr("sys.argv", ["bench_planner.py", "--eval-levels", "8,64", "--evaluate-as", "off:1@4/8"])
    with pytest.raises(SystemExit) as exc:
        bp.main()
    assert exc.value.code == 2
    assert "levels [4] are not in --eval-levels [8, 64]" in capsys.readouterr().err


def test_seconds_at_equal_error_from_one_level_and_from_a_curve(bench_module):
    """One level measured: the error taken as falling with seconds^-0.5 through it (4x the seconds halve it); two:
    log-log interpolation between them."""
    bp = bench_module("bench_planner")
    assert math.isclose(bp.seconds_at([(2.0, 0.01)], 0.005), 8.0)
    assert math.isclose(bp.seconds_at([(1.0, 0.04), (4.0, 0.01)], 0.02), 2.0)
    # the cheapest level already below the target: its seconds (a lower bound on the speed-up), not extrapolated
    assert bp.clamped_seconds([(2.0, 0.01)], 0.02, bp.seconds_at([(2.0, 0.01)], 0.02)) == (2.0, True)


def test_a_setting_label_reads_back_as_the_same_setting(bench_module):
    """What the setting pilot records (``EvaluationSetting.label``) is what ``--evaluate-as`` measures."""
    from evaluation.views import EvaluationSetting

    bp = bench_module("bench_planner")
    for s in (EvaluationSetting("oidn-through", 32, "max", 32, 4, 16), EvaluationSetting("oidn-through", 8, "product",
                                                                                        None, 8)):
        d, k, o = bp.parse_evaluate_as(s.label)
        assert (d, k, o["combine"], o["feature_spp"], o["bg_feature_spp"], o["levels"]) == (
            s.denoise, s.object_spp, s.combine, s.feature_spp, s.background_feature_spp, (s.spp,))


def test_gradient_warmup_gives_every_view_its_silhouette_pass(bench_module):
    """The Stage 1 probes are timed only once every view has had its primary-silhouette pass (a windowed view's first
    one costs a JIT compile of ~8 CPU s): the warm-up runs the asked probes, then exactly the iterations that bring a
    new view, in order, until all have had one; without a budgeted projective integrator, only the asked probes."""
    import types

    from optimizer.rendering.projective import silhouette_view_weights

    bp = bench_module("bench_planner")

    def stage(views: int, every: int, projective: bool = True):
        sensors = [types.SimpleNamespace(id=(lambda i=i: f"sensor_{i:03d}")) for i in range(views)]
        integ = types.SimpleNamespace(silhouette_views=None) if projective else types.SimpleNamespace()
        scene = types.SimpleNamespace(integrator=lambda: integ, sensors=lambda: sensors)
        return types.SimpleNamespace(scene=scene, views_for_step=lambda: list(range(views)),
                                     cfg=types.SimpleNamespace(silhouette_every=every, seed=0))

    ids = [f"sensor_{i:03d}" for i in range(8)]
    its = bp.warmup_iterations(stage(8, 4), 1, 30_000)
    assert its[0] == 30_000 and its == sorted(its) and len(its) >= 4  # 2 views a step: at least 4 steps for 8
    chosen = [set(silhouette_view_weights(ids, 4, k, 0)) for k in its]
    assert set().union(*chosen) == set(ids)
    seen = set(chosen[0])
    for k, c in zip(its[1:], chosen[1:]):  # each extra probe brings a view not seen before ...
        assert not c <= seen
        seen |= c
    skipped = [k for k in range(its[0], its[-1]) if k not in its]  # ... and the iterations left out bring none
    for k in skipped:
        assert set(silhouette_view_weights(ids, 4, k, 0)) <= set().union(
            *[set(silhouette_view_weights(ids, 4, j, 0)) for j in its if j < k])
    assert bp.warmup_iterations(stage(4, 1), 2, 100) == [100, 101]  # every view each step
    assert bp.warmup_iterations(stage(4, 4, projective=False), 1, 7) == [7]


def test_gradient_probe_table_lists_every_probe_in_run_order(bench_module, capsys):
    """The timing check under the gradient table: each repetition's seconds in run order (a compile spike stays
    visible though the table keeps the least), the warm-up's seconds per probe, the cosines' mean and sample sd."""
    bp = bench_module("bench_planner")
    rows = [{"who": "plan", "spp": 4, "rep": k, "seconds": s, "cosine": c, "loss_error": 0.0}
            for k, (s, c) in enumerate([(21.5, 0.80), (3.2, 0.84), (3.4, 0.88)])]
    rows.append({"who": "full-lt", "spp": 4, "rep": 0, "seconds": 4.1, "cosine": 0.7, "loss_error": 0.0})
    bp.print_gradient_probes([{"scene": "meadow", "rows": rows, "warmup": {"plan@4": {"probes": 4, "seconds": 10.0, "settle": 3.0}}}])
    out = capsys.readouterr().out
    assert "| meadow | plan | 4 | 21.50, 3.20, 3.40 | 2.50 (4); 3.00 | 0.840 +- 0.040 |" in out
    assert "| meadow | full-lt | 4 | 4.10 | - | 0.700 +- - |" in out


def test_real_packs_resolve_to_their_pack_files_and_a_missing_one_is_refused(bench_module):
    """``--scenes`` / ``--real`` take the real packs: the diagonal of grids/real.toml by name (packs/real/NAME.toml)
    and the 8 x 8 of grids/real_cross.toml as cross/HDRI-OBJECT; a built-in name is left to the scene resolver."""
    from pathlib import Path

    bp = bench_module("bench_planner")
    p = Path(bp.real_pack_path("forest-teddy"))
    assert p.parts[-3:] == ("packs", "real", "forest-teddy.toml") and p.is_file()
    q = Path(bp.real_pack_path("cross/sky-mug"))
    assert q.parts[-4:] == ("packs", "real", "cross", "sky-mug.toml") and q.is_file()
    assert bp.real_pack_path("meadow") is None
    with pytest.raises(SystemExit, match="no real pack 'cross/sky-teapot'"):
        bp.real_pack_path("cross/sky-teapot")
    assert all(Path(bp.real_pack_path(n)).is_file() for n in bp.REAL_PACKS)


def test_the_variants_table_reads_every_other_curve_against_the_same_full_tracing(bench_module, capsys):
    """``--samplers`` / ``--rr-depths``: each scene's other curves, their speed-ups and errors at the stage's spp,
    with mean and minimum per column; a scene without a variant shows '-'."""
    bp = bench_module("bench_planner")
    v = lambda sp, e: {"speedup": sp, "error_at_spp": e / 255}  # noqa: E731
    res = {"args": {"eval_spp": 64}, "eval": [
        {"scene": "gravel", "speedup": 2.5, "noise_at_spp": 1.7 / 255, "plan_sampler": "sobol", "rr_depth": 5,
         "variants": {"plan-independent": v(1.1, 2.7), "full-sobol": v(2.4, 1.7)}},
        {"scene": "room", "speedup": 3.0, "noise_at_spp": 1.5 / 255, "plan_sampler": "sobol", "rr_depth": 5,
         "variants": {"plan-independent": v(2.0, 2.2)}},
        # a curve whose cheapest level (1 s) is already below full tracing's error: its seconds, a lower bound
        {"scene": "split", "speedup": 4.0, "noise_at_spp": 1.2 / 255, "full_error_at_spp": 0.01,
         "full_seconds_at_spp": 2.0, "variants": {"full-sobol": {**v(4.0, 1.3), "curve": [(1.0, 0.005), (2.0, 0.004)],
                                                                 "seconds_at_equal_error": 0.5}}}]}
    bp.print_variants(res)
    out = capsys.readouterr().out
    assert "(sampler sobol, Russian roulette from vertex 5)" in out
    assert "| gravel | 1.10x / 2.70 | 2.40x / 1.70 | 2.50x / 1.70 |" in out
    assert "| room | 2.00x / 2.20 | - | 3.00x / 1.50 |" in out
    assert "| split | - | >= 2.00x / 1.30 | 4.00x / 1.20 |" in out
    assert "| mean / min | 1.55x / 1.10x | 2.20x / 2.00x | 3.17x / 2.50x |" in out
