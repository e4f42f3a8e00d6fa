"""Mesh preparation, step 1: reading a mesh file (OBJ, PLY, STL, GLB, GLTF, OFF) into one triangle mesh."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from camo_base.errors import CamoError

#: file extensions :func:`load_mesh` reads (lower case)
SUPPORTED_EXTENSIONS: tuple[str, ...] = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")


def _trimesh():
    import trimesh

    return trimesh


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    msg = text[0] if text else ""
    return (msg[:200] or type(exc).__name__)


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
