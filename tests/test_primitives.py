"""Built-in objects: valid closed meshes standing on z = 0, centred, largest side 1."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from optimizer.scenes import primitives
from camo_base.errors import CamoError

NAMES = sorted(primitives.PRIMITIVES)


def _has_manifold() -> bool:
    try:
        import manifold3d  # noqa: F401
    except Exception:
        return False
    return True


@pytest.fixture(scope="module")
def built() -> dict[str, trimesh.Trimesh]:
    return {name: primitives.make_primitive(name) for name in NAMES}


def test_registry_has_the_required_objects():
    required = {"utility_box", "backpack", "chair", "vase", "torus"}
    assert required <= set(primitives.PRIMITIVES)
    assert len(primitives.PRIMITIVES) >= 5
    assert primitives.primitive_names() == NAMES


@pytest.mark.parametrize("name", NAMES)
def test_primitive_is_placed_and_valid(built, name):
    m = built[name]
    assert isinstance(m, trimesh.Trimesh)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    assert len(f) >= 100 and np.isfinite(v).all()
    lo, hi = m.bounds
    assert lo[2] == 0.0  # stands on the ground plane, exactly
    assert np.allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)  # centred in x/y
    assert np.max(hi - lo) == pytest.approx(1.0, abs=1e-9)  # largest side 1
    # no degenerate triangles, no repeated indices, no unused vertices
    assert (m.area_faces > 1e-12).all()
    assert len(np.unique(f)) == len(v)
    # closed, consistently wound, normals pointing outward
    assert m.is_watertight
    assert m.is_winding_consistent
    assert m.volume > 0


@pytest.mark.parametrize("name", sorted(primitives.SINGLE_VOLUME))
def test_single_volume_objects_are_one_body(built, name):
    m = built[name]
    if not _has_manifold() and name in {"utility_box", "backpack", "teapot", "duck"}:
        pytest.skip("boolean union needs manifold3d")
    bodies = m.split(only_watertight=False)
    assert len(bodies) == 1
    assert m.is_volume


def test_chair_is_made_of_parts(built):
    parts = built["chair"].split(only_watertight=False)
    assert len(parts) == 8  # seat, four legs, two back posts, backrest
    seat_height = 0.47
    legs = [p for p in parts if p.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)]
    assert len(legs) == 4 and all(p.bounds[1, 2] < seat_height for p in legs)


def test_torus_lies_on_the_ground(built):
    m = built["torus"]
    ext = m.extents
    assert ext[0] == pytest.approx(1.0) and ext[1] == pytest.approx(1.0)
    assert ext[2] == pytest.approx(0.3, abs=1e-6)  # 2 r / (2 (R + r)) = 0.3
    # the hole: the centre axis does not hit the surface
    ray = trimesh.ray.ray_triangle.RayMeshIntersector(m)
    assert not ray.intersects_any([[0, 0, -1.0]], [[0, 0, 1.0]])[0]


def test_vase_is_open_at_the_top_and_closed_at_the_bottom(built):
    m = built["vase"]
    ray = trimesh.ray.ray_triangle.RayMeshIntersector(m)
    # straight down the axis: enters the cavity through the mouth, hits the inner bottom first
    loc, _, _ = ray.intersects_location([[0, 0, 2.0]], [[0, 0, -1.0]])
    zs = np.sort(loc[:, 2])[::-1]
    assert 0.0 < zs[0] < 0.2  # the first surface below the open mouth is the (thick) bottom
    assert np.isclose(zs[-1], 0.0)


def test_make_primitive_unknown_name_lists_valid_ones():
    with pytest.raises(CamoError) as err:
        primitives.make_primitive("spaceship")
    msg = str(err.value)
    assert "spaceship" in msg and "utility_box" in msg and "\n" not in msg


def test_make_primitive_returns_fresh_meshes():
    a = primitives.make_primitive("bollard")
    a.vertices += 5.0
    b = primitives.make_primitive("bollard")
    assert b.bounds[0, 2] == 0.0


def test_rounded_box_has_requested_extents_and_radius():
    m = primitives.rounded_box((0.6, 0.4, 1.0), radius=0.05)
    assert m.is_watertight and m.volume > 0
    assert np.allclose(m.extents, (0.6, 0.4, 1.0))
    # volume of a rounded box: inner box grown by r, minus what the rounding removes
    a, b, c, r = 0.5, 0.3, 0.9, 0.05
    exact = a * b * c + 2 * r * (a * b + b * c + c * a) + np.pi * r**2 * (a + b + c) + 4 / 3 * np.pi * r**3
    assert m.volume == pytest.approx(exact, rel=5e-3)


def test_primitives_without_manifold_fall_back_to_closed_parts(monkeypatch):
    def no_boolean(*args, **kwargs):
        raise ImportError("manifold3d missing")

    monkeypatch.setattr(trimesh.boolean, "union", no_boolean)
    monkeypatch.setattr(trimesh.boolean, "difference", no_boolean)
    m = primitives.backpack()
    assert m.is_watertight and len(m.split(only_watertight=False)) == 4
    assert m.bounds[0, 2] == 0.0 and np.max(m.extents) == pytest.approx(1.0)
