"""Mesh preparation, step 4: the UV atlas (xatlas, isolated in a child process), the welded and UV-split meshes
(:class:`UVMesh`), and sampling UV maps at the welded vertices (the displacement). Conventions: the package doc."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from camo_base.atomic import atomic_path
from camo_base.errors import CamoError
from optimizer.scenes.mesh.clean import vertex_normals
from optimizer.scenes.mesh.load import _trimesh

#: default xatlas settings; ``max_chart_area_fraction`` bounds every chart's
#: area by this fraction of the surface area, which keeps xatlas fast
#: (chart growing and LSCM scale badly with chart size)
DEFAULT_UNWRAP_OPTIONS: dict[str, Any] = {
    "max_chart_area_fraction": 1.0 / 32.0,
    "padding": 4,
    "resolution": 0,
    "max_iterations": 1,
}


_XATLAS_WORKER = r"""
import json, sys
import numpy as np
from optimizer.scenes.mesh.uv import _xatlas_in_process
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
            root = str(Path(__file__).resolve().parents[3])  # the child imports this module
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
