"""Textured assets as the renderer needs them: read a glTF 2.0 / GLB or OBJ + MTL file (any method's result) or
the mesh and maps of a run directory (:mod:`optimizer.assets.rundir`), and place it in a scene.

One representation, :class:`Asset`, whatever the source:

* ``vertices (N, 3)`` float32 (Z-up, scene units once placed), ``faces (F, 3)`` int64, ``uvs (N, 2)`` float32 in
  **Mitsuba's convention** (``v = 0`` is the top row of the texture image; see :mod:`optimizer.assets.export`) or None;
* ``maps``: the material **as rendered**: ``albedo`` linear RGB ``(H, W, 3)`` or ``(3,)``; ``metallic``,
  ``roughness`` (the rendered roughness, i.e. after :meth:`optimizer.scenes.bsdf_maps.BsdfMap.rendered` for the
  optimiser's maps) and ``transmittance`` ``(H, W, 1)`` or ``()``; all in [0, 1]. Maps may differ in size.
* ``eta`` (index of refraction), ``lambertian`` (the albedo-only ablation renders a diffuse BSDF), ``wrap``
  (texture wrap mode: ``clamp``, ``repeat`` or ``mirror``).

:meth:`Asset.values` returns the maps *as optimised* (roughness inverted once from the rendered value to the map
value ``r`` that :func:`optimizer.rendering.appearance.object_bsdf` and :func:`optimizer.rendering.scene.principled` take, which
apply ``r_min + (1 - r_min) r`` themselves), and :meth:`Asset.bsdf` the BSDF dict that renders exactly
``maps``.

Readers (:func:`load_asset`):

* **glTF 2.0 / GLB**: ``pbrMetallicRoughness`` (baseColor factor x sRGB texture; metallicRoughness texture G =
  roughness, B = metallic, times the factors), ``KHR_materials_transmission`` (factor x texture R),
  ``KHR_materials_ior``. Embedded (bufferView), ``data:`` and file images (PNG/JPEG); node transforms are applied
  and glTF's +Y up is turned +Z up, as :func:`optimizer.scenes.mesh.load_mesh` does. Several primitives are merged when
  they share one material.
* **OBJ + MTL**: ``Kd``/``map_Kd`` (sRGB image, times ``Kd``), ``Pr``/``map_Pr``, ``Pm``/``map_Pm`` (PBR-MTL
  keys); transmission from ``Ptr``/``map_Ptr`` (as :func:`optimizer.assets.export.write_obj` writes it), else ``Tf``
  (mean of the filter colour), else ``Tr``, else ``1 - d`` (``map_d``: ``1 - value``); ``Ni`` = eta. Without
  ``Pr``, roughness comes from ``Ns`` (``sqrt(2 / (Ns + 2))``, Blender's conversion). OBJ ``vt`` is OpenGL's
  (``v`` up) and is flipped to Mitsuba's. Positions are taken as Z-up (as :func:`optimizer.scenes.mesh.load_mesh`).

Unsupported features are one-line :class:`CamoError`\\ s: ``KHR_texture_transform`` (or MTL ``-o``/``-s``/``-t``),
vertex colours (``COLOR_0``, OBJ ``v x y z r g b``), a texture on a second UV set (``texCoord`` 1), a missing
texture file, several materials, non-triangle primitives, sparse accessors, required extensions not listed here.
Stated fallbacks (warnings in :attr:`Asset.warnings`, shown in the evaluation's output): an unused second UV set
is ignored; normal, occlusion and emissive maps and other ``KHR_materials_*`` extensions are ignored; base colour
alpha is ignored (rendered opaque; use transmission); mixed wrap modes use ``repeat``; a rendered roughness below
the renderer's safe minimum 0.035 renders at 0.035.

Placement (:func:`place`): ``"scene"`` keeps the asset's coordinates as scene coordinates (our own
``result.glb`` / ``result.obj`` hold the posed, displaced object in scene coordinates and say so); ``"pack"``
normalises the asset as a scene pack's mesh (largest side 1, centred in x/y, lowest point on z = 0) and applies
the pack's ``[object]`` pose (``size``, ``rotation``, ``translation``: ``T_orig`` of Eq. 2). ``"auto"`` is
``"scene"`` for files written by :mod:`optimizer.assets.export`, else ``"pack"``.
"""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import math
import struct
from pathlib import Path
import numpy as np

from camo_base.errors import CamoError
from optimizer.scenes.bsdf_maps import MAPS, gltf_extensions

#: Index of refraction when an asset gives none (glTF's KHR_materials_ior default).
DEFAULT_ETA = 1.5
#: glTF extensions this reader understands (an asset requiring any other one is refused).
#: Material extensions read: those the BSDF maps live in (``BsdfMap.gltf``) and the index of refraction.
SUPPORTED_GLTF_EXTENSIONS = (*gltf_extensions(), "KHR_materials_ior")
PLACEMENTS = ("auto", "scene", "pack")
ASSET_SUFFIXES = (".glb", ".gltf", ".obj")

_WRAP = {33071: "clamp", 10497: "repeat", 33648: "mirror"}
_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


@dataclasses.dataclass
class Asset:
    """A textured triangle mesh with a principled material (see the module docstring for units and shapes)."""

    source: str  # file or run directory it was read from
    vertices: np.ndarray  # (N, 3) float32
    faces: np.ndarray  # (F, 3) int64
    uvs: np.ndarray | None  # (N, 2) float32, Mitsuba convention
    maps: dict[str, np.ndarray]  # as rendered: albedo, metallic, roughness, transmittance
    eta: float = DEFAULT_ETA
    lambertian: bool = False
    wrap: str = "clamp"
    coordinates: str = "object"  # "scene" once placed (or when the file says it holds scene coordinates)
    warnings: list[str] = dataclasses.field(default_factory=list)
    coordinates_from: str = ""  # after place(): the placement used, "scene" or "pack"

    def values(self) -> dict[str, np.ndarray]:
        """The maps as optimised: a rendered value inverted once (the roughness' safe minimum), clipped to [0, 1]."""
        out = {k: np.clip(v, 0.0, 1.0).astype(np.float32) for k, v in self.maps.items()}
        for name, m in MAPS.items():
            if m.rendered_offset and name in self.maps:
                out[name], _ = map_values_from_rendered(self.maps[name], name)
        return out

    def bsdf(self) -> dict:
        """Mitsuba BSDF dict (fresh each call: ``mi.load_dict`` consumes tensors) that renders :attr:`maps`."""
        from optimizer.rendering import scene as scn

        v = self.values()
        if self.lambertian:
            d = {"type": "diffuse", "reflectance": scn.texture(v["albedo"])}
        else:
            d = scn.principled(v, self.eta)
        if self.wrap != "clamp":
            for t in d.values():
                if isinstance(t, dict) and t.get("type") == "bitmap":
                    t["wrap_mode"] = self.wrap
        return d

    def mesh(self):
        """A fresh ``mi.Mesh`` of the asset with its BSDF (smooth normals recomputed by Mitsuba)."""
        from optimizer.rendering import scene as scn

        return scn.object_mesh(self.vertices, self.faces, self.uvs, self.bsdf())


def map_values_from_rendered(rendered: np.ndarray, name: str = "roughness") -> tuple[np.ndarray, bool]:
    """Invert map ``name``'s rendered value (``r_min + (1 - r_min) r`` for the roughness) to the map value ``r``
    that ``object_bsdf`` / ``scene.principled`` take; returns ``(r, clipped)`` where ``clipped`` says a value lay
    outside ``[r_min, 1]``."""
    r = MAPS[name].from_rendered(rendered)
    clipped = bool((r < -1e-5).any() or (r > 1.0 + 1e-5).any())
    return np.clip(r, 0.0, 1.0).astype(np.float32), clipped


def check_maps(asset: Asset, label: str, where: str = "{label}: {name}") -> None:
    """Warn (in ``asset.warnings``) about maps outside the renderable range; NaN/inf is an error. ``where``
    formats a map's name in the messages (e.g. ``"{label}: maps/{name}.npy"``)."""
    for name, m in MAPS.items():
        at = where.format(label=label, name=name)
        if name not in asset.maps:
            raise CamoError(f"{label}: no {name} map")
        a = asset.maps[name]
        if not np.isfinite(a).all():
            raise CamoError(f"{at}: contains NaN or infinite values")
        lo = m.rendered_offset
        if lo and not asset.lambertian:
            if a.size and (a.min() < lo - 1e-5 or a.max() > 1 + 1e-5):
                asset.warnings.append(f"{at} lies outside the renderable range [{lo}, 1]; clipped")
        elif a.size and (a.min() < -1e-5 or a.max() > 1 + 1e-5):
            asset.warnings.append(f"{at} lies outside [0, 1]; clipped")


# --------------------------------------------------------------------------------------------------------------
# images
# --------------------------------------------------------------------------------------------------------------


def _decode_image(data: bytes, where: str) -> np.ndarray:
    """8/16-bit image bytes -> float32 ``(H, W, C)`` in [0, 1] (no transfer curve applied)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                a = np.asarray(im, dtype=np.float32) / 65535.0
            else:
                if im.mode not in ("L", "LA", "RGB", "RGBA"):
                    im = im.convert("RGBA" if "A" in im.getbands() else "RGB")
                a = np.asarray(im, dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise CamoError(f"{where}: cannot decode the texture image ({exc})") from None
    return a[..., None] if a.ndim == 2 else a


def _read_file(path: Path, what: str) -> bytes:
    if not path.is_file():
        raise CamoError(f"{what} not found: {path}")
    return path.read_bytes()


def _rgb(img: np.ndarray) -> np.ndarray:
    return np.repeat(img[..., :1], 3, axis=-1) if img.shape[-1] < 3 else img[..., :3]


def _srgb_to_linear(a: np.ndarray) -> np.ndarray:
    from camo_base.imaging import srgb_to_linear

    return np.asarray(srgb_to_linear(a), dtype=np.float32)


# --------------------------------------------------------------------------------------------------------------
# glTF 2.0 / GLB
# --------------------------------------------------------------------------------------------------------------


def _gltf_document(path: Path) -> tuple[dict, list[bytes]]:
    data = _read_file(path, "asset file")
    if path.suffix.lower() == ".glb" or data[:4] == b"glTF":
        if len(data) < 20 or data[:4] != b"glTF":
            raise CamoError(f"{path}: not a glTF binary (GLB)")
        version, total = struct.unpack_from("<II", data, 4)
        if version != 2:
            raise CamoError(f"{path}: glTF version {version}; only glTF 2.0 is supported")
        off, js, bin_ = 12, None, b""
        while off + 8 <= min(total, len(data)):
            length, kind = struct.unpack_from("<I4s", data, off)
            chunk = data[off + 8: off + 8 + length]
            if kind == b"JSON":
                js = chunk
            elif kind == b"BIN\x00" and not bin_:
                bin_ = chunk
            off += 8 + length
        if js is None:
            raise CamoError(f"{path}: GLB without a JSON chunk")
        text, embedded = js, bin_
    else:
        text, embedded = data, b""
    try:
        doc = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise CamoError(f"{path}: not valid glTF JSON ({exc})") from None
    if not isinstance(doc, dict) or str(doc.get("asset", {}).get("version", "")).split(".")[0] != "2":
        raise CamoError(f"{path}: not a glTF 2.0 document (asset.version must be 2.x)")
    buffers = []
    for i, b in enumerate(doc.get("buffers", [])):
        uri = b.get("uri")
        if uri is None:
            buffers.append(embedded)
        else:
            buffers.append(_uri_bytes(path, uri, f"buffer {i}"))
        if len(buffers[-1]) < int(b.get("byteLength", 0)):
            raise CamoError(f"{path}: buffer {i} is shorter than its byteLength")
    return doc, buffers


def _uri_bytes(path: Path, uri: str, what: str) -> bytes:
    if uri.startswith("data:"):
        try:
            return base64.b64decode(uri.split(",", 1)[1])
        except (IndexError, ValueError):
            raise CamoError(f"{path}: {what}: malformed data URI") from None
    from urllib.parse import unquote

    return _read_file(path.parent / unquote(uri), f"{path.name}: {what} file")


def _buffer_view(doc: dict, buffers: list[bytes], index: int, path: Path) -> tuple[bytes, int | None]:
    try:
        bv = doc["bufferViews"][index]
        buf = buffers[bv["buffer"]]
    except (KeyError, IndexError, TypeError):
        raise CamoError(f"{path}: bufferView {index} does not exist") from None
    off = int(bv.get("byteOffset", 0))
    return buf[off: off + int(bv["byteLength"])], bv.get("byteStride")


def _accessor(doc: dict, buffers: list[bytes], index: int, path: Path) -> np.ndarray:
    try:
        acc = doc["accessors"][index]
    except (KeyError, IndexError, TypeError):
        raise CamoError(f"{path}: accessor {index} does not exist") from None
    if "sparse" in acc:
        raise CamoError(f"{path}: sparse accessors are not supported (accessor {index})")
    dtype = np.dtype(_COMPONENT.get(acc.get("componentType"), np.float32)).newbyteorder("<")
    if acc.get("componentType") not in _COMPONENT:
        raise CamoError(f"{path}: accessor {index} has an unknown componentType {acc.get('componentType')}")
    n, count = _NCOMP.get(acc.get("type"), 0), int(acc["count"])
    if n == 0:
        raise CamoError(f"{path}: accessor {index} has an unsupported type {acc.get('type')!r}")
    if "bufferView" not in acc:
        out = np.zeros((count, n), dtype)
    else:
        data, stride = _buffer_view(doc, buffers, acc["bufferView"], path)
        off = int(acc.get("byteOffset", 0))
        item = dtype.itemsize * n
        stride = stride or item
        need = off + stride * (count - 1) + item if count else 0
        if need > len(data):
            raise CamoError(f"{path}: accessor {index} reads past the end of its bufferView")
        rows = np.frombuffer(data, np.uint8)[off:need]
        if stride == item:
            out = rows.view(dtype).reshape(count, n)
        else:
            idx = np.arange(count)[:, None] * stride + np.arange(item)[None, :]
            out = np.ascontiguousarray(rows[idx]).view(dtype).reshape(count, n)
    out = np.array(out)
    if acc.get("normalized") and dtype.kind in "iu":
        out = np.maximum(out.astype(np.float64) / np.iinfo(dtype).max, -1.0)
    return out


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    m = np.eye(4)
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m[:3, :3] = r * np.asarray(node.get("scale", (1.0, 1.0, 1.0)))[None, :]
    m[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return m


def _mesh_instances(doc: dict, path: Path) -> list[tuple[int, np.ndarray]]:
    """``[(mesh index, world matrix)]`` of the default scene (every node if there is no scene)."""
    nodes = doc.get("nodes", [])
    scenes = doc.get("scenes")
    if scenes:
        roots = scenes[int(doc.get("scene", 0))].get("nodes", [])
    else:
        children = {c for n in nodes for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    out, stack, seen = [], [(int(i), np.eye(4)) for i in roots], 0
    while stack:
        i, parent = stack.pop()
        seen += 1
        if seen > 100000 or i >= len(nodes):
            raise CamoError(f"{path}: malformed node hierarchy")
        node = nodes[i]
        m = parent @ _node_matrix(node)
        if "mesh" in node:
            out.append((int(node["mesh"]), m))
        stack.extend((int(c), m) for c in node.get("children", []))
    if not out and not nodes and doc.get("meshes"):
        out = [(i, np.eye(4)) for i in range(len(doc["meshes"]))]
    return out


def _texture_image(doc: dict, buffers: list[bytes], info: dict | None, path: Path, slot: str,
                   used_uv: set[int], wraps: set[str]) -> np.ndarray | None:
    if not info:
        return None
    if "KHR_texture_transform" in info.get("extensions", {}):
        raise CamoError(f"{path}: {slot} uses KHR_texture_transform, which is not supported; bake the transform into "
                        "the UVs or the image")
    used_uv.add(int(info.get("texCoord", 0)))
    try:
        tex = doc["textures"][int(info["index"])]
    except (KeyError, IndexError, TypeError):
        raise CamoError(f"{path}: {slot}: texture {info.get('index')} does not exist") from None
    src = tex.get("source")
    if src is None:
        raise CamoError(f"{path}: {slot}: the texture has no PNG/JPEG source (only KHR_texture_basisu or another "
                        "extension image); not supported")
    img = doc["images"][int(src)]
    if "bufferView" in img:
        data, _ = _buffer_view(doc, buffers, img["bufferView"], path)
    elif "uri" in img:
        data = _uri_bytes(path, img["uri"], f"{slot} texture image")
    else:
        raise CamoError(f"{path}: {slot}: image {src} has neither a bufferView nor a uri")
    sampler = doc.get("samplers", [])[tex["sampler"]] if "sampler" in tex else {}
    wraps.update({_WRAP.get(sampler.get("wrapS", 10497), "repeat"), _WRAP.get(sampler.get("wrapT", 10497), "repeat")})
    return _decode_image(data, f"{path}: {slot}")


def read_gltf(path: str | Path) -> Asset:
    """A glTF 2.0 / GLB asset in its own coordinates turned Z-up (see the module docstring)."""
    path = Path(path)
    doc, buffers = _gltf_document(path)
    required = set(doc.get("extensionsRequired", []))
    bad = sorted(required - set(SUPPORTED_GLTF_EXTENSIONS))
    if bad:
        raise CamoError(f"{path}: requires glTF extension(s) {', '.join(bad)}, which are not supported "
                        f"(supported: {', '.join(SUPPORTED_GLTF_EXTENSIONS)})")
    if "KHR_texture_transform" in doc.get("extensionsUsed", []):
        raise CamoError(f"{path}: uses KHR_texture_transform, which is not supported; bake the transform into the UVs "
                        "or the image")
    warnings: list[str] = []
    verts, faces, uvs0, uvs1, materials = [], [], [], [], set()
    base = 0
    for mesh_index, m in _mesh_instances(doc, path):
        try:
            prims = doc["meshes"][mesh_index]["primitives"]
        except (KeyError, IndexError, TypeError):
            raise CamoError(f"{path}: mesh {mesh_index} does not exist") from None
        for p in prims:
            mode = p.get("mode", 4)
            if mode != 4:
                raise CamoError(f"{path}: primitive mode {mode} (not triangles) is not supported")
            attrs = p.get("attributes", {})
            if "COLOR_0" in attrs:
                raise CamoError(f"{path}: vertex colours (COLOR_0) are not supported; bake them into the "
                                "baseColorTexture")
            if "POSITION" not in attrs:
                raise CamoError(f"{path}: a primitive has no POSITION")
            pos = _accessor(doc, buffers, attrs["POSITION"], path).astype(np.float64)[:, :3]
            pos = (np.c_[pos, np.ones(len(pos))] @ m.T)[:, :3]
            if np.linalg.det(m[:3, :3]) < 0:
                warnings.append(f"{path.name}: a node mirrors its mesh; faces re-wound")
            idx = _accessor(doc, buffers, p["indices"], path).astype(np.int64).reshape(-1) if "indices" in p \
                else np.arange(len(pos))
            if idx.size % 3 or (idx.size and (idx.min() < 0 or idx.max() >= len(pos))):
                raise CamoError(f"{path}: a primitive's indices are not triangles over its vertices")
            f = idx.reshape(-1, 3)
            if np.linalg.det(m[:3, :3]) < 0:
                f = f[:, ::-1]
            verts.append(pos)
            faces.append(f + base)
            base += len(pos)
            uvs0.append(_accessor(doc, buffers, attrs["TEXCOORD_0"], path)[:, :2].astype(np.float64)
                        if "TEXCOORD_0" in attrs else None)
            uvs1.append("TEXCOORD_1" in attrs)
            materials.add(p.get("material"))
    if not verts:
        raise CamoError(f"{path}: no triangle mesh in the default scene")
    if len(materials) > 1:
        raise CamoError(f"{path}: {len(materials)} materials; one material per asset is supported (bake them into "
                        "one texture atlas)")
    mat_index = materials.pop()
    mat = doc.get("materials", [])[mat_index] if mat_index is not None else {}
    pbr = mat.get("pbrMetallicRoughness", {})
    ext = mat.get("extensions", {})
    used_uv: set[int] = set()
    wraps: set[str] = set()
    tex = lambda info, slot: _texture_image(doc, buffers, info, path, slot, used_uv, wraps)  # noqa: E731

    base_factor = np.asarray(pbr.get("baseColorFactor", (1.0, 1.0, 1.0, 1.0)), dtype=np.float32)
    base_img = tex(pbr.get("baseColorTexture"), "baseColorTexture")
    if base_img is None:
        albedo = base_factor[:3].copy()
    else:
        albedo = _srgb_to_linear(_rgb(base_img)) * base_factor[:3]
    if mat.get("alphaMode", "OPAQUE") != "OPAQUE" and (base_factor[3] < 1 or (base_img is not None
                                                                                and base_img.shape[-1] in (2, 4)
                                                                                and base_img[..., -1].min() < 1)):
        warnings.append(f"{path.name}: base colour alpha ({mat.get('alphaMode')}) is ignored (rendered opaque); "
                        "use KHR_materials_transmission")
    maps = {"albedo": np.asarray(albedo, np.float32)}
    images: dict[tuple[str, str], np.ndarray | None] = {}
    for name, bm in MAPS.items():  # every other map from its glTF slot (factor x texture channel)
        slot = bm.gltf
        if bm.colour or slot is None:
            continue
        table = pbr if not slot.extension else ext.get(slot.extension, {})
        fac = float(table.get(slot.factor, slot.default))
        key = (slot.extension, slot.texture)
        if key not in images:
            img = tex(table.get(slot.texture), slot.texture)
            images[key] = None if img is None else _rgb(img)
        img = images[key]
        maps[name] = np.asarray(np.float32(fac) if img is None else img[..., slot.channel:slot.channel + 1] * fac,
                                np.float32)
    eta = float(ext.get("KHR_materials_ior", {}).get("ior", DEFAULT_ETA))
    if not math.isfinite(eta) or eta <= 0:
        raise CamoError(f"{path}: KHR_materials_ior.ior must be a positive number, got {eta}")
    for slot in ("normalTexture", "occlusionTexture", "emissiveTexture"):
        if mat.get(slot):
            warnings.append(f"{path.name}: {slot} is ignored")
    if any(float(c) > 0 for c in mat.get("emissiveFactor", (0, 0, 0))) and not mat.get("emissiveTexture"):
        warnings.append(f"{path.name}: emissiveFactor is ignored")
    for e in sorted(set(ext) - set(SUPPORTED_GLTF_EXTENSIONS)):
        warnings.append(f"{path.name}: material extension {e} is ignored")
    if used_uv - {0}:
        raise CamoError(f"{path}: a texture uses a second UV set (texCoord {max(used_uv)}); only TEXCOORD_0 is "
                        "supported")
    if any(uvs1):
        warnings.append(f"{path.name}: TEXCOORD_1 is ignored (no texture uses it)")
    if used_uv and any(u is None for u in uvs0):
        raise CamoError(f"{path}: textures are used but a primitive has no TEXCOORD_0")
    uv = np.concatenate(uvs0).astype(np.float32) if all(u is not None for u in uvs0) else None
    wrap = "clamp" if not wraps else (wraps.pop() if len(wraps) == 1 else "repeat")
    if len(wraps) > 1:
        warnings.append(f"{path.name}: mixed texture wrap modes; rendered with repeat")
    v = np.concatenate(verts)
    v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)  # glTF +Y up -> +Z up (as optimizer.scenes.mesh.load_mesh)
    gen = str(doc.get("asset", {}).get("generator", ""))
    coords = "scene" if gen.startswith("camo") else "object"
    asset = Asset(str(path), v.astype(np.float32), np.concatenate(faces).astype(np.int64), uv, maps,
                  eta, False, wrap, coords, warnings)
    return _checked(asset, path)


def _checked(asset: Asset, path: Path) -> Asset:
    if not np.isfinite(asset.vertices).all():
        raise CamoError(f"{path}: vertex positions contain NaN or infinite values")
    if asset.uvs is not None and not np.isfinite(asset.uvs).all():
        raise CamoError(f"{path}: texture coordinates contain NaN or infinite values")
    if len(asset.faces) == 0:
        raise CamoError(f"{path}: no triangles")
    if asset.uvs is None and any(np.ndim(asset.maps[k]) >= 2 for k in asset.maps):
        raise CamoError(f"{path}: textures without texture coordinates")
    check_maps(asset, path.name)
    return asset


# --------------------------------------------------------------------------------------------------------------
# OBJ + MTL
# --------------------------------------------------------------------------------------------------------------


def _mtl_map(args: list[str], mtl: Path, key: str) -> Path:
    """The file of an MTL ``map_*`` statement; texture transform options are refused, others ignored."""
    i, name = 0, []
    while i < len(args):
        a = args[i]
        if a in ("-o", "-s", "-t"):
            raise CamoError(f"{mtl}: {key} {a} (a texture transform) is not supported; bake it into the UVs or "
                            "the image")
        if a.startswith("-") and not name:
            i += {"-bm": 2, "-blendu": 2, "-blendv": 2, "-boost": 2, "-cc": 2, "-clamp": 2, "-imfchan": 2,
                  "-texres": 2, "-mm": 3, "-type": 2}.get(a, 1)
            continue
        name.append(a)
        i += 1
    if not name:
        raise CamoError(f"{mtl}: {key} without a file name")
    return mtl.parent / " ".join(name)


def _parse_mtl(path: Path) -> dict[str, dict[str, list[str]]]:
    text = _read_file(path, "MTL file").decode("utf-8", "replace")
    out: dict[str, dict[str, list[str]]] = {}
    cur = None
    for line in text.splitlines():
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "newmtl":
            cur = out.setdefault(" ".join(parts[1:]), {})
        elif cur is not None:
            cur[parts[0]] = parts[1:]
    return out


def _scalar_map(img: np.ndarray) -> np.ndarray:
    return img[..., :1].astype(np.float32)


def read_obj(path: str | Path) -> Asset:
    """An OBJ + MTL asset (see the module docstring); positions as written (Z-up)."""
    path = Path(path)
    text = _read_file(path, "asset file").decode("utf-8", "replace")
    pos, tex, faces_v, faces_t = [], [], [], []
    mtllibs, used = [], []
    camo_file = "camo asset: world-space" in text[:300]
    for ln, line in enumerate(text.splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        key = parts[0]
        try:
            if key == "v":
                if len(parts) >= 7:
                    raise CamoError(f"{path}:{ln}: vertex colours (v x y z r g b) are not supported; bake them into "
                                    "map_Kd")
                pos.append([float(x) for x in parts[1:4]])
            elif key == "vt":
                tex.append([float(x) for x in parts[1:3]] + [0.0] * (2 - len(parts[1:3])))
            elif key == "f":
                if len(parts) < 4:
                    raise CamoError(f"{path}:{ln}: a face needs at least 3 vertices")
                vi, ti = [], []
                for c in parts[1:]:
                    s = c.split("/")
                    a = int(s[0])
                    vi.append(a - 1 if a > 0 else len(pos) + a)
                    t = int(s[1]) if len(s) > 1 and s[1] else 0
                    ti.append(t - 1 if t > 0 else (len(tex) + t if t < 0 else -1))
                for k in range(1, len(vi) - 1):  # fan triangulation of polygons
                    faces_v.append((vi[0], vi[k], vi[k + 1]))
                    faces_t.append((ti[0], ti[k], ti[k + 1]))
            elif key == "mtllib":
                mtllibs.append(" ".join(parts[1:]))
            elif key == "usemtl":
                name = " ".join(parts[1:])
                if name not in used:
                    used.append(name)
        except ValueError:
            raise CamoError(f"{path}:{ln}: cannot parse {line.strip()[:60]!r}") from None
    if not faces_v:
        raise CamoError(f"{path}: no faces")
    fv, ft = np.asarray(faces_v, np.int64), np.asarray(faces_t, np.int64)
    if fv.min() < 0 or fv.max() >= len(pos):
        raise CamoError(f"{path}: faces refer to vertices that do not exist")
    if ft.max() >= len(tex):
        raise CamoError(f"{path}: faces refer to texture coordinates that do not exist")
    if len(used) > 1:
        raise CamoError(f"{path}: {len(used)} materials ({', '.join(used[:3])}); one material per asset is supported "
                        "(bake them into one texture atlas)")
    mats: dict[str, dict[str, list[str]]] = {}
    mtl_path = None
    for lib in mtllibs:
        mtl_path = path.parent / lib
        mats.update(_parse_mtl(mtl_path))
    warnings: list[str] = []
    if used and used[0] not in mats:
        raise CamoError(f"{path}: material {used[0]!r} is not defined in {', '.join(mtllibs) or 'any mtllib'}")
    mat = mats.get(used[0], {}) if used else (next(iter(mats.values())) if len(mats) == 1 else {})
    if not mat:
        warnings.append(f"{path.name}: no material; rendered with albedo 0.8, roughness 1, metallic 0")

    def num(key: str, default: float) -> float:
        vals = mat.get(key)
        try:
            return float(np.mean([float(x) for x in vals])) if vals else default
        except ValueError:
            raise CamoError(f"{mtl_path}: {key} is not a number: {' '.join(vals)}") from None

    def image(key: str) -> np.ndarray | None:
        return _decode_image(_read_file(_mtl_map(mat[key], mtl_path, key), f"{key} texture"), f"{mtl_path}: {key}") \
            if key in mat else None

    try:
        kd = [float(x) for x in mat.get("Kd", ["0.8", "0.8", "0.8"])][:3]
    except ValueError:
        raise CamoError(f"{mtl_path}: Kd is not a number: {' '.join(mat['Kd'])}") from None
    kd = np.asarray(kd * 3 if len(kd) == 1 else kd, np.float32)[:3]
    img = image("map_Kd")
    albedo = kd if img is None else _srgb_to_linear(_rgb(img)) * kd
    maps: dict[str, np.ndarray] = {"albedo": np.asarray(albedo, np.float32)}
    for name, bm in MAPS.items():  # every other map from its PBR-MTL key (BsdfMap.mtl): K, map_K = value x texture
        key = bm.mtl
        if bm.colour:
            continue
        if key and (key in mat or f"map_{key}" in mat):
            img = image(f"map_{key}")
            value = np.float32(num(key, bm.mtl_default)) if img is None else _scalar_map(img) * num(key, 1.0)
        else:
            value = _mtl_fallback(name, num, image, mat, path.name, warnings)
        maps[name] = np.asarray(value, np.float32)
    eta = num("Ni", DEFAULT_ETA)
    if eta <= 0:
        raise CamoError(f"{mtl_path}: Ni must be > 0, got {eta}")
    for key in ("map_Bump", "bump", "norm", "map_Ke", "disp"):
        if key in mat:
            warnings.append(f"{path.name}: {key} is ignored")
    textured = any(np.ndim(a) >= 2 for a in maps.values())
    p = np.asarray(pos, np.float64)
    if (ft < 0).any():
        if textured:
            raise CamoError(f"{path}: textures are used but some faces have no texture coordinates (vt)")
        v, f, uv = p, fv, None
    else:
        pairs, inv = np.unique(np.stack([fv.ravel(), ft.ravel()], 1), axis=0, return_inverse=True)
        t = np.asarray(tex, np.float64)[pairs[:, 1]]
        v, f, uv = p[pairs[:, 0]], inv.reshape(-1, 3), np.stack([t[:, 0], 1.0 - t[:, 1]], 1)  # OBJ v up -> Mitsuba
    asset = Asset(str(path), v.astype(np.float32), f.astype(np.int64), None if uv is None else uv.astype(np.float32),
                  maps, float(eta), False, "repeat" if uv is not None and ((uv < 0) | (uv > 1)).any() else "clamp",
                  "scene" if camo_file else "object", warnings)
    return _checked(asset, path)


def _mtl_fallback(name: str, num, image, mat: dict, file: str, warnings: list[str]):
    """A map an MTL file does not give by its PBR key: what the classic keys say (roughness from the specular
    exponent ``Ns``; transmission from ``Tf``, ``Tr`` or ``1 - d``), else its ``BsdfMap.mtl_default`` (roughness
    1, metallic and transmission 0)."""
    if name == "roughness" and "Ns" in mat:
        r = np.float32(math.sqrt(2.0 / (max(num("Ns", 0.0), 0.0) + 2.0)))
        warnings.append(f"{file}: no Pr; roughness {float(r):.3f} from Ns (sqrt(2 / (Ns + 2)))")
        return r
    if name == "transmittance":
        if "Tf" in mat:
            return np.float32(num("Tf", 0.0))
        if "Tr" in mat:
            return np.float32(num("Tr", 0.0))
        if "d" in mat or "map_d" in mat:
            img = image("map_d")
            t = np.float32(1.0 - num("d", 1.0)) if img is None else 1.0 - _scalar_map(img) * num("d", 1.0)
            if img is not None or float(t) > 0:
                warnings.append(f"{file}: dissolve (d / map_d) read as transmission 1 - d")
            return t
    return np.float32(MAPS[name].mtl_default)


# --------------------------------------------------------------------------------------------------------------
# loading and placing
# --------------------------------------------------------------------------------------------------------------


def load_asset(path: str | Path) -> Asset:
    """Read a ``.glb`` / ``.gltf`` / ``.obj`` asset (CamoError, one line, for anything unsupported)."""
    path = Path(path).expanduser()
    ext = path.suffix.lower()
    if ext not in ASSET_SUFFIXES:
        raise CamoError(f"asset {path}: unsupported format {ext or '(none)'!r}; use {', '.join(ASSET_SUFFIXES)}")
    if not path.is_file():
        raise CamoError(f"asset file not found: {path}")
    return read_obj(path) if ext == ".obj" else read_gltf(path)


def place(asset: Asset, pack, placement: str = "auto") -> Asset:
    """The asset in ``pack``'s scene coordinates (see the module docstring for the placements)."""
    from optimizer.scenes.pose import model_matrix, transform_points

    if placement not in PLACEMENTS:
        raise CamoError(f"placement must be one of {', '.join(PLACEMENTS)}, got {placement!r}")
    if placement == "auto":
        placement = "scene" if asset.coordinates == "scene" else "pack"
    if placement == "scene":
        return dataclasses.replace(asset, coordinates="scene", coordinates_from="scene")
    v = asset.vertices.astype(np.float64)
    lo, hi = v.min(0), v.max(0)
    extent = float((hi - lo).max())
    if not math.isfinite(extent) or extent <= 0:
        raise CamoError(f"{asset.source}: the asset has zero size")
    unit = (v - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]) / extent
    o = pack.object
    placed = transform_points(model_matrix(o.size, o.rotation, o.translation), unit)
    return dataclasses.replace(asset, vertices=placed.astype(np.float32), coordinates="scene", coordinates_from="pack")
