"""Mesh preparation: loading, cleaning, normalisation, remeshing, UV unwrapping, displacement, cache."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from optimizer.scenes import mesh as M
from optimizer.scenes import primitives
from camo_base.errors import CamoError

# --------------------------------------------------------------------------- helpers


def _box(extents=(1.0, 1.0, 1.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents)


def _dense_sphere() -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=5)  # 10242 vertices
    rng = np.random.default_rng(0)
    m.vertices = m.vertices + rng.normal(0, 1e-5, m.vertices.shape)
    return m


def _surface_distance(a: trimesh.Trimesh, b: trimesh.Trimesh, n: int = 400) -> float:
    """Symmetric max distance of surface samples of one mesh to the other (Hausdorff-ish)."""
    pa = trimesh.sample.sample_surface_even(a, n, seed=1)[0]
    pb = trimesh.sample.sample_surface_even(b, n, seed=2)[0]
    da = trimesh.proximity.closest_point(b, pa)[1]
    db = trimesh.proximity.closest_point(a, pb)[1]
    return float(max(da.max(), db.max()))


@pytest.fixture(scope="module")
def prepared(tmp_path_factory) -> M.PreparedMesh:
    """A small prepared torus (1500 welded vertices), shared by the read-only tests."""
    cache = tmp_path_factory.mktemp("cache")
    return M.prepare_mesh(primitives.torus(), target_vertices=1500, cache_dir=cache)


# --------------------------------------------------------------------------- load


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "off", "glb", "gltf"])
def test_load_mesh_formats(tmp_path, ext):
    box = _box((1.0, 2.0, 3.0))
    path = tmp_path / f"box.{ext}"
    if ext == "gltf":
        files = box.export(file_type="gltf")
        for name, data in files.items():
            (tmp_path / name).write_bytes(data)
        path = tmp_path / "model.gltf"
    else:
        box.export(path)
    m = M.load_mesh(path)
    assert isinstance(m, trimesh.Trimesh)
    assert len(m.faces) == 12
    expected = (1.0, 3.0, 2.0) if ext in ("glb", "gltf") else (1.0, 2.0, 3.0)  # glTF's +Y up becomes +Z up
    assert np.allclose(m.extents, expected, atol=1e-6)


def test_load_mesh_flattens_scenes(tmp_path):
    a = _box()
    b = _box()
    b.apply_translation((3.0, 0, 0))
    scene = trimesh.Scene([a, b])
    path = tmp_path / "two.glb"
    scene.export(path)
    m = M.load_mesh(path)
    assert len(m.faces) == 24
    assert m.bounds[1, 0] == pytest.approx(3.5)


@pytest.mark.parametrize(
    "name, content, expect",
    [
        ("broken.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 10\ngarbage\n\x00\x01", "cannot read"),
        ("broken.glb", b"glTF\x02\x00\x00\x00\xff\xff\x00\x00garbage-not-json", "cannot read"),
        ("broken.stl", b"solid x\n facet normal 0 0 banana\n", "cannot read"),
        ("words.obj", b"this is not a mesh\njust some words\n", "no triangles"),
        ("empty.obj", b"", "empty"),
        ("nan.obj", b"v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "NaN"),
        ("inf.obj", b"v 0 0 0\nv 1 0 0\nv inf 1 0\nf 1 2 3\n", "NaN or infinite"),
    ],
)
def test_load_mesh_bad_files_raise_camo_error(tmp_path, name, content, expect):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(CamoError) as err:
        M.load_mesh(path)
    msg = str(err.value)
    assert expect in msg and "\n" not in msg and name in msg


def test_load_mesh_missing_and_unsupported(tmp_path):
    with pytest.raises(CamoError, match="not found"):
        M.load_mesh(tmp_path / "nope.obj")
    (tmp_path / "model.fbx").write_bytes(b"whatever")
    with pytest.raises(CamoError, match=r"unsupported mesh format '\.fbx'.*OBJ, PLY, STL, GLB, GLTF, OFF"):
        M.load_mesh(tmp_path / "model.fbx")
    with pytest.raises(CamoError, match="not a file"):
        M.load_mesh(tmp_path)


# --------------------------------------------------------------------------- clean


def test_clean_merges_duplicates_and_drops_bad_faces():
    box = _box()
    v = np.asarray(box.vertices)[box.faces].reshape(-1, 3)  # 36 unmerged vertices
    f = np.arange(36).reshape(-1, 3)
    v = v + np.random.default_rng(0).normal(0, 1e-9, v.shape)  # near-duplicates, not bit-identical
    extra_faces = np.array([[0, 0, 5], [2, 1, 0]])  # repeated index; same triangle as face 0, reversed
    v = np.vstack([v, [[9.0, 9.0, 9.0]]])  # unreferenced vertex
    m = trimesh.Trimesh(v, np.vstack([f, extra_faces]), process=False)
    out, rep = M.clean_mesh(m)
    assert len(out.vertices) == 8 and len(out.faces) == 12
    assert rep["merged_vertices"] == 28
    assert rep["degenerate_faces"] == 1
    assert rep["duplicate_faces"] == 1
    assert rep["unreferenced_vertices"] == 1
    assert rep["is_watertight"] and rep["boundary_edges"] == 0 and rep["non_manifold_edges"] == 0
    assert rep["warnings"] == []
    assert out.volume == pytest.approx(1.0)


def test_clean_drops_zero_area_faces():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], float)
    f = np.array([[0, 1, 2], [0, 1, 3]])  # second one is collinear
    out, rep = M.clean_mesh(trimesh.Trimesh(v, f, process=False))
    assert rep["degenerate_faces"] == 1 and len(out.faces) == 1
    assert rep["unreferenced_vertices"] == 1


def test_clean_fixes_winding_and_inside_out():
    box = _box()
    f = np.asarray(box.faces).copy()
    f[:5] = f[:5, ::-1]  # some faces flipped
    out, rep = M.clean_mesh(trimesh.Trimesh(box.vertices, f, process=False))
    assert out.is_winding_consistent and out.volume == pytest.approx(1.0)
    inside_out = trimesh.Trimesh(box.vertices, np.asarray(box.faces)[:, ::-1], process=False)
    out, rep = M.clean_mesh(inside_out)
    assert out.volume == pytest.approx(1.0) and rep["flipped_faces"] == 12


def test_clean_reports_holes():
    box = _box()
    holed = trimesh.Trimesh(box.vertices, np.asarray(box.faces)[1:], process=False)
    out, rep = M.clean_mesh(holed)
    assert rep["boundary_edges"] == 3
    assert rep["non_manifold_edges"] == 0
    assert rep["is_watertight"] is False
    assert any("boundary edges" in w for w in rep["warnings"])


def _non_manifold_mesh() -> trimesh.Trimesh:
    """Closed box plus a fin triangle hanging off one of its edges: that edge has three faces."""
    box = _box()
    v = np.asarray(box.vertices)
    f = np.asarray(box.faces)
    edges, counts = np.unique(np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0, return_counts=True)
    # an edge of the cube (not a face diagonal): length 1
    e = next(e for e in edges if np.isclose(np.linalg.norm(v[e[0]] - v[e[1]]), 1.0))
    tip = (v[e[0]] + v[e[1]]) / 2 + 0.5 * np.sign((v[e[0]] + v[e[1]]) / 2) * np.array([1, 1, 1]) * (
        np.abs((v[e[0]] + v[e[1]]) / 2) > 0.25
    )
    v2 = np.vstack([v, tip])
    f2 = np.vstack([f, [[e[0], e[1], len(v)]]])
    return trimesh.Trimesh(v2, f2, process=False)


def test_clean_reports_non_manifold_edges():
    out, rep = M.clean_mesh(_non_manifold_mesh())
    assert rep["non_manifold_edges"] == 1
    assert rep["boundary_edges"] == 2  # the fin's two free edges
    assert any("non-manifold" in w for w in rep["warnings"])


def test_clean_refuses_when_nothing_is_left():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)
    with pytest.raises(CamoError, match="nothing left after cleaning"):
        M.clean_mesh(trimesh.Trimesh(v, [[0, 1, 2], [0, 0, 1]], process=False))


# --------------------------------------------------------------------------- normalise


@pytest.mark.parametrize("size", [1.0, 2.5])
def test_normalise(size):
    m = _box((0.2, 4.0, 1.0))
    m.apply_translation((10.0, -3.0, 7.0))
    out, T = M.normalise(m, size)
    lo, hi = out.bounds
    assert lo[2] == 0.0
    assert np.max(hi - lo) == pytest.approx(size)
    assert np.allclose((lo[:2] + hi[:2]) / 2, 0.0)
    homog = np.c_[m.vertices, np.ones(len(m.vertices))] @ T.T
    assert np.allclose(homog[:, :3], out.vertices)
    with pytest.raises(CamoError):
        M.normalise(m, 0.0)


# --------------------------------------------------------------------------- remesh


def test_remesh_subdivides_low_poly_to_target_without_changing_the_shape():
    box = _box((1.0, 0.5, 0.25))
    out = M.remesh_to_target(box, 1000)
    assert abs(len(out.vertices) - 1000) <= 150
    assert out.metadata["camo_remesh"]["steps"][-1].startswith("split")
    assert out.is_watertight and out.is_winding_consistent
    assert out.volume == pytest.approx(box.volume)
    assert np.allclose(out.bounds, box.bounds)
    # every new vertex lies on the original surface
    d = trimesh.proximity.closest_point(box, out.vertices)[1]
    assert d.max() < 1e-9
    # edges got short and fairly even
    edges = out.edges_unique_length
    assert edges.max() < 0.1 and edges.max() / edges.mean() < 3.0


@pytest.mark.parametrize("decimator", ["quadric", "cluster"])
def test_remesh_decimates_dense_input(decimator):
    if decimator == "quadric" and not M.remesh._have_fast_simplification():
        pytest.skip("fast-simplification is not installed")
    dense = _dense_sphere()
    out = M.remesh_to_target(dense, 1500, decimator=decimator)
    assert abs(len(out.vertices) - 1500) <= 0.15 * 1500
    assert out.metadata["camo_remesh"]["steps"][0].startswith(f"decimate:{decimator}")
    assert _surface_distance(dense, out) < 0.03  # radius 1
    assert (out.area_faces > 0).all()


def test_remesh_keeps_meshes_within_tolerance_and_checks_arguments():
    m = trimesh.creation.icosphere(subdivisions=3)  # 642 vertices
    out = M.remesh_to_target(m, 600)
    assert len(out.vertices) == 642 and out.metadata["camo_remesh"]["steps"] == ["kept"]
    with pytest.raises(CamoError):
        M.remesh_to_target(m, 0)
    with pytest.raises(CamoError):
        M.remesh_to_target(m, 100.5)


# --------------------------------------------------------------------------- normals


def test_vertex_normals_flat_and_sphere():
    grid = trimesh.creation.box((1, 1, 1))
    top = grid.faces[grid.face_normals[:, 2] > 0.5]
    n = M.vertex_normals(np.asarray(grid.vertices, np.float32), top)
    used = np.unique(top)
    assert n.dtype == np.float32
    assert np.allclose(n[used], [0, 0, 1], atol=1e-6)
    sphere = trimesh.creation.icosphere(subdivisions=4)
    n = M.vertex_normals(sphere.vertices, sphere.faces)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.einsum("ij,ij->i", n, sphere.vertices / np.linalg.norm(sphere.vertices, axis=1)[:, None]).min() > 0.999


def test_vertex_normals_area_weighted():
    # vertex 0 shared by a big triangle in the xy plane and a small one in the xz plane
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, -0.5], [0.5, 0, 0]], float)
    f = np.array([[0, 1, 2], [0, 3, 4]])
    n = M.vertex_normals(v, f)[0]
    a_big, a_small = 2.0, 0.125
    expected = np.array([0, a_small * -1, a_big]) / np.hypot(a_small, a_big)
    # face 2 normal: (0,0,-.5)x(.5,0,0) = (0,-0.25,0) -> -y
    assert np.allclose(n, expected)


# --------------------------------------------------------------------------- UV unwrap / prepared mesh


def test_prepared_mesh_arrays(prepared):
    p = prepared
    assert abs(p.n_welded - 1500) <= 0.15 * 1500
    assert p.vertices.dtype == np.float32 and p.normals.dtype == np.float32 and p.uvs.dtype == np.float32
    assert p.vertices.shape == (p.n_welded, 3) and p.uv_vertices.shape == (p.n_uv, 3)
    assert p.uvs.shape == (p.n_uv, 2) and p.uv_to_welded.shape == (p.n_uv,)
    assert p.uvs.min() >= 0.0 and p.uvs.max() <= 1.0
    # both views describe the same triangles
    assert np.array_equal(p.uv_to_welded[p.uv_faces], p.faces)
    assert np.array_equal(p.uv_vertices, p.vertices[p.uv_to_welded])
    # every welded vertex is used; a closed surface needs seams
    assert np.array_equal(np.unique(p.uv_to_welded), np.arange(p.n_welded))
    assert p.n_uv > p.n_welded
    # unit normals; no degenerate faces in 3D or in UV space
    assert np.allclose(np.linalg.norm(p.normals, axis=1), 1.0, atol=1e-6)
    f = p.faces
    assert not ((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])).any()
    area3 = np.linalg.norm(np.cross(p.vertices[f[:, 1]] - p.vertices[f[:, 0]], p.vertices[f[:, 2]] - p.vertices[f[:, 0]]), axis=1)
    assert area3.min() > 0
    t = p.uvs[p.uv_faces]
    area_uv = np.abs(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]))
    assert area_uv.min() > 0
    # normalised on the ground
    assert p.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-6)
    assert np.ptp(p.vertices, axis=0).max() == pytest.approx(1.0, abs=1e-5)
    assert p.report["is_watertight"] and p.report["unwrap"]["charts"] >= 1


def test_prepare_mesh_holed_and_non_manifold_inputs(tmp_path):
    box = _box()
    holed = trimesh.Trimesh(box.vertices, np.asarray(box.faces)[1:], process=False)
    for mesh, key in ((holed, "boundary_edges"), (_non_manifold_mesh(), "non_manifold_edges")):
        p = M.prepare_mesh(mesh, target_vertices=400, cache_dir=tmp_path)
        assert p.report[key] >= 1 and p.report["warnings"]
        assert abs(p.n_welded - 400) <= 60
        assert p.uvs.min() >= 0 and p.uvs.max() <= 1
        assert np.array_equal(p.uv_to_welded[p.uv_faces], p.faces)


def test_prepare_mesh_from_file_and_default_target(tmp_path, monkeypatch):
    path = tmp_path / "bollard.obj"
    primitives.bollard().export(path)
    monkeypatch.setenv("CAMO_CACHE", str(tmp_path / "camo-cache"))
    assert M.default_cache_dir() == tmp_path / "camo-cache" / "meshes"
    p = M.prepare_mesh(path)  # paper default: ~30,000 vertices
    assert abs(p.n_welded - 30_000) <= 0.15 * 30_000
    assert p.report["source"] == str(path)
    assert list((tmp_path / "camo-cache" / "meshes").glob("*.npz"))


def test_to_ply_and_to_trimesh(prepared, tmp_path):
    p = prepared
    path = p.to_ply(tmp_path / "uv.ply")
    back = trimesh.load(path, process=False)
    assert len(back.vertices) == p.n_uv and np.array_equal(back.faces, p.uv_faces)
    assert np.allclose(back.vertices, p.uv_vertices)
    t = p.to_trimesh()
    assert np.allclose(t.visual.uv[:, 0], p.uvs[:, 0]) and np.allclose(t.visual.uv[:, 1], 1.0 - p.uvs[:, 1])
    moved = M.displace_welded(p, 0.01)
    assert np.allclose(p.to_trimesh(moved).vertices, moved[p.uv_to_welded])


# --------------------------------------------------------------------------- displacement and sampling


def test_displacement_moves_along_normals_and_keeps_seams_closed(prepared):
    p = prepared
    d = np.random.default_rng(3).uniform(-0.05, 0.05, p.n_welded)
    welded = M.displace_welded(p, d)
    delta = welded.astype(np.float64) - p.vertices
    assert np.allclose(np.linalg.norm(delta, axis=1), np.abs(d), atol=1e-6)
    assert np.allclose(delta, d[:, None] * p.normals, atol=1e-6)
    uv_pos = M.displace(p, d)
    assert uv_pos.shape == (p.n_uv, 3)
    counts = np.bincount(p.uv_to_welded)
    seam = np.flatnonzero(counts >= 2)
    assert len(seam) > 0
    for w in seam[:50]:
        copies = uv_pos[p.uv_to_welded == w]
        assert (copies == copies[0]).all()  # bit-identical: no crack
    with pytest.raises(ValueError):
        M.displace(p, np.zeros(p.n_welded + 1))


def test_bilinear_sampling_on_a_2x2_map():
    a, b, c, d = 1.0, 2.0, 4.0, 8.0
    m = np.array([[a, b], [c, d]], np.float32)  # row 0 = top of the image = v in [0, 0.5]
    uv = np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75],
                   [0.5, 0.5], [0.5, 0.25], [0.375, 0.25], [0.25, 0.625]])
    expect = [a, b, c, d, (a + b + c + d) / 4, (a + b) / 2, 0.75 * a + 0.25 * b, 0.25 * a + 0.75 * c]
    assert np.allclose(M.sample_map_bilinear(m, uv), expect)
    # OpenGL-style UVs: (0, 0) is the bottom-left texel
    assert np.allclose(M.sample_map_bilinear(m, uv[:4], flip_v=True), [c, d, a, b])
    # borders: clamp keeps the corner texel, repeat blends with the opposite side (Mitsuba default)
    corner = np.array([[0.0, 0.0]])
    assert M.sample_map_bilinear(m, corner, wrap="clamp")[0] == pytest.approx(a)
    assert M.sample_map_bilinear(m, corner, wrap="repeat")[0] == pytest.approx((a + b + c + d) / 4)
    # channels
    rgb = np.stack([m, 2 * m, -m], axis=-1)
    out = M.sample_map_bilinear(rgb, uv)
    assert out.shape == (len(uv), 3) and np.allclose(out[:, 1], 2 * np.asarray(expect))


def test_welded_sampling_averages_seam_copies(prepared):
    p = prepared
    rng = np.random.default_rng(5)
    mp = rng.random((16, 16)).astype(np.float32)
    per_uv = M.sample_map_bilinear(mp, p.uvs)
    welded = M.sample_welded(p, mp)
    w = int(np.flatnonzero(np.bincount(p.uv_to_welded) >= 2)[0])
    assert welded[w] == pytest.approx(per_uv[p.uv_to_welded == w].mean())
    S = M.welded_sampling_matrix(p, mp.shape)
    assert S.shape == (p.n_welded, 256)
    assert np.allclose(S @ mp.ravel(), welded)
    assert np.allclose(np.asarray(S.sum(axis=1)).ravel(), 1.0)


# --------------------------------------------------------------------------- cache


def test_cache_hit_and_corrupt_cache_rebuilt(tmp_path):
    mesh = primitives.bollard()
    first = M.prepare_mesh(mesh, target_vertices=600, cache_dir=tmp_path)
    files = list(tmp_path.glob("*.npz"))
    assert not first.cache_hit and len(files) == 1 and files[0].stem == first.key
    second = M.prepare_mesh(mesh, target_vertices=600, cache_dir=tmp_path)
    assert second.cache_hit
    for name in ("vertices", "faces", "normals", "uv_vertices", "uv_faces", "uvs", "uv_to_welded"):
        assert np.array_equal(getattr(first, name), getattr(second, name))
    assert np.array_equal(first.transform, second.transform)
    assert second.report["remesh"] == first.report["remesh"]
    # other parameters -> other key
    other = M.prepare_mesh(mesh, target_vertices=700, cache_dir=tmp_path)
    assert other.key != first.key and len(list(tmp_path.glob("*.npz"))) == 2
    # corrupt file: ignored and rebuilt
    files[0].write_bytes(b"PK\x03\x04 this is not a zip archive")
    third = M.prepare_mesh(mesh, target_vertices=600, cache_dir=tmp_path)
    assert not third.cache_hit
    assert np.array_equal(third.uvs, first.uvs) and np.array_equal(third.faces, first.faces)
    fourth = M.prepare_mesh(mesh, target_vertices=600, cache_dir=tmp_path)
    assert fourth.cache_hit
    # truncated file
    data = files[0].read_bytes()
    files[0].write_bytes(data[: len(data) // 2])
    assert not M.prepare_mesh(mesh, target_vertices=600, cache_dir=tmp_path).cache_hit
    # no temporary files left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in tmp_path.glob("*.npz"))


def test_prepare_mesh_rejects_bad_input(tmp_path):
    with pytest.raises(CamoError):
        M.prepare_mesh(42, cache_dir=tmp_path)
    with pytest.raises(CamoError, match="not found"):
        M.prepare_mesh(tmp_path / "missing.glb", cache_dir=tmp_path)


# --------------------------------------------------------------------------- xatlas isolation


def test_xatlas_crash_becomes_camo_error(monkeypatch):
    monkeypatch.setattr(M.uv, "_XATLAS_WORKER", "import os; os.abort()")
    with pytest.raises(CamoError, match="xatlas"):
        M.uv_unwrap(_box())


# --------------------------------------------------------------------------- Mitsuba's UV convention


_MITSUBA_SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    ply, tex_path, out, res = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    tex = np.load(tex_path).astype(np.float32)
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
                   "sampler": {"type": "stratified", "sample_count": 64}},
        "quad": {"type": "ply", "filename": ply,
                 "emitter": {"type": "area", "radiance": {"type": "bitmap", "bitmap": mi.Bitmap(tex), "raw": True,
                                                            "filter_type": "bilinear", "wrap_mode": "clamp"}},
                 "bsdf": {"type": "diffuse", "reflectance": 0.0}},
    })
    np.save(out, np.array(mi.render(scene)))
    """
)


def test_uv_convention_matches_mitsuba(tmp_path):
    """A quad written by ``to_ply`` and rendered by Mitsuba shows the map exactly as
    ``sample_map_bilinear`` samples it (and not v-flipped)."""
    probe = subprocess.run([sys.executable, "-c", "import mitsuba"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip("mitsuba is not importable")
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    uv = ((v[:, :2] + 1) / 2).astype(np.float32)
    quad = M.UVMesh(v, f, M.vertex_normals(v, f), v.copy(), f.copy(), uv, np.arange(4, dtype=np.int32))
    quad.to_ply(tmp_path / "quad.ply")
    tex = np.random.default_rng(0).random((4, 4, 3)).astype(np.float32)
    np.save(tmp_path / "tex.npy", tex)
    script = tmp_path / "render.py"
    script.write_text(_MITSUBA_SCRIPT)
    res = 16
    env = {k: val for k, val in os.environ.items() if k != "CAMO_VARIANT"}
    run = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "quad.ply"), str(tmp_path / "tex.npy"), str(tmp_path / "out.npy"),
         str(res)], capture_output=True, text=True, timeout=120, env=env,
    )
    if run.returncode != 0 and "variant" in run.stderr:
        pytest.skip(f"mitsuba scalar_rgb unavailable: {run.stderr.strip().splitlines()[-1]}")
    assert run.returncode == 0, run.stderr[-2000:]
    img = np.load(tmp_path / "out.npy")[..., :3]
    # pixel (row i, col j) centre sees u = (j + .5) / res, v = 1 - (i + .5) / res (image row 0 = top = +y)
    jj, ii = np.meshgrid(np.arange(res), np.arange(res))
    uv_px = np.stack([(jj + 0.5) / res, 1.0 - (ii + 0.5) / res], axis=-1).reshape(-1, 2)
    ours = M.sample_map_bilinear(tex, uv_px, wrap="clamp").reshape(res, res, 3)
    flipped = M.sample_map_bilinear(tex, uv_px, wrap="clamp", flip_v=True).reshape(res, res, 3)
    assert np.abs(ours - img).max() < 0.02
    assert np.abs(flipped - img).max() > 0.2


# --------------------------------------------------------------------------- more properties


@settings(max_examples=50, deadline=None)
@given(
    h=st.integers(2, 9), w=st.integers(2, 9),
    alpha=st.floats(-3, 3), beta=st.floats(-3, 3),
    s=st.floats(0, 1), t=st.floats(0, 1),
)
def test_bilinear_reproduces_linear_maps(h, w, alpha, beta, s, t):
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    m = alpha * cols + beta * rows + 0.5
    # anywhere between the outermost texel centres, bilinear interpolation of a linear map is exact
    u = (0.5 + s * (w - 1)) / w
    v = (0.5 + t * (h - 1)) / h
    got = M.sample_map_bilinear(m, np.array([[u, v]]))[0]
    assert got == pytest.approx(alpha * (u * w - 0.5) + beta * (v * h - 0.5) + 0.5, abs=1e-9)
    got_flip = M.sample_map_bilinear(m, np.array([[u, 1.0 - v]]), flip_v=True)[0]
    assert got_flip == pytest.approx(got, abs=1e-9)


def test_vertex_normals_fallback_for_cancelling_faces():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    n = M.vertex_normals(v, np.array([[0, 1, 2], [0, 2, 1]]))  # two opposite faces: the sum vanishes
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.allclose(np.abs(n[:, 2]), 1.0)


def test_clean_merges_stl_style_triangle_soup(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    path = tmp_path / "soup.stl"
    sphere.export(path)  # STL stores every triangle with its own three vertices
    soup = M.load_mesh(path)
    assert len(soup.vertices) == 3 * len(sphere.faces)
    out, rep = M.clean_mesh(soup)
    assert len(out.vertices) == len(sphere.vertices)
    assert rep["merged_vertices"] == 3 * len(sphere.faces) - len(sphere.vertices)
    assert rep["is_watertight"] and out.volume > 0


def test_auto_decimator_falls_back_to_clustering(monkeypatch):
    monkeypatch.setattr(M.remesh, "_have_fast_simplification", lambda: False)
    out = M.remesh_to_target(_dense_sphere(), 1200)
    assert out.metadata["camo_remesh"]["steps"][0].startswith("decimate:cluster")
    assert abs(len(out.vertices) - 1200) <= 180
    with pytest.raises(CamoError, match="fast-simplification"):
        M.remesh_to_target(_dense_sphere(), 1200, decimator="quadric")


def test_prepare_mesh_checks_parameters_and_report_is_json(prepared, tmp_path):
    import json

    json.dumps(prepared.report)
    assert prepared.report["remesh"]["vertices_after"] == prepared.n_welded
    box = _box()
    for kwargs in ({"target_vertices": 0}, {"target_vertices": 10.5}, {"size": -1.0}, {"tol": 1.5},
                   {"decimator": "magic"}, {"unwrap_options": {"bogus": 1}}):
        with pytest.raises(CamoError):
            M.prepare_mesh(box, cache_dir=tmp_path, **kwargs)
    assert not list(tmp_path.iterdir())



def test_uv_unwrap_in_process_matches_isolated():
    box = M.remesh_to_target(_box(), 300)
    a = M.uv_unwrap(box, isolate=False)
    b = M.uv_unwrap(box, isolate=True)
    assert np.array_equal(a.uv_to_welded[a.uv_faces], a.faces)
    assert a.n_welded == b.n_welded == 300
    assert np.array_equal(a.faces, b.faces) and np.allclose(a.uvs, b.uvs)


def test_gltf_is_turned_z_up(tmp_path):
    """glTF is +Y up by specification: a tall box exported to GLB comes back tall along z."""
    import trimesh

    from optimizer.scenes.mesh import load_mesh

    box = trimesh.creation.box([0.2, 1.0, 0.3])  # tallest along y, as a glTF author would model "up"
    box.export(tmp_path / "tall.glb")
    ext = load_mesh(tmp_path / "tall.glb").extents
    np.testing.assert_allclose(sorted(ext), [0.2, 0.3, 1.0], atol=1e-6)
    assert ext[2] == pytest.approx(1.0)
