"""Write a Mitsuba 3 XML scene (``scene.xml``) that renders the same image as our in-memory scene.

:func:`write_scene_xml` serialises the scene-element dicts that :mod:`optimizer.scenes.environments`
and :mod:`optimizer.rendering.scene` build (plugin dicts with ``"type"``), the object (a PLY written by
:func:`optimizer.assets.export.write_ply` plus its BSDF dict), the sensors and the integrator.

Mapping of dict values to XML (Mitsuba 3 syntax, checked by loading with ``mi.load_file``):

=====================================  ==========================================================
``{"type": plugin, ...}``              ``<shape|bsdf|texture|emitter|sensor|film|sampler|rfilter|
                                       integrator|medium|phase|volume type=...>``: the tag comes
                                       from Mitsuba's plugin registry (``PluginManager.plugin_type``),
                                       else from the property name / a list of Python plugins
``{"type": "rgb", "value": v}``        ``<rgb name=... value="r g b"/>``
``{"type": "ref", "id": x}``           ``<ref id="x" name=.../>``
``bool`` / ``int`` / ``float`` / ``str``  ``<boolean>`` / ``<integer>`` / ``<float>`` / ``<string>``
3-vector (list, tuple, array)          ``<point>`` for position-like names (``p0``, ``p1``,
                                       ``center``, ``origin``, ``target``, ``up``, ``position``),
                                       else ``<vector>``
``ScalarTransform4f``                  ``<transform name=...><matrix value="16 row-major"/></transform>``
``ScalarTransform3f`` (``to_uv``)      the 2-D affine map embedded in a 4x4 matrix (Mitsuba drops
                                       the translation of a 9-value ``<matrix>``)
bitmap ``"data": mi.TensorXf``         saved as float EXR under ``textures/``, referenced by
                                       ``<string name="filename" value="textures/....exr"/>``
                                       (``raw``, ``filter_type``, ``wrap_mode``, ``to_uv`` kept)
``"bitmap": mi.Bitmap`` (``envmap``)   saved as EXR, referenced by ``filename``
=====================================  ==========================================================

Identical textures are written once (content hash). Floats are written with Python's
shortest round-trip ``repr`` so the XML scene reproduces the dict scene bit for bit.

Elements that are already *instantiated* Mitsuba objects (a user's XML environment: its
shapes and emitters are loaded objects) cannot be turned back into XML: a
:class:`~camo_base.errors.CamoError` names the element.

All files are written atomically.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
from pathlib import Path
from typing import Any, Sequence
from xml.sax.saxutils import quoteattr

import numpy as np

from camo_base import atomic
from camo_base.errors import CamoError
from optimizer.rendering.scene import OBJECT_ID

#: Property names whose 3-vectors are points (``<point>``); others become ``<vector>``.
POINT_NAMES = frozenset({"p0", "p1", "center", "origin", "target", "up", "position"})

#: Plugins implemented in Python (unknown to the C++ registry) and their XML tag.
PYTHON_PLUGINS = {
    "prb": "integrator", "prb_basic": "integrator", "prb_reparam": "integrator",
    "prb_projective": "integrator", "direct_projective": "integrator", "direct_reparam": "integrator",
    "camo_prb_projective": "integrator", "camo_direct_projective": "integrator",
    "emission_reparam": "integrator", "prbvolpath": "integrator",
}

#: Property names that tell the tag of a nested plugin when the registry does not.
NAME_TAGS = {
    "bsdf": "bsdf", "emitter": "emitter", "film": "film", "sampler": "sampler", "rfilter": "rfilter",
    "integrator": "integrator", "interior": "medium", "exterior": "medium", "medium": "medium",
    "phase": "phase", "sensor": "sensor",
}

_TYPE_TAGS = {
    "shape": "shape", "bsdf": "bsdf", "texture": "texture", "emitter": "emitter", "sensor": "sensor",
    "film": "film", "sampler": "sampler", "reconstructionfilter": "rfilter", "integrator": "integrator",
    "medium": "medium", "phasefunction": "phase", "volume": "volume",
}

TEXTURES_DIR = "textures"


def _fmt(x: float) -> str:
    x = float(x)
    if not math.isfinite(x):
        raise CamoError(f"scene.xml: non-finite number {x}")
    r = repr(x)
    return r[:-2] if r.endswith(".0") else r


def _tag_for(plugin: str, key: str, where: str) -> str:
    import mitsuba as mi

    try:
        kind = str(mi.PluginManager.instance().plugin_type(plugin)).split(".")[-1].lower()
    except Exception:
        kind = "unknown"
    if kind in _TYPE_TAGS:
        return _TYPE_TAGS[kind]
    if plugin in PYTHON_PLUGINS:
        return PYTHON_PLUGINS[plugin]
    if key in NAME_TAGS:
        return NAME_TAGS[key]
    raise CamoError(f"scene.xml: cannot tell what kind of Mitsuba plugin {plugin!r} is ({where})")


def _is_transform(v: Any) -> bool:
    return "Transform" in type(v).__name__ and hasattr(v, "matrix")


def _is_mitsuba_object(v: Any) -> bool:
    mod = type(v).__module__ or ""
    return (mod.startswith("mitsuba") or mod.startswith("drjit")) and not _is_transform(v)


def _is_vector_like(v: Any) -> bool:
    """Lists, tuples, NumPy arrays and Dr.Jit/Mitsuba scalar 3-arrays (not tensors or objects)."""
    if isinstance(v, (list, tuple, np.ndarray)):
        return True
    name = type(v).__name__
    return _is_mitsuba_object(v) and any(s in name for s in ("Array3", "Point3", "Vector3", "Normal3", "Color3"))


def _vector3(v: Any) -> list[float] | None:
    if isinstance(v, (str, bytes, dict)):
        return None
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return [float(x) for x in a.ravel()] if a.size == 3 and a.ndim <= 2 else None


class _Writer:
    def __init__(self, xml_dir: Path, textures_dir: str) -> None:
        self.xml_dir = xml_dir
        self.textures_dir = textures_dir
        self.lines: list[str] = []
        self.files: dict[str, str] = {}  # content hash -> relative file name
        self.names: set[str] = set()
        self.pending: list[tuple[str, np.ndarray]] = []  # (relative file name, image) to write

    # -- helpers ------------------------------------------------------------

    def emit(self, depth: int, text: str) -> None:
        self.lines.append("    " * depth + text)

    def save_image(self, arr: np.ndarray, where: str) -> str:
        """Queue a float image as an EXR under ``textures/``; returns its path relative to the XML."""
        a = np.ascontiguousarray(np.asarray(arr, dtype=np.float32))
        if a.ndim == 3 and a.shape[2] == 1:
            a = a[..., 0]
        if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
            raise CamoError(f"scene.xml: {where}: only 1- or 3-channel images can be saved, got shape {a.shape}")
        h = hashlib.sha256(str(a.shape).encode() + a.tobytes()).hexdigest()
        if h in self.files:
            return self.files[h]
        base = re.sub(r"[^A-Za-z0-9_.-]+", "_", where).strip("._") or "texture"
        name, i = base, 1
        while name in self.names:
            i += 1
            name = f"{base}_{i}"
        self.names.add(name)
        rel = f"{self.textures_dir}/{name}.exr"
        self.pending.append((rel, a))
        self.files[h] = rel
        return rel

    # -- values -------------------------------------------------------------

    def transform(self, depth: int, name: str, t: Any) -> None:
        m = np.asarray(t.matrix, dtype=np.float64)
        if m.ndim == 3 and m.shape[2] == 1:  # a vectorised transform of width 1 (e.g. from mi.traverse)
            m = m[..., 0]
        if m.shape == (3, 3):  # 2-D affine (to_uv): embed in 4x4, as Mitsuba converts it back
            m4 = np.eye(4)
            m4[:2, :2] = m[:2, :2]
            m4[:2, 3] = m[:2, 2]
            m = m4
        if m.shape != (4, 4):
            raise CamoError(f"scene.xml: transform {name!r} has an unsupported shape {m.shape}")
        vals = " ".join(_fmt(x) for x in m.ravel())
        self.emit(depth, f'<transform name={quoteattr(name)}>')
        self.emit(depth + 1, f'<matrix value="{vals}"/>')
        self.emit(depth, "</transform>")

    def prop(self, depth: int, key: str, value: Any, where: str) -> None:
        here = f"{where}.{key}"
        if isinstance(value, dict):
            typ = value.get("type")
            if typ == "rgb":
                val = value.get("value")
                vec = _vector3(val)
                if vec is None:
                    if isinstance(val, (int, float, np.number)):
                        vec = [float(val)] * 3
                    else:
                        raise CamoError(f"scene.xml: {here}: rgb value must be 3 numbers, got {val!r}")
                self.emit(depth, f'<rgb name={quoteattr(key)} value="{" ".join(_fmt(x) for x in vec)}"/>')
            elif typ == "spectrum" and isinstance(value.get("value"), (int, float, np.number)):
                self.emit(depth, f'<spectrum name={quoteattr(key)} value="{_fmt(value["value"])}"/>')
            elif typ == "ref":
                self.emit(depth, f'<ref id={quoteattr(str(value["id"]))} name={quoteattr(key)}/>')
            elif typ is not None:
                self.plugin(depth, key, value, where, top=False)
            else:
                raise CamoError(f"scene.xml: {here}: a nested dict needs a 'type'")
        elif _is_transform(value):
            self.transform(depth, key, value)
        elif isinstance(value, (bool, np.bool_)):
            self.emit(depth, f'<boolean name={quoteattr(key)} value="{"true" if value else "false"}"/>')
        elif isinstance(value, (int, np.integer)):
            self.emit(depth, f'<integer name={quoteattr(key)} value="{int(value)}"/>')
        elif isinstance(value, (float, np.floating)):
            self.emit(depth, f'<float name={quoteattr(key)} value="{_fmt(value)}"/>')
        elif isinstance(value, str):
            self.emit(depth, f'<string name={quoteattr(key)} value={quoteattr(value)}/>')
        elif isinstance(value, os.PathLike):
            self.emit(depth, f'<string name={quoteattr(key)} value={quoteattr(os.fspath(value))}/>')
        else:
            vec = _vector3(value) if _is_vector_like(value) else None
            if vec is not None:
                tag = "point" if key in POINT_NAMES else "vector"
                self.emit(depth, f'<{tag} name={quoteattr(key)} x="{_fmt(vec[0])}" y="{_fmt(vec[1])}" z="{_fmt(vec[2])}"/>')
            elif _is_mitsuba_object(value):
                raise CamoError(
                    f"scene.xml: {here} is an instantiated Mitsuba {type(value).__name__}, which cannot be "
                    "written to XML (only plugin dicts can)")
            else:
                raise CamoError(f"scene.xml: {here}: cannot write a value of type {type(value).__name__}")

    def plugin(self, depth: int, key: str, d: dict, where: str, top: bool) -> None:
        plugin = str(d["type"])
        here = f"{where}.{key}" if where else key
        tag = _tag_for(plugin, key, here)
        ident = str(d.get("id", key))
        attr = f"id={quoteattr(ident)}" if top else f"name={quoteattr(key)}"
        if not top and "id" in d:
            attr += f" id={quoteattr(ident)}"
        self.emit(depth, f"<{tag} type={quoteattr(plugin)} {attr}>")
        for k, v in d.items():
            if k in ("type", "id"):
                continue
            if plugin == "bitmap" and k == "data":
                rel = self.save_image(np.asarray(v), here)
                self.emit(depth + 1, f'<string name="filename" value={quoteattr(rel)}/>')
            elif k == "bitmap" and type(v).__name__ == "Bitmap":
                rel = self.save_image(np.asarray(v), here)
                self.emit(depth + 1, f'<string name="filename" value={quoteattr(rel)}/>')
            else:
                self.prop(depth + 1, k, v, here)
        self.emit(depth, f"</{tag}>")

    def element(self, key: str, value: Any) -> None:
        if isinstance(value, dict) and "type" in value:
            self.plugin(1, key, value, "", top=True)
            self.lines.append("")
        elif _is_mitsuba_object(value):
            raise CamoError(
                f"scene.xml: scene element {key!r} is an instantiated Mitsuba {type(value).__name__} "
                "(e.g. from a user XML environment) and cannot be written to XML; "
                "scene.xml is only available for built-in and panorama environments")
        else:
            raise CamoError(f"scene.xml: scene element {key!r} is not a Mitsuba plugin dict "
                            f"(got {type(value).__name__})")


def scene_xml_string(xml_dir: str | os.PathLike, elements: dict[str, Any], obj_ply: str | os.PathLike | None,
                     obj_bsdf: dict | None, sensors: Sequence[dict], integrator: dict | None, *,
                     obj_id: str = OBJECT_ID, face_normals: bool = False,
                     textures_dir: str = TEXTURES_DIR) -> tuple[str, list[tuple[str, np.ndarray]]]:
    """The XML text of :func:`write_scene_xml` and the images it references
    (``[(path relative to xml_dir, float32 array)]``); writes nothing."""
    xml_dir = Path(xml_dir)
    w = _Writer(xml_dir, textures_dir)
    w.lines += ['<?xml version="1.0" encoding="utf-8"?>',
                "<!-- written by camo (optimizer.assets.scene_xml); textures are linear float EXRs -->",
                '<scene version="3.0.0">']
    for key, value in elements.items():
        w.element(str(key), value)
    if obj_ply is not None:
        ply = Path(obj_ply)
        try:
            rel = os.path.relpath(ply.resolve(), xml_dir.resolve())
        except ValueError:  # other drive (Windows)
            rel = str(ply.resolve())
        rel = rel.replace(os.sep, "/")
        w.emit(1, f'<shape type="ply" id={quoteattr(obj_id)}>')
        w.emit(2, f'<string name="filename" value={quoteattr(rel)}/>')
        w.emit(2, f'<boolean name="face_normals" value="{"true" if face_normals else "false"}"/>')
        if obj_bsdf is not None:
            if not isinstance(obj_bsdf, dict):
                raise CamoError(f"scene.xml: the object's BSDF is an instantiated Mitsuba "
                                f"{type(obj_bsdf).__name__}; pass the BSDF dict instead")
            w.plugin(2, "bsdf", obj_bsdf, obj_id, top=False)
        w.emit(1, "</shape>")
    elif obj_bsdf is not None:
        raise ValueError("obj_bsdf given without obj_ply")
    for i, s in enumerate(sensors):
        w.element(f"sensor_{i:03d}", s)
    if integrator is not None:
        w.element("integrator", integrator)
    w.lines.append("</scene>")
    return "\n".join(w.lines) + "\n", w.pending


def write_scene_xml(path: str | os.PathLike, elements: dict[str, Any], obj_ply: str | os.PathLike | None,
                    obj_bsdf: dict | None, sensors: Sequence[dict], integrator: dict | None, *,
                    obj_id: str = OBJECT_ID, face_normals: bool = False, textures_dir: str = TEXTURES_DIR) -> Path:
    """Write a Mitsuba 3 XML scene at ``path``; textures go to ``<dir of path>/textures/*.exr``.

    ``elements``: environment elements (``{id: plugin dict}``, as ``Environment.build()``
    returns them); ``obj_ply``: the object's PLY (:func:`optimizer.assets.export.write_ply`),
    referenced relative to the XML, as shape ``obj_id`` with ``obj_bsdf`` (a BSDF dict, e.g.
    :func:`optimizer.rendering.scene.principled`; its bitmaps become EXRs); ``sensors``: sensor dicts
    (``perspective`` or ``batch``, with film and sampler), written in order as
    ``sensor_000``, ...; ``integrator``: the integrator dict. ``face_normals`` must match
    how the in-memory object was built (``object_mesh(smooth=True)`` -> False).

    Elements are written in :func:`optimizer.rendering.scene.build_scene`'s order (environment, object,
    sensors, integrator), so ``mi.load_file`` builds the same scene (same shape and emitter
    order, hence the same random-number use: renders agree bit for bit with the same seed).
    Raises :class:`CamoError` for elements that cannot be serialised, before writing anything.
    """
    from camo_base.imaging import save_exr

    path = Path(path)
    text, images = scene_xml_string(path.parent, elements, obj_ply, obj_bsdf, sensors, integrator, obj_id=obj_id,
                                    face_normals=face_normals, textures_dir=textures_dir)
    for rel, img in images:  # only once the whole scene is known to serialise
        save_exr(path.parent / rel, img)
    atomic.write_text(path, text)
    return path
