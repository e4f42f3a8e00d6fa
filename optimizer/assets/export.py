"""Asset writers for the camouflaged object: glTF binary, OBJ + MTL, PLY, and map previews.

Inputs (NumPy, as the optimiser holds them):

* ``vertices (N, 3)`` world-space positions (Z-up, scene units) of the UV-split mesh,
  ``faces (F, 3)`` vertex indices, ``uvs (N, 2)`` in [0, 1] in **Mitsuba's convention**;
* ``maps``: ``{name: array}`` for every BSDF map of :data:`optimizer.scenes.bsdf_maps.MAPS` **as rendered**
  (``roughness`` after the safe minimum): a colour map (``albedo``) ``(H, W, 3)`` linear in [0, 1], the others
  ``(H, W)`` in [0, 1]; ``eta`` the scalar index of refraction. Where each map goes in glTF and MTL is its
  registry record (``BsdfMap.gltf``, ``BsdfMap.mtl``).

Texture-coordinate conventions (verified with Mitsuba 3.9.1, see ``tests/test_export.py``):

* **Mitsuba** ``bitmap``: ``uv = (u, v)`` looks up column ``u * W`` and row ``v * H`` of
  the data, where row 0 is the first row of the array (the *top* row of the image file).
  So ``v = 0`` is the top of the image (a ``bitmap`` evaluated at ``uv = (0.1, 0.1)`` returns
  ``data[0, 0]``, at ``(0.1, 0.9)`` returns ``data[-1, 0]``).
* **glTF 2.0**: ``TEXCOORD_0 (0, 0)`` is the first pixel of the image (top-left), i.e.
  the same as Mitsuba: the glb stores ``uvs`` unchanged and the images top row first.
* **OBJ**: ``vt (0, 0)`` is the *bottom*-left of the image (OpenGL convention), so the OBJ
  stores ``vt = (u, 1 - v)``; Mitsuba's own ``obj`` plugin flips ``v`` back by default
  (``flip_tex_coords = true``), so the OBJ also renders correctly in Mitsuba.
* **PLY** (:func:`write_ply`, used by ``scene.xml``): Mitsuba's ``ply`` plugin does *not*
  flip, so ``u, v`` are written unchanged (Mitsuba convention; tools that read PLY
  ``u, v`` as OpenGL texture coordinates would see the texture upside down).

Axes: the glb's mesh data are the world-space (Z-up) positions; with ``y_up`` (default)
the glb's single node carries the rotation Z-up -> Y-up (glTF's +Y is up), so viewers
show the object upright. OBJ and PLY store world-space (Z-up) positions unchanged.

Normals in glb/OBJ are angle-weighted vertex normals of the split mesh, computed as
Mitsuba's ``Mesh.recompute_vertex_normals`` does (so seams shade as in the render).

All files are written atomically (:mod:`camo_base.atomic`).
"""

from __future__ import annotations

import io
import json
import os
import struct
from pathlib import Path
from typing import Mapping

import numpy as np

from camo_base.atomic import atomic_path, write_bytes, write_text
from camo_base.imaging import linear_to_srgb, save_png, to_uint8
from optimizer.scenes.bsdf_maps import MAPS, gltf_extensions

#: Rotation taking world (Z-up) coordinates to glTF (Y-up): (x, y, z) -> (x, z, -y).
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# glTF enums
_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP_TO_EDGE = 9729, 9987, 33071

#: glTF extensions the glb uses: those of the maps (KHR_materials_transmission) and the index of refraction.
GLB_EXTENSIONS = (*gltf_extensions(), "KHR_materials_ior")


# --- input checks --------------------------------------------------------------


def _geometry(vertices, faces, uvs) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    v = np.ascontiguousarray(np.asarray(vertices, dtype=np.float32))
    f = np.ascontiguousarray(np.asarray(faces, dtype=np.int64))
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must be (N, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"faces must be (F, 3), got {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    if not np.isfinite(v).all():
        raise ValueError("vertices contain NaN or infinite values")
    uv = None
    if uvs is not None:
        uv = np.ascontiguousarray(np.asarray(uvs, dtype=np.float32))
        if uv.shape != (len(v), 2):
            raise ValueError(f"uvs must be ({len(v)}, 2), got {uv.shape}")
        if not np.isfinite(uv).all():
            raise ValueError("uvs contain NaN or infinite values")
    return v, f.astype(np.uint32), uv


def _scalar_map(name: str, m, shape: tuple[int, int] | None = None) -> np.ndarray:
    a = np.asarray(m, dtype=np.float32)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise ValueError(f"{name} must be (H, W), got {a.shape}")
    if shape is not None and a.shape != shape:
        raise ValueError(f"{name} must be {shape} like the map it shares a texture with, got {a.shape}")
    return np.nan_to_num(a, nan=0.0)


def _maps(maps: Mapping[str, np.ndarray], eta) -> tuple[dict[str, np.ndarray], float]:
    """The maps checked and as float32: colour maps ``(H, W, 3)``, the others ``(H, W)``; maps sharing a glTF
    texture have one shape."""
    out: dict[str, np.ndarray] = {}
    shared: dict[str, tuple[int, ...]] = {}
    for name, m in MAPS.items():
        if name not in maps:
            raise ValueError(f"no {name} map")
        if m.colour:
            a = np.asarray(maps[name], dtype=np.float32)
            if a.ndim != 3 or a.shape[2] != 3:
                raise ValueError(f"{name} must be (H, W, 3), got {a.shape}")
        else:
            key = m.gltf.texture if m.gltf else name
            a = _scalar_map(name, maps[name], shared.get(key))
            shared.setdefault(key, a.shape)
        out[name] = a
    eta = float(eta)
    if not np.isfinite(eta) or eta <= 0:
        raise ValueError(f"eta must be a positive number, got {eta}")
    return out, eta


# --- geometry helpers ----------------------------------------------------------


def _unit_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors, the numerically robust form Mitsuba uses."""
    dot = (a * b).sum(-1)
    return np.where(dot < 0, np.pi - 2.0 * np.arcsin(np.clip(np.linalg.norm(a + b, axis=-1) / 2, 0, 1)),
                    2.0 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=-1) / 2, 0, 1)))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Angle-weighted vertex normals (Thuermer & Wuethrich 1998), as Mitsuba's
    ``recompute_vertex_normals``: each face adds its unit normal times the corner angle.
    Vertices touched by no valid face get ``(0, 0, 1)``. Returns float32 ``(N, 3)``."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    p = [v[f[:, k]] for k in range(3)]
    n = np.cross(p[1] - p[0], p[2] - p[0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    valid = length[:, 0] > 0
    n = np.where(valid[:, None], n / np.maximum(length, 1e-300), 0.0)
    acc = np.zeros_like(v)

    def unit(x):
        ln = np.linalg.norm(x, axis=1, keepdims=True)
        return x / np.maximum(ln, 1e-300)

    for k in range(3):
        angle = _unit_angle(unit(p[(k + 1) % 3] - p[k]), unit(p[(k + 2) % 3] - p[k]))
        angle = np.where(valid, np.nan_to_num(angle), 0.0)
        np.add.at(acc, f[:, k], n * angle[:, None])
    ln = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(ln > 0, acc / np.maximum(ln, 1e-300), np.array([0.0, 0.0, 1.0]))
    return out.astype(np.float32)


# --- images --------------------------------------------------------------------


def srgb8(albedo_linear: np.ndarray) -> np.ndarray:
    """Linear albedo -> 8-bit sRGB-encoded ``uint8`` (what glTF's baseColorTexture requires)."""
    return to_uint8(linear_to_srgb(albedo_linear))


def linear8(x: np.ndarray) -> np.ndarray:
    """Linear data in [0, 1] -> ``uint8`` (no transfer curve; glTF's data textures)."""
    return np.round(np.clip(np.nan_to_num(np.asarray(x, dtype=np.float32)), 0.0, 1.0) * 255.0).astype(np.uint8)


def _png_bytes(arr: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(arr)).save(buf, format="PNG")
    return buf.getvalue()


def _grey_rgb(x: np.ndarray) -> np.ndarray:
    g = linear8(x)
    return np.repeat(g[..., None], 3, axis=-1)


def packed8(channels: Mapping[int, np.ndarray]) -> np.ndarray:
    """An 8-bit RGB data texture (linear) holding several maps, one per channel (``{channel: (H, W)}``); unused
    channels are 255. glTF's metallicRoughnessTexture is ``{1: roughness, 2: metallic}`` (R unused)."""
    shape = next(iter(channels.values())).shape
    out = np.full(shape + (3,), 255, np.uint8)
    for c, x in channels.items():
        out[..., c] = linear8(x)
    return out


def gltf_images(maps: Mapping[str, np.ndarray]) -> list[tuple[str, np.ndarray, list[str]]]:
    """The images of the glb, in order: ``(name, uint8 RGB, maps in it)``, one per glTF texture of the maps
    (``BsdfMap.gltf``): a colour map sRGB-encoded, a texture holding one map grey, one holding several packed
    (:func:`packed8`)."""
    groups: dict[tuple[str, str], list[str]] = {}
    for name, m in MAPS.items():
        if m.gltf is not None:
            groups.setdefault((m.gltf.extension, m.gltf.texture), []).append(name)
    out = []
    for names in groups.values():
        first = MAPS[names[0]]
        if first.colour:
            img = srgb8(maps[names[0]])
        elif len(names) == 1:
            img = _grey_rgb(maps[names[0]])
        else:
            img = packed8({MAPS[n].gltf.channel: maps[n] for n in names})
        out.append((first.gltf.image, img, names))
    return out


def gltf_material(name: str, images: list[tuple[str, np.ndarray, list[str]]], eta: float) -> dict:
    """The glb's material: each map's factor (1) and texture in ``pbrMetallicRoughness`` or its extension, then
    ``KHR_materials_ior``."""
    pbr: dict = {}
    ext: dict = {}
    for index, (_, _, names) in enumerate(images):
        slot = MAPS[names[0]].gltf
        table = pbr if not slot.extension else ext.setdefault(slot.extension, {})
        for n in names:
            table[MAPS[n].gltf.factor] = [1.0, 1.0, 1.0, 1.0] if MAPS[n].colour else 1.0
        table[slot.texture] = {"index": index, "texCoord": 0}
    ext["KHR_materials_ior"] = {"ior": eta}
    return {"name": f"{name}_material", "pbrMetallicRoughness": pbr, "extensions": ext}


# --- glTF binary ---------------------------------------------------------------


class _BinBuilder:
    """Accumulates the glb BIN chunk; every buffer view starts 4-byte aligned."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []

    def add(self, payload: bytes, target: int | None = None) -> int:
        pad = (-len(self.data)) % 4
        self.data.extend(b"\x00" * pad)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(payload)}
        if target is not None:
            view["target"] = target
        self.data.extend(payload)
        self.views.append(view)
        return len(self.views) - 1


def glb_bytes(vertices, faces, uvs, maps: Mapping[str, np.ndarray], eta: float, *,
              normals: np.ndarray | None = None, y_up: bool = True, name: str = "camo_object") -> bytes:
    """The glb file content (see :func:`write_glb`)."""
    v, f, uv = _geometry(vertices, faces, uvs)
    if uv is None:
        raise ValueError("the glb needs uvs")
    maps, eta = _maps(maps, eta)
    nrm = vertex_normals(v, f) if normals is None else np.ascontiguousarray(np.asarray(normals, np.float32))
    if nrm.shape != v.shape:
        raise ValueError(f"normals must be {v.shape}, got {nrm.shape}")

    b = _BinBuilder()
    accessors = [
        {"bufferView": b.add(v.tobytes(), _ARRAY_BUFFER), "componentType": _FLOAT, "count": len(v), "type": "VEC3",
         "min": [float(x) for x in v.min(0)], "max": [float(x) for x in v.max(0)]},
        {"bufferView": b.add(nrm.tobytes(), _ARRAY_BUFFER), "componentType": _FLOAT, "count": len(v), "type": "VEC3"},
        {"bufferView": b.add(uv.tobytes(), _ARRAY_BUFFER), "componentType": _FLOAT, "count": len(v), "type": "VEC2"},
        {"bufferView": b.add(f.astype("<u4").tobytes(), _ELEMENT_ARRAY_BUFFER), "componentType": _UINT,
         "count": int(f.size), "type": "SCALAR", "min": [int(f.min())], "max": [int(f.max())]},
    ]
    pictures = gltf_images(maps)
    images = [{"bufferView": b.add(_png_bytes(img)), "mimeType": "image/png", "name": image}
              for image, img, _ in pictures]
    node: dict = {"mesh": 0, "name": name}
    if y_up:
        m4 = np.eye(4)
        m4[:3, :3] = Z_UP_TO_Y_UP
        node["matrix"] = [float(x) for x in m4.T.ravel()]  # glTF matrices are column-major
    gltf = {
        "asset": {"version": "2.0", "generator": "camo optimizer.assets.export"},
        "extensionsUsed": list(GLB_EXTENSIONS),
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node],
        "meshes": [{"name": name, "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
            "indices": 3, "material": 0, "mode": 4}]}],
        "materials": [gltf_material(name, pictures, eta)],
        "samplers": [{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR,
                      "wrapS": _CLAMP_TO_EDGE, "wrapT": _CLAMP_TO_EDGE}],
        "textures": [{"sampler": 0, "source": i} for i in range(len(images))],
        "images": images,
        "accessors": accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": len(b.data)}],
    }
    js = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    bin_ = bytes(b.data) + b"\x00" * ((-len(b.data)) % 4)
    total = 12 + 8 + len(js) + 8 + len(bin_)
    return b"".join([
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<I4s", len(js), b"JSON"), js,
        struct.pack("<I4s", len(bin_), b"BIN\x00"), bin_,
    ])


def write_glb(path: str | os.PathLike, vertices, faces, uvs, maps: Mapping[str, np.ndarray], eta: float,
              *, normals: np.ndarray | None = None, y_up: bool = True, name: str = "camo_object") -> Path:
    """Write a glTF 2.0 binary with one mesh and a PBR material (the maps' places: ``BsdfMap.gltf``).

    * ``baseColorTexture``: 8-bit sRGB-encoded PNG of ``albedo`` (linear input);
    * ``metallicRoughnessTexture``: linear PNG, G = roughness (the rendered one), B = metallic;
    * ``KHR_materials_transmission``: ``transmissionFactor`` 1, ``transmissionTexture`` (R) =
      ``transmittance``; ``KHR_materials_ior``: ``ior = eta``; both in ``extensionsUsed``; a map in
      another extension likewise (factor 1, its texture).
    * attributes POSITION (with min/max), NORMAL, TEXCOORD_0 (= Mitsuba ``uvs``, unchanged;
      see the module docstring), uint32 indices; sampler bilinear + clamp as in the render.

    The mesh holds world-space Z-up positions; with ``y_up`` the node rotates them to
    glTF's Y-up. The glb is written by this module (no trimesh exporter: it cannot carry
    the two extensions); the JSON and BIN chunks and every buffer view are 4-byte aligned.
    """
    path = Path(path)
    write_bytes(path, glb_bytes(vertices, faces, uvs, maps, eta, normals=normals, y_up=y_up, name=name))
    return path


def read_glb(path: str | os.PathLike) -> tuple[dict, bytes]:
    """Parse a glb into its JSON dict and BIN chunk (for checks and tools)."""
    data = Path(path).read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2 or total != len(data):
        raise ValueError(f"{path} is not a glTF 2.0 binary")
    off, js, bin_ = 12, None, b""
    while off < len(data):
        length, kind = struct.unpack_from("<I4s", data, off)
        chunk = data[off + 8: off + 8 + length]
        if kind == b"JSON":
            js = json.loads(chunk.decode("utf-8"))
        elif kind == b"BIN\x00":
            bin_ = chunk
        off += 8 + length
    if js is None:
        raise ValueError(f"{path} has no JSON chunk")
    return js, bin_


# --- OBJ + MTL -----------------------------------------------------------------


def write_obj(path: str | os.PathLike, vertices, faces, uvs, maps: Mapping[str, np.ndarray], eta: float,
              *, normals: np.ndarray | None = None, material: str = "camo") -> dict[str, Path]:
    """Write ``path`` (.obj), its ``.mtl`` and the texture PNGs beside it.

    Files: ``<stem>.obj``, ``<stem>.mtl``, one ``<stem>_<map>.png`` per BSDF map (the colour map sRGB-encoded, the
    others linear grey). OBJ texture coordinates are ``vt = (u, 1 - v)`` (OBJ's v points up;
    see the module docstring); positions are world space (Z-up), normals as in the render.

    MTL keys: the classic ``Kd 1 1 1`` + ``map_Kd`` (albedo), ``Ka``/``Ks`` 0, ``d 1``,
    ``illum 2``, ``Ni`` = eta; and for every other map its key ``K 1`` and ``map_K`` (``BsdfMap.mtl``: the widely
    read PBR extension keys of Blender, assimp, tinyobjloader, three.js: ``Pm`` metallic, ``Pr`` roughness (the
    rendered one), ``Ptr`` transmission -- the three.js / assimp PBR-MTL spelling of glTF's transmission).
    ``Tf`` is deliberately *not* written: in classic MTL it is a whole-material transmission filter colour, which
    would make readers that honour it treat every texel as transparent.

    Returns ``{"obj", "mtl", <map>...}`` paths.
    """
    path = Path(path)
    v, f, uv = _geometry(vertices, faces, uvs)
    if uv is None:
        raise ValueError("the OBJ needs uvs")
    maps, eta = _maps(maps, eta)
    nrm = vertex_normals(v, f) if normals is None else np.asarray(normals, np.float32)
    stem = path.stem
    out = {"obj": path, "mtl": path.with_suffix(".mtl"),
           **{name: path.with_name(f"{stem}_{name}.png") for name in MAPS}}
    for name, m in MAPS.items():
        save_png(out[name], srgb8(maps[name]) if m.colour else linear8(maps[name]))
    scalars = [(name, m.mtl) for name, m in MAPS.items() if not m.colour and m.mtl]
    colour = next(name for name, m in MAPS.items() if m.colour)
    mtl = "\n".join([
        f"# camo asset: PBR material ({colour} sRGB PNG; {'/'.join(n for n, _ in scalars)} linear grey PNGs)",
        f"# {'/'.join(k for _, k in scalars)}: PBR-MTL extension keys ({', '.join(n for n, _ in scalars)}); "
        "Ni: index of refraction",
        f"newmtl {material}",
        "Ka 0 0 0",
        "Kd 1 1 1",
        "Ks 0 0 0",
        "Ns 0",
        "d 1",
        "illum 2",
        f"Ni {eta!r}",
        *(f"{key} 1" for _, key in scalars),
        f"map_Kd {out[colour].name}",
        *(f"map_{key} {out[name].name}" for name, key in scalars),
        "",
    ])
    write_text(out["mtl"], mtl)

    vt = uv.astype(np.float64).copy()
    vt[:, 1] = 1.0 - vt[:, 1]
    buf = io.StringIO()
    buf.write("# camo asset: world-space positions (Z-up, scene units); vt = (u, 1 - v_mitsuba)\n")
    buf.write(f"mtllib {out['mtl'].name}\no {material}\n")
    np.savetxt(buf, v, fmt="v %.9g %.9g %.9g")
    np.savetxt(buf, vt, fmt="vt %.9g %.9g")
    np.savetxt(buf, nrm, fmt="vn %.7g %.7g %.7g")
    buf.write(f"usemtl {material}\n")
    fi = f.astype(np.int64) + 1
    np.savetxt(buf, np.repeat(fi, 3, axis=1), fmt="f %d/%d/%d %d/%d/%d %d/%d/%d")
    write_text(out["obj"], buf.getvalue())
    return out


# --- PLY -----------------------------------------------------------------------


def ply_bytes(vertices, faces, uvs=None, normals=None) -> bytes:
    v, f, uv = _geometry(vertices, faces, uvs)
    props = ["x", "y", "z"]
    cols = [v]
    if normals is not None:
        n = np.asarray(normals, dtype=np.float32)
        if n.shape != v.shape:
            raise ValueError(f"normals must be {v.shape}, got {n.shape}")
        props += ["nx", "ny", "nz"]
        cols.append(n)
    if uv is not None:
        props += ["u", "v"]
        cols.append(uv)
    header = ["ply", "format binary_little_endian 1.0", "comment camo asset: u, v in Mitsuba's convention (v = 0: top row)",
              f"element vertex {len(v)}"]
    header += [f"property float {p}" for p in props]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.ascontiguousarray(np.concatenate(cols, axis=1).astype("<f4"))
    face_dt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    fr = np.empty(len(f), dtype=face_dt)
    fr["n"] = 3
    fr["i"] = f.astype(np.int32)
    return ("\n".join(header) + "\n").encode("ascii") + vert.tobytes() + fr.tobytes()


def write_ply(path: str | os.PathLike, vertices, faces, uvs=None, normals=None) -> Path:
    """Binary little-endian PLY with ``x y z [nx ny nz] [u v]`` float vertices and int faces.

    ``u, v`` are written unchanged: Mitsuba's ``ply`` plugin reads them without flipping,
    so the texture maps exactly as on the in-memory mesh. Leave ``normals`` out to let
    Mitsuba recompute smooth vertex normals, as :func:`optimizer.rendering.scene.object_mesh` does.
    """
    path = Path(path)
    write_bytes(path, ply_bytes(vertices, faces, uvs, normals))
    return path


# --- maps ----------------------------------------------------------------------


def map_preview(name: str, arr: np.ndarray, displacement_bound: float | None = None) -> np.ndarray | None:
    """The 8-bit preview of one map, or None when it is not an image (e.g. per-vertex data).

    * ``albedo`` (and any other 3-channel map named ``*albedo*``/``*color*``): sRGB-encoded;
    * ``displacement``: ``[-bound, bound] -> [0, 255]`` (0 displacement = 127.5 -> 128),
      clipped; ``bound`` is ``displacement_bound`` or, when None, ``max |d|`` (1 if all zero);
    * other maps: linear values in [0, 1] -> [0, 255], clipped (scalar maps grey).
    """
    a = np.asarray(arr, dtype=np.float32)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        return None
    if name == "displacement" or name.startswith("displacement"):
        bound = displacement_bound
        if bound is None:
            m = float(np.nanmax(np.abs(a))) if a.size else 0.0
            bound = m if m > 0 else 1.0
        return linear8(0.5 + 0.5 * np.nan_to_num(a) / float(bound))
    if a.ndim == 3 and (name in MAPS and MAPS[name].colour or "albedo" in name or "color" in name):
        return srgb8(a[..., :3])
    return linear8(a)


def save_maps(directory: str | os.PathLike, maps: Mapping[str, np.ndarray],
              displacement_bound: float | None = None) -> dict[str, dict[str, Path]]:
    """Save each map as ``<name>.npy`` (float32, exact) and ``<name>.png`` (8-bit preview).

    See :func:`map_preview` for the preview encodings (albedo sRGB, scalar maps grey,
    displacement ``[-bound, bound] -> [0, 255]``). Maps that are not images (1-D, e.g.
    per-vertex displacement) get only the ``.npy``. All writes are atomic. Returns
    ``{name: {"npy": path, "png": path}}``.
    """
    directory = Path(directory)
    out: dict[str, dict[str, Path]] = {}
    for name, arr in maps.items():
        a = np.asarray(arr, dtype=np.float32)
        paths: dict[str, Path] = {"npy": directory / f"{name}.npy"}
        with atomic_path(paths["npy"]) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, a)
        prev = map_preview(name, a, displacement_bound)
        if prev is not None:
            paths["png"] = directory / f"{name}.png"
            save_png(paths["png"], prev)
        out[name] = paths
    return out
