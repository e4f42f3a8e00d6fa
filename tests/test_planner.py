"""Effect-planner decisions for scene / parameter combinations."""

from __future__ import annotations

import dataclasses

import pytest

from optimizer import builtin_scenes
from optimizer.environments import ENVIRONMENTS, Environment
from optimizer.planner import plan


def env_of(name: str) -> Environment:
    desc, build, emitters, nearby, occl = ENVIRONMENTS[name]
    return Environment(name, desc, build, emitters, nearby, occl)


ALL = {"albedo", "pose", "displacement", "bsdf", "transmittance"}


def test_full_method_outdoors_uses_prb_projective_for_transmission():
    pack = builtin_scenes.get("meadow")
    p = plan(pack, env_of("meadow"), ALL)
    assert p.integrator["type"] == "prb_projective"
    assert p.integrator["sppi"] == 0 and p.integrator["max_depth"] == 6 == p.integrator["rr_depth"]
    assert not p.batch


def test_opaque_object_in_open_scene_uses_direct_projective():
    pack = builtin_scenes.get("meadow")
    pack.material = dataclasses.replace(pack.material, transmittance=0.0)
    p = plan(pack, env_of("meadow"), ALL - {"transmittance"})
    assert p.integrator == {"type": "direct_projective", "sppi": 0}
    assert p.max_depth == 2


def test_opaque_object_indoors_keeps_interreflection():
    pack = builtin_scenes.get("room")
    pack.material = dataclasses.replace(pack.material, transmittance=0.0)
    p = plan(pack, env_of("room"), {"albedo", "pose", "bsdf"})
    assert p.integrator["type"] == "prb_projective" and p.integrator["max_depth"] == 4


def test_material_only_uses_prb_and_batch():
    pack = builtin_scenes.get("gravel")
    p = plan(pack, env_of("gravel"), {"albedo", "bsdf", "transmittance"})
    assert p.integrator["type"] == "prb" and p.batch and p.integrator["max_depth"] == 6


def test_albedo_only_opaque_is_shallow():
    pack = builtin_scenes.get("gravel")
    pack.material = dataclasses.replace(pack.material, transmittance=0.0)
    p = plan(pack, env_of("gravel"), {"albedo"})
    assert p.integrator == {"type": "prb", "max_depth": 3, "rr_depth": 3}


def test_shadow_gradients_turn_indirect_visibility_on():
    pack = builtin_scenes.get("meadow")
    p = plan(pack, env_of("meadow"), ALL, shadow_gradients=True)
    assert "sppi" not in p.integrator  # Mitsuba's default (on)


@pytest.mark.parametrize("purpose", ["render", "evaluate"])
def test_rendering_uses_path_tracing(purpose):
    pack = builtin_scenes.get("occluded")
    p = plan(pack, env_of("occluded"), ALL, purpose=purpose)
    assert p.integrator["type"] == "path" and p.batch
    assert p.integrator["max_depth"] == 6
    assert any(k == "emitters" and "sun" in v for k, v in p.reasons)
