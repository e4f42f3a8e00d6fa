"""Mesh preparation: load -> clean -> normalise -> remesh -> UV-unwrap, with an on-disk cache.

The paper (Sec. IV-A) remeshes/subdivides every object to about 30,000
vertices and UV-unwraps it so that texture maps (albedo, roughness, metallic,
transmittance) and the displacement map ``D`` can be stored in UV space; the
displacement moves every vertex along its normal, ``v' = v + D(u) n``
(Sec. III-B.2). This module produces exactly that input.

Frame and units
---------------
Z is up. After :func:`normalise` (and in every :class:`PreparedMesh`) the
object's largest bounding-box side equals ``size`` scene units, its bounding
box is centred at ``x = y = 0`` and its lowest point lies on ``z = 0``.

Welded mesh and UV mesh
-----------------------
xatlas cuts the surface into charts, so a vertex on a seam gets one UV vertex
per chart it belongs to. Displacing those copies independently would tear the
surface open along the seams. A :class:`UVMesh` therefore holds two views of
one surface:

* the **welded** mesh ``vertices (Nw,3)``, ``faces (F,3)``, ``normals (Nw,3)``
  (area-weighted, unit length): one vertex per surface point; the
  displacement is applied here;
* the **UV** mesh ``uv_vertices (Nu,3)``, ``uv_faces (F,3)``, ``uvs (Nu,2)``:
  what the renderer gets; ``uv_to_welded (Nu,)`` maps every UV vertex to its
  welded vertex, and ``uv_faces[i]`` is the same triangle as ``faces[i]``
  (``uv_to_welded[uv_faces] == faces``).

Sampling a UV map for a welded vertex
-------------------------------------
A welded vertex on a seam has several UV positions (one per chart). Its value
is the **mean of the bilinear samples at all of its UV copies**
(:func:`sample_welded`, or the equivalent sparse matrix from
:func:`welded_sampling_matrix`). Both sides of a seam then get the same
displacement and move together, and the surface stays closed. Vertices off
the seams have one copy and get the plain bilinear sample.

UV convention (checked against Mitsuba 3.9)
-------------------------------------------
Mitsuba's ``bitmap`` texture does **not** flip v: its texel lookup is
``(u W - 0.5, v H - 0.5)`` into the tensor, row 0 first, so ``uv = (0, 0)``
is the first row of the ``(H, W[, C])`` array, i.e. the **top-left** of the
image as written to PNG (checked in ``src/textures/bitmap.cpp`` and with a
render: a quad whose bottom edge has ``v = 0`` shows image row 0 there). The
flip people remember comes from Mitsuba's OBJ loader, which by default
(``flip_tex_coords=true``) turns OBJ's bottom-left ``vt`` into ``1 - v`` on
load; the PLY loader does not flip by default (``flip_tex_coords=false``), and
UVs set directly on an ``mi.Mesh`` are used as they are.

``PreparedMesh.uvs`` are stored in Mitsuba's (and glTF's) convention:
``(0, 0)`` is row 0 of the map array. Hence:

* ``mi.Mesh`` ``vertex_texcoords = uvs`` and :meth:`UVMesh.to_ply` (read by
  Mitsuba's ``ply`` plugin with its default ``flip_tex_coords=false``) render
  the maps exactly as :func:`sample_map_bilinear` (default ``flip_v=False``)
  samples them;
* OBJ files need ``vt = (u, 1 - v)``; :meth:`UVMesh.to_trimesh` stores
  ``(u, 1 - v)`` because trimesh keeps OpenGL-style UVs internally and flips
  again when it writes glTF;
* UVs in the OpenGL/OBJ convention (``(0, 0)`` = bottom-left = row ``H-1``)
  are sampled with ``sample_map_bilinear(..., flip_v=True)``.

Texel centres are at ``(i + 0.5) / W``; ``wrap="repeat"`` (Mitsuba's default
``wrap_mode``) or ``"clamp"``.

Cache
-----
:func:`prepare_mesh` stores its result as ``<key>.npz`` in
``$CAMO_CACHE/meshes`` (default ``~/.cache/camo/meshes``); the key hashes the
input vertex/face arrays, the parameters, the source of this module and the
xatlas version. Files are written atomically; an unreadable or inconsistent
cache file is ignored and rebuilt.

Supported input formats: OBJ, PLY, STL, GLB, GLTF, OFF (scenes are flattened
into one mesh with their node transforms).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from camo_base.atomic import atomic_path
from camo_base.errors import CamoError

__all__ = [
    "DEFAULT_TARGET_VERTICES",
    "SUPPORTED_EXTENSIONS",
    "PreparedMesh",
    "UVMesh",
    "bilinear_weights",
    "clean_mesh",
    "default_cache_dir",
    "displace",
    "displace_welded",
    "load_mesh",
    "normalise",
    "prepare_mesh",
    "remesh_to_target",
    "sample_map_bilinear",
    "sample_welded",
    "uv_unwrap",
    "vertex_normals",
    "welded_mean",
    "welded_sampling_matrix",
]

#: file extensions :func:`load_mesh` reads (lower case)
SUPPORTED_EXTENSIONS: tuple[str, ...] = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")

#: vertex count of the prepared (welded) mesh, as in the paper (Sec. IV-A)
DEFAULT_TARGET_VERTICES = 30_000

#: bump when the cache file layout changes (the module source is hashed as well)
CACHE_FORMAT = 1

#: a dense mesh is decimated to this fraction of the target, then split up to
#: the target, so large flat triangles left by the decimation get refined too
DECIMATE_FRACTION = 0.7

#: relative (to the bounding-box diagonal) distance under which vertices are merged
MERGE_TOLERANCE = 1e-6

#: default xatlas settings; ``max_chart_area_fraction`` bounds every chart's
#: area by this fraction of the surface area, which keeps xatlas fast
#: (chart growing and LSCM scale badly with chart size)
DEFAULT_UNWRAP_OPTIONS: dict[str, Any] = {
    "max_chart_area_fraction": 1.0 / 32.0,
    "padding": 4,
    "resolution": 0,
    "max_iterations": 1,
}


def _trimesh():
    import trimesh

    return trimesh


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    msg = text[0] if text else ""
    return (msg[:200] or type(exc).__name__)


# =========================================================================== load


def load_mesh(path: str | os.PathLike):
    """Read a triangle mesh from OBJ/PLY/STL/GLB/GLTF/OFF.

    Scenes (several meshes, node transforms) are flattened into one mesh.
    glTF/GLB files (+Y up by specification) are turned +Z up.
    Returns a plain ``trimesh.Trimesh`` (float64 vertices, int64 faces, no
    visuals; nothing merged or removed yet, see :func:`clean_mesh`).

    Raises :class:`CamoError` for a missing file, an unsupported extension, a
    file that cannot be parsed, a file without triangles, and NaN/inf
    coordinates.
    """
    trimesh = _trimesh()
    p = Path(path).expanduser()
    if not p.exists():
        raise CamoError(f"mesh file not found: {p}")
    if not p.is_file():
        raise CamoError(f"mesh path is not a file: {p}")
    ext = p.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise CamoError(
            f"unsupported mesh format {ext or '(no extension)'!r} for {p}; "
            f"supported: {', '.join(e[1:].upper() for e in SUPPORTED_EXTENSIONS)}"
        )
    if p.stat().st_size == 0:
        raise CamoError(f"cannot read mesh {p}: the file is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(str(p), file_type=ext[1:], force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds of errors for bad files
        raise CamoError(f"cannot read mesh {p}: {_one_line(exc)}") from None
    if isinstance(loaded, (list, tuple)):
        loaded = trimesh.util.concatenate([m for m in loaded if isinstance(m, trimesh.Trimesh)] or [trimesh.Trimesh()])
    if not isinstance(loaded, trimesh.Trimesh):
        raise CamoError(f"cannot read mesh {p}: it holds no triangle mesh ({type(loaded).__name__})")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if faces.size == 0 or vertices.size == 0:
        raise CamoError(f"cannot read mesh {p}: it contains no triangles (corrupt, empty or not a surface)")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise CamoError(f"cannot read mesh {p}: faces are not triangles")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise CamoError(f"cannot read mesh {p}: faces refer to vertices that do not exist")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise CamoError(f"mesh {p} has {int(bad.sum())} vertices with NaN or infinite coordinates")
    if ext in (".glb", ".gltf"):
        # glTF is +Y up by specification; the toolkit is +Z up: rotate +90 degrees about x (y -> z).
        vertices = np.stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]], axis=1)
    return trimesh.Trimesh(vertices, faces, process=False)


# =========================================================================== clean


def _edge_keys(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(F*3,) int64 key ``min * n + max`` of every face edge (e0=v0v1, e1=v1v2, e2=v2v0 per face)."""
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64)
    lo, hi = np.minimum(e[:, 0], e[:, 1]), np.maximum(e[:, 0], e[:, 1])
    return lo * np.int64(max(n_vertices, 1)) + hi


def _edges_with_counts(faces: np.ndarray, n_vertices: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    n = int(faces.max()) + 1 if n_vertices is None else int(n_vertices)
    keys, counts = np.unique(_edge_keys(faces, n), return_counts=True)
    return np.column_stack([keys // max(n, 1), keys % max(n, 1)]), counts


def _merge_close_vertices(vertices: np.ndarray, faces: np.ndarray, tol: float):
    """Union vertices closer than ``tol`` (exact duplicates first, then KD-tree pairs + components).

    Each merged vertex keeps the position of its lowest-index member; the
    kept vertices stay in the order of their first index.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(vertices)
    if n == 0:
        return vertices, faces, 0
    uniq, inverse = np.unique(vertices, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    nu = len(uniq)
    labels_u = np.arange(nu)
    if tol > 0 and nu > 1:
        pairs = cKDTree(uniq).query_pairs(tol, output_type="ndarray")
        if len(pairs):
            graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(nu, nu))
            _, labels_u = connected_components(graph, directed=False)
    labels = labels_u[inverse]
    n_comp = int(labels.max()) + 1
    if n_comp == n:
        return vertices, faces, 0
    # representative = smallest original index in the component; number components by it
    rep = np.full(n_comp, n, dtype=np.int64)
    np.minimum.at(rep, labels, np.arange(n))
    order = np.argsort(rep, kind="stable")
    new_label = np.empty(n_comp, dtype=np.int64)
    new_label[order] = np.arange(n_comp)
    return vertices[rep[order]], new_label[labels][faces], n - n_comp


def _clean_arrays(vertices: np.ndarray, faces: np.ndarray, merge_tol: float = MERGE_TOLERANCE):
    """Merge, drop degenerate/duplicate faces and unreferenced vertices. Returns (V, F, counts)."""
    counts: dict[str, int] = {}
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    valid = (f >= 0).all(axis=1) & (f < len(v)).all(axis=1)
    counts["invalid_faces"] = int((~valid).sum())
    f = f[valid]
    diag = float(np.linalg.norm(np.ptp(v, axis=0))) if len(v) else 0.0
    v, f, merged = _merge_close_vertices(v, f, merge_tol * diag)
    counts["merged_vertices"] = int(merged)
    # degenerate: repeated index or (numerically) zero area
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area2 = np.linalg.norm(cross, axis=1)
    zero = area2 <= 1e-14 * max(diag, 1e-300) ** 2
    degenerate = repeated | zero
    counts["degenerate_faces"] = int(degenerate.sum())
    f = f[~degenerate]
    # duplicates: same three vertices, whatever the order or winding
    if len(f):
        _, keep = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
        keep = np.sort(keep)
        counts["duplicate_faces"] = int(len(f) - len(keep))
        f = f[keep]
    else:
        counts["duplicate_faces"] = 0
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    counts["unreferenced_vertices"] = int((~used).sum())
    remap = np.cumsum(used) - 1
    return v[used], remap[f], counts


def _orient_outward(mesh) -> int:
    """Flip connected components whose faces point inward on the whole; returns faces flipped.

    For a closed component the criterion is the sign of its volume; for an
    open one it is the same flux integral ``sum (c_f - c) . n_f A_f`` about the
    component's centroid, a sensible guess for "outside".
    """
    trimesh = _trimesh()
    faces = np.asarray(mesh.faces)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(faces))
    tri = mesh.triangles
    centers = tri.mean(axis=1)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # 2 A n
    areas = np.linalg.norm(cross, axis=1)
    n_lab = labels.max() + 1
    w = np.bincount(labels, weights=areas, minlength=n_lab)
    cen = np.stack([np.bincount(labels, weights=areas * centers[:, k], minlength=n_lab) for k in range(3)], 1)
    cen /= np.maximum(w, 1e-300)[:, None]
    flux = np.einsum("ij,ij->i", centers - cen[labels], cross)
    total = np.bincount(labels, weights=flux, minlength=n_lab)
    flip = (total < 0)[labels]
    if flip.any():
        new_faces = faces.copy()
        new_faces[flip] = new_faces[flip][:, ::-1]
        mesh.faces = new_faces
    return int(flip.sum())


def clean_mesh(mesh, merge_tol: float = MERGE_TOLERANCE):
    """Repair a mesh for preparation; returns ``(clean_mesh, report)``.

    Steps: merge vertices closer than ``merge_tol`` x bounding-box diagonal,
    drop degenerate (repeated-index or zero-area) and duplicate faces (same
    three vertices in any order), remove unreferenced vertices, make the
    winding consistent (``trimesh.repair.fix_winding``) and orient every
    connected component outward.

    Holes and non-manifold edges are kept (they cannot be fixed without
    changing the shape) and reported with a warning. The report is a
    JSON-serialisable dict with the counts removed (``merged_vertices``,
    ``degenerate_faces``, ``duplicate_faces``, ``unreferenced_vertices``,
    ``invalid_faces``), the result's ``vertices``/``faces``/``components``,
    ``is_watertight``, ``is_winding_consistent``, ``boundary_edges``,
    ``non_manifold_edges``, ``flipped_faces`` and ``warnings`` (list of str).

    Raises :class:`CamoError` when the input has NaN/inf coordinates or
    nothing is left after cleaning.
    """
    trimesh = _trimesh()
    v_in = np.asarray(mesh.vertices, dtype=np.float64)
    f_in = np.asarray(mesh.faces, dtype=np.int64)
    if f_in.size == 0 or v_in.size == 0:
        raise CamoError("mesh has no triangles")
    if not np.isfinite(v_in).all():
        raise CamoError(f"mesh has {int((~np.isfinite(v_in).all(axis=1)).sum())} vertices with NaN or infinite coordinates")
    v, f, counts = _clean_arrays(v_in, f_in, merge_tol)
    if len(f) == 0:
        raise CamoError(
            f"mesh has nothing left after cleaning: all {len(f_in)} triangles were degenerate, duplicated or invalid"
        )
    out = trimesh.Trimesh(v, f, process=False)
    warn: list[str] = []
    if not out.is_winding_consistent:
        try:
            trimesh.repair.fix_winding(out)
        except Exception as exc:  # pragma: no cover - trimesh internals on odd topology
            warn.append(f"winding could not be repaired: {_one_line(exc)}")
    flipped = _orient_outward(out)
    _, ecount = _edges_with_counts(np.asarray(out.faces), len(out.vertices))
    boundary = int((ecount == 1).sum())
    non_manifold = int((ecount > 2).sum())
    labels = trimesh.graph.connected_component_labels(out.face_adjacency, node_count=len(out.faces))
    components = int(labels.max() + 1) if len(labels) else 0
    consistent = bool(out.is_winding_consistent)
    if boundary:
        warn.append(f"mesh is open: {boundary} boundary edges (holes); they are kept open")
    if non_manifold:
        warn.append(f"{non_manifold} non-manifold edges (shared by more than two triangles); kept as they are")
    if not consistent:
        warn.append("triangle winding is not consistent everywhere (non-orientable or non-manifold parts); "
                    "some normals may point inward")
    report = {
        "vertices_in": int(len(v_in)),
        "faces_in": int(len(f_in)),
        **counts,
        "vertices": int(len(out.vertices)),
        "faces": int(len(out.faces)),
        "components": components,
        "is_watertight": bool(boundary == 0 and non_manifold == 0),
        "is_winding_consistent": consistent,
        "boundary_edges": boundary,
        "non_manifold_edges": non_manifold,
        "flipped_faces": flipped,
        "warnings": warn,
    }
    return out, report


# =========================================================================== normalise


def normalise(mesh, size: float = 1.0):
    """Scale so the largest bounding-box side is ``size``, centre x/y at 0, lowest point on z = 0.

    Returns ``(new_mesh, T)`` with ``T`` the (4, 4) float64 matrix applied
    (``new = T @ [old, 1]``): uniform scale, then translation.
    """
    trimesh = _trimesh()
    size = float(size)
    if not np.isfinite(size) or size <= 0:
        raise CamoError(f"object size must be a positive number, got {size}")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if len(v) == 0:
        raise CamoError("mesh has no vertices")
    lo, hi = v.min(axis=0), v.max(axis=0)
    extent = float(np.max(hi - lo))
    if not np.isfinite(extent) or extent <= 0:
        raise CamoError("mesh has zero size (all vertices coincide)")
    s = size / extent
    t = -s * np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    T = np.eye(4)
    T[:3, :3] *= s
    T[:3, 3] = t
    nv = v * s + t
    dz = nv[:, 2].min()  # rounding residue, so that min z is exactly 0
    nv[:, 2] -= dz
    T[2, 3] -= dz
    return trimesh.Trimesh(nv, np.asarray(mesh.faces), process=False), T


# =========================================================================== remesh


def _unique_edges(faces: np.ndarray, n_vertices: int):
    """(E, 2) unique sorted edges and the (F, 3) edge index of every face edge (e0=v0v1, e1=v1v2, e2=v2v0)."""
    keys, inverse = np.unique(_edge_keys(faces, n_vertices), return_inverse=True)
    n = np.int64(max(n_vertices, 1))
    return np.column_stack([keys // n, keys % n]), inverse.reshape(-1, 3)


def _split_edges(v: np.ndarray, f: np.ndarray, mark: np.ndarray, edges: np.ndarray, face_edges: np.ndarray):
    """Split the marked edges at their midpoints; faces get 2, 3 or 4 children. Keeps orientation."""
    n = len(v)
    mid_index = np.full(len(edges), -1, dtype=np.int64)
    marked = np.flatnonzero(mark)
    mid_index[marked] = n + np.arange(len(marked))
    v = np.concatenate([v, 0.5 * (v[edges[marked, 0]] + v[edges[marked, 1]])])
    fm = mark[face_edges]  # (F, 3)
    mids = mid_index[face_edges]
    cnt = fm.sum(axis=1)
    out = [f[cnt == 0]]
    rows = np.arange(3)

    # one marked edge: rotate it to e0 = (a, b); children (a, m, c), (m, b, c)
    sel = np.flatnonzero(cnt == 1)
    if len(sel):
        r = np.argmax(fm[sel], axis=1)
        idx = (r[:, None] + rows) % 3
        a, b, c = (f[sel[:, None], idx]).T
        m = mids[sel, r]
        out += [np.column_stack([a, m, c]), np.column_stack([m, b, c])]

    # two marked edges: rotate so the unmarked one is e2 = (c, a)
    sel = np.flatnonzero(cnt == 2)
    if len(sel):
        r = (np.argmin(fm[sel], axis=1) + 1) % 3
        idx = (r[:, None] + rows) % 3
        a, b, c = (f[sel[:, None], idx]).T
        mab = mids[sel, r]
        mbc = mids[sel, (r + 1) % 3]
        out.append(np.column_stack([mab, b, mbc]))
        # split the quad (a, mab, mbc, c) along its shorter diagonal
        d1 = np.linalg.norm(v[a] - v[mbc], axis=1)
        d2 = np.linalg.norm(v[mab] - v[c], axis=1)
        use1 = d1 <= d2
        out += [
            np.column_stack([a, mab, mbc])[use1], np.column_stack([a, mbc, c])[use1],
            np.column_stack([a, mab, c])[~use1], np.column_stack([mab, mbc, c])[~use1],
        ]

    sel = np.flatnonzero(cnt == 3)
    if len(sel):
        a, b, c = f[sel].T
        m0, m1, m2 = mids[sel].T
        out += [np.column_stack(t) for t in ((a, m0, m2), (m0, b, m1), (m2, m1, c), (m0, m1, m2))]
    return v, np.concatenate(out).astype(np.int64)


def _flip_edges(v: np.ndarray, f: np.ndarray, max_dihedral_deg: float = 1.0, max_rounds: int = 30) -> np.ndarray:
    """Delaunay edge flips restricted to (nearly) flat pairs of triangles; returns new faces.

    An interior edge ``ab`` shared by ``(a, b, c)`` and ``(b, a, d)`` is
    flipped to ``cd`` when the opposite angles sum to more than pi (the
    Delaunay criterion, which raises the smaller angles), the two triangles
    are within ``max_dihedral_deg`` of coplanar (so the surface does not
    change beyond that), the new triangles are not inverted and ``cd`` is not
    an edge yet. Each round flips an independent set of edges (every face in
    at most one flip). Vertex positions are never changed.
    """
    f = np.array(f, dtype=np.int64, copy=True)
    n = len(v)
    cos_max = np.cos(np.radians(max_dihedral_deg))

    def angle(p, q, r):  # angle at p in the triangle (p, q, r)
        u, w = q - p, r - p
        return np.arctan2(np.linalg.norm(np.cross(u, w), axis=1), np.einsum("ij,ij->i", u, w))

    for _ in range(max_rounds):
        keys = _edge_keys(f, n)
        order = np.argsort(keys, kind="stable")
        uniq, start, counts = np.unique(keys[order], return_index=True, return_counts=True)
        two = counts == 2
        h1, h2 = order[start[two]], order[start[two] + 1]
        f1, k1, f2, k2 = h1 // 3, h1 % 3, h2 // 3, h2 % 3
        a, b, c = f[f1, k1], f[f1, (k1 + 1) % 3], f[f1, (k1 + 2) % 3]
        d = f[f2, (k2 + 2) % 3]
        ok = (f[f2, k2] == b) & (f[f2, (k2 + 1) % 3] == a) & (c != d)
        pa, pb, pc, pd = v[a], v[b], v[c], v[d]
        n1, n2 = np.cross(pb - pa, pc - pa), np.cross(pa - pb, pd - pb)
        l1, l2 = np.linalg.norm(n1, axis=1), np.linalg.norm(n2, axis=1)
        ok &= (l1 > 0) & (l2 > 0)
        ok &= np.einsum("ij,ij->i", n1, n2) >= cos_max * l1 * l2
        excess = angle(pc, pa, pb) + angle(pd, pb, pa) - np.pi
        ok &= excess > 1e-9
        ref = n1 / np.maximum(l1, 1e-300)[:, None] + n2 / np.maximum(l2, 1e-300)[:, None]
        ok &= np.einsum("ij,ij->i", np.cross(pd - pa, pc - pa), ref) > 0
        ok &= np.einsum("ij,ij->i", np.cross(pb - pd, pc - pd), ref) > 0
        new_key = np.minimum(c, d) * np.int64(n) + np.maximum(c, d)
        ok &= ~np.isin(new_key, uniq)
        cand = np.flatnonzero(ok)
        if len(cand) == 0:
            break
        # an edge flips when it is the worst candidate of both of its faces
        srt = cand[np.argsort(-excess[cand], kind="stable")]
        face_seq = np.column_stack([f1[srt], f2[srt]]).ravel()
        _, first = np.unique(face_seq, return_index=True)
        best = np.full(len(f), -1, dtype=np.int64)
        best[face_seq[first]] = np.repeat(srt, 2)[first]
        sel = cand[(best[f1[cand]] == cand) & (best[f2[cand]] == cand)]
        sel = sel[np.unique(new_key[sel], return_index=True)[1]]
        f[f1[sel]] = np.column_stack([a[sel], d[sel], c[sel]])
        f[f2[sel]] = np.column_stack([d[sel], b[sel], c[sel]])
    return f


def _split_to_count(v: np.ndarray, f: np.ndarray, target: int, band: float = 0.75, flip_rounds: int = 2,
                    final_flip_rounds: int = 30):
    """Longest-edge refinement until the mesh has exactly ``target`` vertices.

    Every round splits the edges longer than ``band`` x the current longest
    edge (longest first, at most as many as vertices are still missing); each
    split edge adds exactly one vertex, so the count is hit exactly. Midpoint
    splits keep the surface (piecewise linear) unchanged.
    """
    v = np.asarray(v, dtype=np.float64)
    f = np.asarray(f, dtype=np.int64)
    while len(v) < target:
        edges, face_edges = _unique_edges(f, len(v))
        length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
        # Relative lengths rounded to 1e-9: equal edges of a scaled copy tie exactly (stable sort by index),
        # so preparation does not depend on the input's scale through the last float bits.
        length = np.round(length / length.max(), 9)
        budget = target - len(v)
        cand = np.flatnonzero(length >= band)
        if len(cand) > budget:
            order = np.argsort(-length[cand], kind="stable")
            cand = cand[order[:budget]]
        mark = np.zeros(len(edges), dtype=bool)
        mark[cand] = True
        v, f = _split_edges(v, f, mark, edges, face_edges)
        if flip_rounds:
            f = _flip_edges(v, f, max_rounds=flip_rounds)
    if final_flip_rounds:
        f = _flip_edges(v, f, max_rounds=final_flip_rounds)
    return v, f


def _have_fast_simplification() -> bool:
    try:
        import fast_simplification  # noqa: F401
    except Exception:
        return False
    return True


def _resolve_decimator(decimator: str) -> str:
    if decimator not in ("auto", "quadric", "cluster"):
        raise CamoError(f"unknown decimator {decimator!r}; choose auto, quadric or cluster")
    if decimator == "auto":
        return "quadric" if _have_fast_simplification() else "cluster"
    if decimator == "quadric" and not _have_fast_simplification():
        raise CamoError("decimator 'quadric' needs the package fast-simplification (pip install fast-simplification)")
    return decimator


def _decimate_quadric(v: np.ndarray, f: np.ndarray, target: int):
    """Quadric edge-collapse decimation (fast-simplification) to about ``target`` vertices."""
    import fast_simplification

    nv, nf = v, f
    face_target = int(len(f) * target / max(len(v), 1))
    for _ in range(3):
        nv, nf = fast_simplification.simplify(
            np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(f, dtype=np.int64),
            target_count=max(face_target, 4),
        )
        nv, nf, _ = _clean_arrays(nv, nf, merge_tol=0.0)
        if len(nv) <= target * 1.02 or len(nf) == 0:
            break
        face_target = int(face_target * target / len(nv))
    return nv, nf


def _cluster_once(v: np.ndarray, f: np.ndarray, cell: float, bucket: np.ndarray):
    lo = v.min(axis=0)
    key = np.column_stack([np.floor((v - lo) / cell).astype(np.int64), bucket])
    _, labels, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    labels = labels.reshape(-1)
    pos = np.stack([np.bincount(labels, weights=v[:, k]) for k in range(3)], axis=1) / cnt[:, None]
    return pos, labels[f]


def _decimate_cluster(v: np.ndarray, f: np.ndarray, target: int):
    """Vertex clustering on a regular grid whose cell size is found by bisection (fallback decimator).

    Each occupied cell becomes one vertex at the mean of its members; faces
    that collapse are dropped. Two groupings are tried, by cell alone and by
    cell plus the dominant direction of the vertex normal (+-x, +-y, +-z, so
    the two sides of a thin wall do not collapse into each other); the result
    with fewer non-manifold and boundary edges wins. Clustering can still
    damage the topology of thin parts: the quadric decimator (used when
    ``fast-simplification`` is installed) is the better choice.
    """
    n = vertex_normals(v, f)
    axis = np.argmax(np.abs(n), axis=1)
    by_normal = 2 * axis + (n[np.arange(len(n)), axis] < 0)
    best = None
    for bucket in (np.zeros(len(v), dtype=np.int64), by_normal):
        nv, nf = _cluster_to_count(v, f, target, bucket)
        if len(nf) == 0:
            continue
        _, cnt = _edges_with_counts(nf, len(nv))
        defects = int((cnt != 2).sum())
        if best is None or defects < best[0]:
            best = (defects, nv, nf)
    if best is None:
        return v[:0], f[:0]
    return best[1], best[2]


def _cluster_to_count(v: np.ndarray, f: np.ndarray, target: int, bucket: np.ndarray):
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    lo_c, hi_c = diag * 1e-6, diag  # fine cell -> many vertices, coarse -> few
    best = None
    for _ in range(40):
        cell = np.sqrt(lo_c * hi_c)
        pos, ff = _cluster_once(v, f, cell, bucket)
        if len(pos) > target:
            lo_c = cell
        else:
            hi_c = cell
            best = (pos, ff)
            if len(pos) >= 0.9 * target:
                break
    if best is None:
        best = _cluster_once(v, f, hi_c, bucket)
    nv, nf, _ = _clean_arrays(best[0], best[1], merge_tol=0.0)
    return nv, nf


def _check_target(target_vertices, tol) -> int:
    if isinstance(target_vertices, bool) or not isinstance(target_vertices, (int, np.integer, float, np.floating)):
        raise CamoError(f"target vertex count must be an integer >= 4, got {target_vertices!r}")
    if not float(target_vertices).is_integer() or target_vertices < 4:
        raise CamoError(f"target vertex count must be an integer >= 4, got {target_vertices!r}")
    try:
        ok = 0.0 <= float(tol) < 1.0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise CamoError(f"remesh tolerance must be in [0, 1), got {tol!r}")
    return int(target_vertices)


def _remesh(mesh, target_vertices: int, tol: float = 0.15, decimator: str = "auto"):
    trimesh = _trimesh()
    target = _check_target(target_vertices, tol)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    n0 = len(v)
    lo, hi = target * (1.0 - tol), target * (1.0 + tol)
    info: dict[str, Any] = {"vertices_before": n0, "target": target, "tol": float(tol), "steps": []}
    if lo <= n0 <= hi:
        info["steps"].append("kept")
    else:
        if n0 > hi:
            method = _resolve_decimator(decimator)
            goal = max(4, int(round(DECIMATE_FRACTION * target)))
            if method == "quadric":
                v, f = _decimate_quadric(v, f, goal)
            if method == "cluster" or len(v) > hi or len(f) == 0:
                if method == "quadric":
                    info["steps"].append("quadric (insufficient)")
                    method = "cluster"
                    v, f = _decimate_cluster(np.asarray(mesh.vertices, dtype=np.float64),
                                             np.asarray(mesh.faces, dtype=np.int64), goal)
                else:
                    v, f = _decimate_cluster(v, f, goal)
            if len(f) == 0:
                raise CamoError("decimation left no triangles; the mesh may be degenerate")
            info["steps"].append(f"decimate:{method}->{len(v)}")
        if len(v) < target:
            v, f = _split_to_count(v, f, target)
            info["steps"].append(f"split->{len(v)}")
    info["vertices_after"] = int(len(v))
    out = trimesh.Trimesh(v, f, process=False)
    return out, info


def remesh_to_target(mesh, target_vertices: int = DEFAULT_TARGET_VERTICES, tol: float = 0.15,
                     decimator: str = "auto"):
    """Bring the vertex count within ``target_vertices * (1 +- tol)``.

    * Already within: returned unchanged (as a copy).
    * Too few vertices: longest-edge midpoint refinement up to exactly
      ``target_vertices``, with Delaunay edge flips between nearly coplanar
      triangles (dihedral < 1 degree) to keep the triangles well shaped; the
      surface does not change (up to those flips on almost flat pairs).
    * Too many: decimate to ``DECIMATE_FRACTION * target`` with quadric edge
      collapse (``fast-simplification``, when installed; ``decimator="auto"``)
      or grid vertex clustering (``decimator="cluster"``, the fallback), then
      refine up to exactly ``target_vertices`` so that large flat triangles are
      subdivided as well.

    The steps taken are in ``result.metadata["camo_remesh"]``.
    """
    out, info = _remesh(mesh, target_vertices, tol, decimator)
    out.metadata["camo_remesh"] = info
    return out


# =========================================================================== normals, UVs


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (sum of un-normalised face cross products).

    A vertex whose weighted sum vanishes (e.g. between two opposite sheets)
    gets the normal of its largest adjacent face; an unreferenced vertex gets
    ``(0, 0, 1)``. Returned with the dtype of ``vertices`` (float32/float64).
    """
    v = np.asarray(vertices)
    fa = np.asarray(faces, dtype=np.int64)
    vd = v.astype(np.float64)
    cross = np.cross(vd[fa[:, 1]] - vd[fa[:, 0]], vd[fa[:, 2]] - vd[fa[:, 0]])  # = 2 A n
    acc = np.zeros((len(v), 3))
    for k in range(3):
        np.add.at(acc, fa[:, k], cross)
    norm = np.linalg.norm(acc, axis=1)
    scale = max(float(np.abs(cross).max()) if len(cross) else 0.0, 1e-300)
    bad = norm <= 1e-12 * scale
    if bad.any():
        # largest adjacent face of every vertex: sort corners by (vertex, area), take the last per vertex
        area = np.linalg.norm(cross, axis=1)
        vi = fa.ravel()
        fi = np.repeat(np.arange(len(fa)), 3)
        order = np.lexsort((area[fi], vi))
        vs, fs = vi[order], fi[order]
        last = np.flatnonzero(np.r_[vs[1:] != vs[:-1], True])
        fallback = np.zeros((len(v), 3))
        fallback[:, 2] = 1.0
        fn = cross[fs[last]]
        fn_len = np.linalg.norm(fn, axis=1)
        ok = fn_len > 0
        fallback[vs[last][ok]] = fn[ok] / fn_len[ok, None]
        acc[bad] = fallback[bad]
        norm = np.linalg.norm(acc, axis=1)
    out = acc / norm[:, None]
    return out.astype(v.dtype if np.issubdtype(v.dtype, np.floating) else np.float64)


_XATLAS_WORKER = r"""
import json, sys
import numpy as np
from optimizer.scenes.mesh import _xatlas_in_process
src, dst, opts = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
d = np.load(src)
result, _ = _xatlas_in_process(d["vertices"], d["faces"], opts)
np.savez(dst, **result)
"""


def _xatlas_in_subprocess(v: np.ndarray, f: np.ndarray, opts: Mapping[str, Any], timeout: float):
    """Run xatlas in a child interpreter: a crash there (xatlas can segfault on some
    inputs) becomes a return code here instead of killing the caller."""
    with tempfile.TemporaryDirectory(prefix="camo-xatlas-") as tmp:
        src, dst = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        np.savez(src, vertices=v, faces=f)
        try:
            root = str(Path(__file__).resolve().parents[1])  # the child imports this module
            env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
            proc = subprocess.run(
                [sys.executable, "-c", _XATLAS_WORKER, src, dst, json.dumps(dict(opts))],
                capture_output=True, timeout=timeout, check=False, env=env,
            )
        except subprocess.TimeoutExpired:
            return None, f"timed out after {timeout:.0f} s"
        if proc.returncode != 0 or not os.path.exists(dst):
            tail = proc.stderr.decode("utf-8", "replace").strip().splitlines()
            why = tail[-1] if tail else ""
            return None, f"exit code {proc.returncode}" + (f": {why}" if why else "")
        with np.load(dst) as z:
            return {k: z[k] for k in z.files}, ""


def _xatlas_in_process(v: np.ndarray, f: np.ndarray, opts: Mapping[str, Any]):
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(v, dtype=np.float32), np.ascontiguousarray(f, dtype=np.uint32))
    co = xatlas.ChartOptions()
    co.max_iterations = int(opts["max_iterations"])
    if opts.get("max_chart_area", 0) > 0:
        co.max_chart_area = float(opts["max_chart_area"])
    po = xatlas.PackOptions()
    po.padding = int(opts["padding"])
    po.resolution = int(opts["resolution"])
    atlas.generate(co, po)
    vm, idx, uv = atlas[0]
    return {"vmapping": vm, "indices": idx, "uvs": uv, "width": atlas.width, "height": atlas.height,
            "charts": atlas.chart_count, "atlases": atlas.atlas_count}, ""


@dataclasses.dataclass(eq=False)
class UVMesh:
    """A welded mesh (for displacement) and its UV-split copy (for rendering); see the module doc.

    Arrays: ``vertices (Nw,3) float32``, ``faces (F,3) int32``, ``normals
    (Nw,3) float32`` (area-weighted, unit), ``uv_vertices (Nu,3) float32``,
    ``uv_faces (F,3) int32``, ``uvs (Nu,2) float32`` in [0, 1] (Mitsuba/glTF
    convention, ``(0,0)`` = row 0 of a map array), ``uv_to_welded (Nu,)
    int32``. ``uv_to_welded[uv_faces] == faces``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uv_vertices: np.ndarray
    uv_faces: np.ndarray
    uvs: np.ndarray
    uv_to_welded: np.ndarray
    #: xatlas statistics (charts, atlas size in texels, faces/vertices it dropped)
    atlas: dict = dataclasses.field(default_factory=dict)

    @property
    def n_welded(self) -> int:
        return int(len(self.vertices))

    @property
    def n_uv(self) -> int:
        return int(len(self.uv_vertices))

    @property
    def uv_normals(self) -> np.ndarray:
        """Welded normals gathered to the UV vertices (seam copies share a normal)."""
        return self.normals[self.uv_to_welded]

    def _uv_positions(self, vertices: np.ndarray | None) -> np.ndarray:
        if vertices is None:
            return self.uv_vertices
        vertices = np.asarray(vertices)
        if vertices.shape == (self.n_welded, 3):
            return vertices[self.uv_to_welded]
        if vertices.shape == (self.n_uv, 3):
            return vertices
        raise ValueError(f"vertices must be ({self.n_welded}, 3) welded or ({self.n_uv}, 3) UV positions, "
                         f"got {vertices.shape}")

    def _normals_for(self, vertices: np.ndarray | None) -> np.ndarray:
        """UV-vertex normals: stored ones, or recomputed (welded, area-weighted) for new positions."""
        if vertices is None:
            return self.uv_normals
        vertices = np.asarray(vertices, dtype=np.float64)
        if vertices.shape == (self.n_welded, 3):
            welded = vertices
        else:
            welded = np.zeros((self.n_welded, 3))
            welded[self.uv_to_welded] = self._uv_positions(vertices)
        return vertex_normals(welded, self.faces)[self.uv_to_welded]

    def to_trimesh(self, vertices: np.ndarray | None = None):
        """The UV mesh as a ``trimesh.Trimesh`` with ``TextureVisuals``.

        ``vertices``: optional displaced positions, welded ``(Nw,3)`` or UV
        ``(Nu,3)`` (normals are then recomputed on the welded mesh). UVs are
        stored as ``(u, 1 - v)``, trimesh's OpenGL convention, so trimesh's
        OBJ and glTF exporters write files that show the maps as Mitsuba does.
        """
        trimesh = _trimesh()
        pos = self._uv_positions(vertices)
        uv_gl = np.column_stack([self.uvs[:, 0], 1.0 - self.uvs[:, 1]])
        return trimesh.Trimesh(
            vertices=np.asarray(pos, dtype=np.float64), faces=np.asarray(self.uv_faces, dtype=np.int64),
            vertex_normals=np.asarray(self._normals_for(vertices), dtype=np.float64),
            visual=trimesh.visual.TextureVisuals(uv=uv_gl), process=False,
        )

    def to_ply(self, path: str | os.PathLike, vertices: np.ndarray | None = None) -> Path:
        """Write the UV mesh as binary PLY (x y z nx ny nz u v; float32) atomically.

        Mitsuba's ``ply`` plugin (default ``flip_tex_coords=false``) reads the
        UVs as stored, i.e. in the convention of :func:`sample_map_bilinear`.
        ``vertices``: optional displaced positions, welded ``(Nw,3)`` (normals
        are then recomputed on the welded mesh) or UV ``(Nu,3)``.
        """
        pos = self._uv_positions(vertices)
        nrm = self._normals_for(vertices)
        rec = np.zeros(self.n_uv, dtype=[(n, "<f4") for n in ("x", "y", "z", "nx", "ny", "nz", "u", "v")])
        for k, n in enumerate(("x", "y", "z")):
            rec[n] = pos[:, k]
        for k, n in enumerate(("nx", "ny", "nz")):
            rec[n] = nrm[:, k]
        rec["u"], rec["v"] = self.uvs[:, 0], self.uvs[:, 1]
        frec = np.zeros(len(self.uv_faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        frec["n"] = 3
        frec["i"] = self.uv_faces
        header = (
            "ply\nformat binary_little_endian 1.0\ncomment camo toolkit UV mesh\n"
            f"element vertex {self.n_uv}\n"
            + "".join(f"property float {n}\n" for n in ("x", "y", "z", "nx", "ny", "nz", "u", "v"))
            + f"element face {len(self.uv_faces)}\nproperty list uchar int vertex_indices\nend_header\n"
        )
        path = Path(path)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(header.encode("ascii"))
                fh.write(rec.tobytes())
                fh.write(frec.tobytes())
        return path


def uv_unwrap(mesh, *, max_chart_area_fraction: float = DEFAULT_UNWRAP_OPTIONS["max_chart_area_fraction"],
              padding: int = DEFAULT_UNWRAP_OPTIONS["padding"], resolution: int = DEFAULT_UNWRAP_OPTIONS["resolution"],
              max_iterations: int = DEFAULT_UNWRAP_OPTIONS["max_iterations"], isolate: bool = True,
              timeout: float = 600.0) -> UVMesh:
    """UV-unwrap ``mesh`` with xatlas; returns a :class:`UVMesh` (welded + UV-split views).

    ``max_chart_area_fraction`` caps every chart at that fraction of the
    surface area (0 = no cap; smaller is faster and gives more, smaller
    charts); ``padding`` is the gap between charts in atlas texels (the atlas
    is about 1k texels wide when ``resolution`` is 0). With ``isolate`` xatlas
    runs in a child interpreter, so that a crash inside xatlas (it segfaults
    on a few inputs, e.g. a perfectly regular icosphere) cannot take the
    caller down; the unwrap is then retried once with the positions jittered
    by 1e-5 of the size, and a :class:`CamoError` is raised if it fails again.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if len(f) == 0:
        raise CamoError("cannot UV-unwrap a mesh without triangles")
    area = float(np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum() / 2)
    opts = {
        "max_chart_area": float(max_chart_area_fraction) * area if max_chart_area_fraction > 0 else 0.0,
        "padding": int(padding), "resolution": int(resolution), "max_iterations": int(max_iterations),
    }
    v32 = v.astype(np.float32)
    result, why = None, ""
    for attempt in range(2):
        vin = v32
        if attempt:
            rng = np.random.default_rng(12345)
            diag = float(np.linalg.norm(np.ptp(v, axis=0)))
            vin = (v + rng.normal(0.0, 1e-5 * diag, v.shape)).astype(np.float32)
        if isolate and sys.executable:
            result, why = _xatlas_in_subprocess(vin, f.astype(np.uint32), opts, timeout)
        else:
            result, why = _xatlas_in_process(vin, f.astype(np.uint32), opts)
        if result is not None and int(result["atlases"]) == 1:
            break
        if result is not None:
            why, result = f"{int(result['atlases'])} atlases instead of one", None
    if result is None:
        raise CamoError(f"UV unwrapping (xatlas) failed on this mesh ({why}); "
                        "try another target vertex count or repair the mesh")
    vmap = result["vmapping"].astype(np.int64)
    uv_faces = result["indices"].astype(np.int64).reshape(-1, 3)
    uvs = np.clip(result["uvs"].astype(np.float32).reshape(-1, 2), 0.0, 1.0)
    faces = vmap[uv_faces]
    # compact the welded vertices in case xatlas dropped faces (it skips degenerate ones)
    used = np.zeros(len(v), dtype=bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    wv = v[used]
    faces = remap[faces]
    vmap = remap[vmap]
    normals = vertex_normals(wv, faces)
    uvm = UVMesh(
        vertices=wv.astype(np.float32),
        faces=faces.astype(np.int32),
        normals=normals.astype(np.float32),
        uv_vertices=wv[vmap].astype(np.float32),
        uv_faces=uv_faces.astype(np.int32),
        uvs=uvs,
        uv_to_welded=vmap.astype(np.int32),
        atlas={
            "charts": int(result["charts"]), "atlas_width": int(result["width"]),
            "atlas_height": int(result["height"]), "dropped_faces": int(len(f) - len(uv_faces)),
            "dropped_vertices": int((~used).sum()),
        },
    )
    return uvm


# =========================================================================== sampling, displacement


def bilinear_weights(uv: np.ndarray, shape: tuple[int, int], *, flip_v: bool = False, wrap: str = "repeat"):
    """Texel rows, columns and weights of a bilinear lookup, Mitsuba-style.

    ``uv`` (N, 2); ``shape`` = (H, W). Texel centres lie at ``(i + 0.5) / W``;
    the lookup position is ``(u W - 0.5, v H - 0.5)`` (``v`` replaced by
    ``1 - v`` when ``flip_v``). ``wrap``: ``"repeat"`` (Mitsuba's default) or
    ``"clamp"``. Returns ``rows, cols, weights``, each (N, 4), corners in the
    order (r0,c0), (r0,c1), (r1,c0), (r1,c1); the weights sum to 1.
    """
    if wrap not in ("repeat", "clamp"):
        raise ValueError(f"wrap must be 'repeat' or 'clamp', got {wrap!r}")
    H, W = int(shape[0]), int(shape[1])
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    u, v = uv[:, 0], uv[:, 1]
    if flip_v:
        v = 1.0 - v
    x = u * W - 0.5
    y = v * H - 0.5
    x0f, y0f = np.floor(x), np.floor(y)
    fx, fy = x - x0f, y - y0f
    x0, y0 = x0f.astype(np.int64), y0f.astype(np.int64)
    x1, y1 = x0 + 1, y0 + 1
    if wrap == "repeat":
        x0, x1, y0, y1 = x0 % W, x1 % W, y0 % H, y1 % H
    else:
        x0, x1 = np.clip(x0, 0, W - 1), np.clip(x1, 0, W - 1)
        y0, y1 = np.clip(y0, 0, H - 1), np.clip(y1, 0, H - 1)
    rows = np.stack([y0, y0, y1, y1], axis=1)
    cols = np.stack([x0, x1, x0, x1], axis=1)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    return rows, cols, w


def sample_map_bilinear(map_: np.ndarray, uv: np.ndarray, *, flip_v: bool = False, wrap: str = "repeat") -> np.ndarray:
    """Bilinear lookup of a map ``(H, W)`` or ``(H, W, C)`` at ``uv (N, 2)``; returns ``(N,)`` or ``(N, C)``.

    Same convention as Mitsuba's ``bitmap`` texture (see the module doc):
    ``uv = (0, 0)`` is row 0 (the top-left of the image); pass ``flip_v=True``
    for OpenGL/OBJ-style UVs whose ``(0, 0)`` is the bottom-left (row H-1).
    """
    m = np.asarray(map_)
    if m.ndim not in (2, 3):
        raise ValueError(f"map must be (H, W) or (H, W, C), got shape {m.shape}")
    rows, cols, w = bilinear_weights(uv, m.shape[:2], flip_v=flip_v, wrap=wrap)
    vals = m[rows, cols].astype(np.float64)  # (N, 4[, C])
    if m.ndim == 2:
        out = (vals * w).sum(axis=1)
    else:
        out = (vals * w[:, :, None]).sum(axis=1)
    return out.astype(np.result_type(m.dtype, np.float32)) if np.issubdtype(m.dtype, np.floating) else out


def welded_mean(prep: UVMesh, uv_values: np.ndarray) -> np.ndarray:
    """Average per-UV-vertex values ``(Nu,)``/``(Nu, C)`` over the copies of each welded vertex."""
    vals = np.asarray(uv_values, dtype=np.float64)
    idx = np.asarray(prep.uv_to_welded, dtype=np.int64)
    cnt = np.bincount(idx, minlength=prep.n_welded).astype(np.float64)
    cnt = np.maximum(cnt, 1.0)
    if vals.ndim == 1:
        return np.bincount(idx, weights=vals, minlength=prep.n_welded) / cnt
    return np.stack([np.bincount(idx, weights=vals[:, k], minlength=prep.n_welded) for k in range(vals.shape[1])],
                    axis=1) / cnt[:, None]


def sample_welded(prep: UVMesh, map_: np.ndarray, *, flip_v: bool = False, wrap: str = "repeat") -> np.ndarray:
    """Per-welded-vertex value of a UV map: mean of the bilinear samples at the vertex's UV copies."""
    return welded_mean(prep, sample_map_bilinear(map_, prep.uvs, flip_v=flip_v, wrap=wrap))


def welded_sampling_matrix(prep: UVMesh, shape: tuple[int, int], *, flip_v: bool = False, wrap: str = "repeat"):
    """Sparse ``(Nw, H*W)`` CSR matrix ``S`` with ``S @ map.reshape(H*W, -1) == sample_welded(prep, map)``.

    Rows sum to 1. Handy for a differentiable displacement in torch
    (``torch.sparse_csr_tensor`` from ``S.indptr, S.indices, S.data``) and for
    scattering a gradient on the vertices back to the map (``S.T``).
    """
    from scipy.sparse import coo_matrix

    H, W = int(shape[0]), int(shape[1])
    rows, cols, w = bilinear_weights(prep.uvs, (H, W), flip_v=flip_v, wrap=wrap)
    idx = np.asarray(prep.uv_to_welded, dtype=np.int64)
    cnt = np.maximum(np.bincount(idx, minlength=prep.n_welded), 1).astype(np.float64)
    data = (w / cnt[idx][:, None]).ravel()
    r = np.repeat(idx, 4)
    c = (rows * W + cols).ravel()
    return coo_matrix((data, (r, c)), shape=(prep.n_welded, H * W)).tocsr()


def displace_welded(prep: UVMesh, d: np.ndarray | float) -> np.ndarray:
    """``v' = v + d n`` on the welded mesh; ``d`` scalar or ``(Nw,)``. Returns ``(Nw, 3)`` float32."""
    d = np.asarray(d, dtype=np.float64)
    if d.ndim == 0:
        d = np.full(prep.n_welded, float(d))
    if d.shape != (prep.n_welded,):
        raise ValueError(f"displacement must have shape ({prep.n_welded},) (one value per welded vertex), got {d.shape}")
    out = prep.vertices.astype(np.float64) + d[:, None] * prep.normals.astype(np.float64)
    return out.astype(np.float32)


def displace(prep: UVMesh, d: np.ndarray | float) -> np.ndarray:
    """Displaced UV-mesh positions ``(Nu, 3)``: :func:`displace_welded` gathered to the UV vertices,
    so every seam copy moves exactly like its welded vertex (no cracks)."""
    return displace_welded(prep, d)[prep.uv_to_welded]


# =========================================================================== prepare + cache


@dataclasses.dataclass(eq=False)
class PreparedMesh(UVMesh):
    """Output of :func:`prepare_mesh`: a :class:`UVMesh` plus where it came from.

    ``report``: the :func:`clean_mesh` report with ``remesh``, ``unwrap``,
    ``seconds`` and ``source`` entries added. ``transform``: (4, 4) float64,
    input coordinates -> prepared coordinates (normalisation). ``key``: cache
    key. ``cache_hit``: whether it was read from the cache.
    """

    report: dict = dataclasses.field(default_factory=dict)
    transform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    key: str = ""
    cache_hit: bool = False


_ARRAY_FIELDS = ("vertices", "faces", "normals", "uv_vertices", "uv_faces", "uvs", "uv_to_welded")


def default_cache_dir() -> Path:
    """``$CAMO_CACHE/meshes`` when ``CAMO_CACHE`` is set, else ``~/.cache/camo/meshes``."""
    root = os.environ.get("CAMO_CACHE")
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "camo"
    return base / "meshes"


_CODE_DIGEST: str | None = None


def _code_digest() -> str:
    global _CODE_DIGEST
    if _CODE_DIGEST is None:
        try:
            _CODE_DIGEST = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:16]
        except OSError:  # pragma: no cover - frozen installs
            _CODE_DIGEST = "unknown"
    return _CODE_DIGEST


def _xatlas_version() -> str:
    try:
        from importlib.metadata import version

        return version("xatlas")
    except Exception:
        return "unknown"


def _cache_key(v: np.ndarray, f: np.ndarray, params: Mapping[str, Any]) -> str:
    h = hashlib.sha256()
    meta = {"format": CACHE_FORMAT, "code": _code_digest(), "xatlas": _xatlas_version(), **params}
    h.update(json.dumps(meta, sort_keys=True).encode())
    h.update(np.ascontiguousarray(v, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(f, dtype="<i8").tobytes())
    return h.hexdigest()[:32]


def _read_cache(path: Path, key: str) -> PreparedMesh | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            arrays = {name: np.array(z[name]) for name in _ARRAY_FIELDS}
            report = json.loads(str(z["report"]))
            transform = np.array(z["transform"], dtype=np.float64)
    except Exception:
        return None
    nw, nu = len(arrays["vertices"]), len(arrays["uv_vertices"])
    ok = (
        arrays["vertices"].shape == (nw, 3) and arrays["normals"].shape == (nw, 3)
        and arrays["uv_vertices"].shape == (nu, 3) and arrays["uvs"].shape == (nu, 2)
        and arrays["uv_to_welded"].shape == (nu,) and arrays["faces"].ndim == 2 and arrays["faces"].shape[1] == 3
        and arrays["uv_faces"].shape == arrays["faces"].shape and transform.shape == (4, 4)
        and nw > 0 and len(arrays["faces"]) > 0
        and arrays["faces"].min() >= 0 and arrays["faces"].max() < nw
        and arrays["uv_faces"].min() >= 0 and arrays["uv_faces"].max() < nu
        and arrays["uv_to_welded"].min() >= 0 and arrays["uv_to_welded"].max() < nw
        and all(np.isfinite(arrays[k]).all() for k in ("vertices", "normals", "uv_vertices", "uvs"))
        and isinstance(report, dict)
    )
    if not ok:
        return None
    atlas = {k: v for k, v in report.get("unwrap", {}).items() if k in ("charts", "atlas_width", "atlas_height",
                                                                      "dropped_faces", "dropped_vertices")}
    return PreparedMesh(**arrays, atlas=atlas, report=report, transform=transform, key=key, cache_hit=True)


def _write_cache(path: Path, prep: PreparedMesh) -> None:
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh, key=np.array(prep.key), report=np.array(json.dumps(prep.report)),
                    transform=prep.transform, **{k: getattr(prep, k) for k in _ARRAY_FIELDS},
                )
    except OSError as exc:
        warnings.warn(f"could not write the mesh cache {path}: {_one_line(exc)}", RuntimeWarning, stacklevel=3)


def prepare_mesh(
    path_or_mesh,
    target_vertices: int = DEFAULT_TARGET_VERTICES,
    size: float = 1.0,
    cache_dir: str | os.PathLike | None = None,
    *,
    tol: float = 0.15,
    use_cache: bool = True,
    decimator: str = "auto",
    unwrap_options: Mapping[str, Any] | None = None,
) -> PreparedMesh:
    """load -> clean -> normalise -> remesh -> UV-unwrap, cached on disk.

    ``path_or_mesh``: a file path (see :data:`SUPPORTED_EXTENSIONS`) or a
    ``trimesh.Trimesh``. ``target_vertices``: welded vertex count (the paper
    uses about 30,000; the result is within ``+-tol``, normally exact).
    ``size``: largest bounding-box side after normalisation. The cache key
    hashes the input vertex and face arrays, every parameter, this module's
    source and the xatlas version; ``cache_dir`` defaults to
    :func:`default_cache_dir`; a corrupt cache file is rebuilt.
    """
    trimesh = _trimesh()
    if isinstance(path_or_mesh, (str, os.PathLike)):
        source = str(path_or_mesh)
        mesh = load_mesh(path_or_mesh)
    elif isinstance(path_or_mesh, trimesh.Trimesh):
        source = "<trimesh>"
        mesh = path_or_mesh
    else:
        raise CamoError(f"prepare_mesh needs a mesh file path or a trimesh.Trimesh, got {type(path_or_mesh).__name__}")
    v_in = np.asarray(mesh.vertices, dtype=np.float64)
    f_in = np.asarray(mesh.faces, dtype=np.int64)
    if f_in.size == 0:
        raise CamoError(f"mesh {source} has no triangles")
    uopts = {**DEFAULT_UNWRAP_OPTIONS, **dict(unwrap_options or {})}
    unknown = set(uopts) - set(DEFAULT_UNWRAP_OPTIONS) - {"isolate", "timeout"}
    if unknown:
        raise CamoError(f"unknown unwrap option(s): {', '.join(sorted(unknown))}")
    method = _resolve_decimator(decimator)
    target = _check_target(target_vertices, tol)
    if not isinstance(size, (int, float, np.integer, np.floating)) or not np.isfinite(size) or size <= 0:
        raise CamoError(f"object size must be a positive number, got {size!r}")
    params = {
        "target_vertices": target,
        "size": float(size), "tol": float(tol), "decimator": method,
        "unwrap": {k: uopts[k] for k in DEFAULT_UNWRAP_OPTIONS},
    }
    key = _cache_key(v_in, f_in, params)
    cache_path = Path(cache_dir).expanduser() / f"{key}.npz" if cache_dir is not None else default_cache_dir() / f"{key}.npz"
    if use_cache and cache_path.exists():
        hit = _read_cache(cache_path, key)
        if hit is not None:
            hit.report["source"] = source
            return hit

    t0 = time.perf_counter()
    cleaned, report = clean_mesh(mesh)
    t1 = time.perf_counter()
    normed, T1 = normalise(cleaned, size)
    remeshed, info = _remesh(normed, target, tol, method)
    # decimation can create slivers/duplicates; refinement never does
    rv, rf, post = _clean_arrays(remeshed.vertices, remeshed.faces, merge_tol=0.0)
    info["post_clean"] = post
    remeshed = trimesh.Trimesh(rv, rf, process=False)
    final, T2 = normalise(remeshed, size)  # decimation may move the bounds a little
    t2 = time.perf_counter()
    uvm = uv_unwrap(final, **{k: v for k, v in uopts.items()})
    t3 = time.perf_counter()
    report = dict(report)
    report["remesh"] = info
    report["unwrap"] = {**uvm.atlas, "uv_vertices": uvm.n_uv, "welded_vertices": uvm.n_welded,
                        "options": params["unwrap"]}
    report["seconds"] = {"clean": round(t1 - t0, 3), "remesh": round(t2 - t1, 3), "unwrap": round(t3 - t2, 3)}
    report["source"] = source
    prep = PreparedMesh(
        **{k: getattr(uvm, k) for k in _ARRAY_FIELDS}, atlas=uvm.atlas,
        report=report, transform=T2 @ T1, key=key, cache_hit=False,
    )
    if use_cache:
        _write_cache(cache_path, prep)
    return prep
