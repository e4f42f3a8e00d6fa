"""Mesh preparation, step 3: remeshing to a target vertex count (edge splits up, quadric or clustering decimation
down), as the paper does (about 30,000 vertices, Sec. IV-A)."""

from __future__ import annotations

from typing import Any

import numpy as np

from camo_base.errors import CamoError
from optimizer.scenes.mesh.clean import _clean_arrays, _edge_keys, _edges_with_counts, vertex_normals
from optimizer.scenes.mesh.load import _trimesh

#: vertex count of the prepared (welded) mesh, as in the paper (Sec. IV-A)
DEFAULT_TARGET_VERTICES = 30_000

#: a dense mesh is decimated to this fraction of the target, then split up to
#: the target, so large flat triangles left by the decimation get refined too
DECIMATE_FRACTION = 0.7


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
