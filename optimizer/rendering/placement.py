"""The object of a scene pack: its prepared mesh and its placement in the scene (T_orig = T_t R S)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from optimizer.rendering import scene as scn
from optimizer.scenes.bsdf_maps import material_values
from optimizer.scenes.pose import model_matrix, transform_points
from optimizer.scenes.scenepack import MaterialSpec, ScenePack


def prepare_object(pack: ScenePack, target_vertices: int | None = None):
    """Load (or build), clean, normalise, remesh and UV-unwrap the pack's object (cached by content)."""
    from optimizer.scenes.mesh import prepare_mesh
    from optimizer.scenes.primitives import make_primitive

    o = pack.object
    src = make_primitive(o.primitive) if o.primitive else o.mesh
    return prepare_mesh(src, target_vertices=target_vertices or o.target_vertices, size=1.0)


def placed_vertices(pack: ScenePack, prepared) -> np.ndarray:
    """World-space positions ``(Nu, 3)`` of the UV-split mesh at ``T_orig``."""
    o = pack.object
    m = model_matrix(o.size, o.rotation, o.translation)
    return transform_points(m, prepared.vertices[prepared.uv_to_welded].astype(np.float64)).astype(np.float32)


def static_object_fn(pack: ScenePack, prepared, material: MaterialSpec | None = None) -> Callable:
    """A function building the object mesh with the pack's constant initial material."""
    mat = material or pack.material
    verts = placed_vertices(pack, prepared)

    def build():
        bsdf = scn.principled(material_values(mat), mat.eta)
        return scn.object_mesh(verts, prepared.uv_faces, prepared.uvs, bsdf)

    return build
