"""Mesh preparation: load -> clean -> normalise -> remesh -> UV-unwrap, with an on-disk cache, one module per role:
:mod:`.load` (files), :mod:`.clean` (clean, normalise, normals), :mod:`.remesh`, :mod:`.uv` (atlas, welded and UV
meshes, sampling), :mod:`.cache` (:func:`prepare_mesh` and its cache). The names below are their public API.

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
input vertex/face arrays, the parameters, the source of this package and the
xatlas version. Files are written atomically; an unreadable or inconsistent
cache file is ignored and rebuilt.

Supported input formats: OBJ, PLY, STL, GLB, GLTF, OFF (scenes are flattened
into one mesh with their node transforms).
"""

from optimizer.scenes.mesh.cache import PreparedMesh, default_cache_dir, prepare_mesh
from optimizer.scenes.mesh.clean import clean_mesh, normalise, vertex_normals
from optimizer.scenes.mesh.load import SUPPORTED_EXTENSIONS, load_mesh
from optimizer.scenes.mesh.remesh import DEFAULT_TARGET_VERTICES, remesh_to_target
from optimizer.scenes.mesh.uv import (UVMesh, bilinear_weights, displace, displace_welded, sample_map_bilinear,
                                     sample_welded, uv_unwrap, welded_mean, welded_sampling_matrix)

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
