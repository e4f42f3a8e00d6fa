"""Mitsuba scene assembly: environment + object + sensors + integrator.

All builders return *fresh* dicts or objects (a dict holding an ``mi.TensorXf``
is consumed by ``mi.load_dict``). The object is an ``mi.Mesh`` built from NumPy
arrays (world-space vertices, faces, UVs) so the optimiser can overwrite its
vertex buffer through ``mi.traverse``.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from optimizer.scenes.bsdf_maps import MAPS
from optimizer.scenes.cameras import Camera

OBJECT_ID = "object"

def effective_roughness(r):
    """The rendered roughness of map value ``r`` (the safe minimum :data:`~optimizer.scenes.bsdf_maps.ROUGHNESS_MIN`
    applied; :meth:`~optimizer.scenes.bsdf_maps.BsdfMap.rendered` of the roughness map)."""
    return MAPS["roughness"].rendered(r)


def texture(value, raw: bool = True) -> dict:
    """A Mitsuba texture dict from a scalar, an RGB triple, or a map ``(H, W)`` / ``(H, W, C)``."""
    import mitsuba as mi

    if isinstance(value, mi.TensorXf):
        return {"type": "bitmap", "data": value, "raw": raw, "filter_type": "bilinear", "wrap_mode": "clamp"}
    arr = np.asarray(value, dtype=np.float32)
    if arr.ndim == 0:
        return {"type": "rgb", "value": [float(arr)] * 3} if not raw else float(arr)
    if arr.ndim == 1:
        return {"type": "rgb", "value": [float(x) for x in arr]}
    if arr.ndim == 2:
        arr = arr[..., None]
    return {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(arr)), "raw": raw,
            "filter_type": "bilinear", "wrap_mode": "clamp"}


def principled(maps: Mapping[str, Any], eta: float = 1.5) -> dict:
    """Principled BSDF dict of the BSDF maps' values (``{name: value}`` for every map of
    :data:`~optimizer.scenes.bsdf_maps.MAPS`; each a scalar, an RGB triple, a NumPy map or an ``mi.TensorXf``), as
    *map values*: a map's rendered value (the roughness' safe minimum) is applied here, for constants and maps."""
    import mitsuba as mi

    d: dict[str, Any] = {"type": "principled"}
    for name, m in MAPS.items():
        v = maps[name]
        if not isinstance(v, mi.TensorXf):
            v = np.asarray(v, dtype=np.float32)
        d[m.principled] = texture(m.rendered(v) if m.rendered_offset else v)
    d["eta"] = float(eta)
    return d


def object_mesh(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray | None, bsdf: dict | Any,
                name: str = OBJECT_ID, smooth: bool = True):
    """An ``mi.Mesh`` from world-space ``vertices (N, 3)``, ``faces (F, 3)``, ``uvs (N, 2)`` and a BSDF.

    With ``smooth``, Mitsuba recomputes area-weighted vertex normals from the
    positions whenever they change (differentiably).
    """
    import drjit as dr
    import mitsuba as mi

    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    mesh = mi.Mesh(name, int(len(vertices)), int(len(faces)), props=props,
                   has_vertex_normals=smooth, has_vertex_texcoords=uvs is not None)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(vertices, dtype=np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(faces, dtype=np.uint32).ravel())
    if uvs is not None:
        params["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uvs, dtype=np.float32).ravel())
    params.update()
    if smooth:
        mesh.recompute_vertex_normals()
    dr.eval()
    return mesh


def perspective(cam: Camera, spp: int = 16, film: bool = True, sample_border: bool = False,
                crop: tuple[int, int, int, int] | None = None) -> dict:
    """A perspective sensor of ``cam``; ``crop = (x0, y0, x1, y1)`` (pixels, end exclusive) renders only that window
    of the film (Mitsuba's crop window: same camera, fewer pixels)."""
    import mitsuba as mi

    d: dict[str, Any] = {
        "type": "perspective",
        "fov": float(cam.fov),
        "fov_axis": "x",
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "to_world": mi.ScalarTransform4f().look_at(origin=list(cam.origin), target=list(cam.target), up=list(cam.up)),
    }
    if film:
        d["film"] = hdrfilm(cam.width, cam.height, sample_border)
        if crop is not None:
            x0, y0, x1, y1 = (int(c) for c in crop)
            if not (0 <= x0 < x1 <= cam.width and 0 <= y0 < y1 <= cam.height):
                raise ValueError(f"crop {crop} is not a window of the {cam.width}x{cam.height} film")
            d["film"].update(crop_offset_x=x0, crop_offset_y=y0, crop_width=x1 - x0, crop_height=y1 - y0)
        d["sampler"] = {"type": "independent", "sample_count": int(spp)}
    return d


def hdrfilm(width: int, height: int, sample_border: bool = False) -> dict:
    """Box-filtered RGB film. ``sample_border`` lets geometry gradients see shapes entering the frame."""
    return {"type": "hdrfilm", "width": int(width), "height": int(height), "rfilter": {"type": "box"},
            "pixel_format": "rgb", "sample_border": bool(sample_border)}


def batch(cams: Sequence[Camera], spp: int = 16) -> dict:
    """One ``batch`` sensor holding every view side by side (film ``V * W`` wide)."""
    w, h = cams[0].width, cams[0].height
    if any((c.width, c.height) != (w, h) for c in cams):
        raise ValueError("all cameras of a batch need the same resolution")
    d: dict[str, Any] = {"type": "batch", "film": hdrfilm(w * len(cams), h),
                         "sampler": {"type": "independent", "sample_count": int(spp)}}
    for i, c in enumerate(cams):
        d[f"view_{i:03d}"] = perspective(c, film=False)
    return d


def build_scene(elements: dict[str, Any], obj=None, sensors: Sequence[dict] = (), integrator: dict | None = None):
    """Load a scene from environment elements, an optional object mesh, sensors and an integrator."""
    import mitsuba as mi

    d: dict[str, Any] = {"type": "scene", **elements}
    if obj is not None:
        d[OBJECT_ID] = obj
    for i, s in enumerate(sensors):
        d[f"sensor_{i:03d}"] = s
    if integrator is not None:
        d["integrator"] = integrator
    return mi.load_dict(d)
