"""Mesh preparation, step 2: cleaning (merged duplicate vertices, degenerate and duplicate faces dropped, outward
winding), normalising to the scene frame, and area-weighted vertex normals."""

from __future__ import annotations

import numpy as np

from camo_base.errors import CamoError
from optimizer.scenes.mesh.load import _one_line, _trimesh

#: relative (to the bounding-box diagonal) distance under which vertices are merged
MERGE_TOLERANCE = 1e-6


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
