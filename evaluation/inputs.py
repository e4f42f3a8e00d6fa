"""What ``camo evaluate`` scores: run directories, external assets placed in a scene, and 2D image triplets.

Three kinds of input, mixed freely in one evaluation (:class:`InputSpec`, resolved into :class:`Entry`):

* ``run``: a ``camo optimize`` run directory (:mod:`optimizer.assets.rundir`); scene, method and ablation from its
  ``config.toml`` (the method label can be overridden), seconds from its ``summary.json`` / ``log.jsonl``.
* ``asset``: a glTF 2.0 / GLB or OBJ + MTL file (:mod:`optimizer.assets.asset`) placed in ``scene`` -- a built-in scene
  name (``gravel``, ``split:chair``), a scene pack ``.toml`` or a run directory (its resolved pack: the same
  cameras as that run) -- by ``placement`` (``auto``/``scene``/``pack``, see :func:`optimizer.assets.asset.place`).
  The method label is the user's; ``seconds`` (optional) is what the method cost.
* ``triplets``: a folder of given images per view, scored with the same metrics and written as study stimuli:
  ``<view>_obj.png`` (with the object), ``<view>_bg.png`` (background), ``<view>_mask.png`` (object mask,
  >= 128 is object) and optionally ``<view>_depth.npy`` / ``.exr`` (background depth, scene units); or the
  same stems in subfolders ``with_object/``, ``background/``, ``mask/`` (and ``depth/``). PNG/JPEG are read as
  8-bit sRGB (16-bit PNG rounded to 8 bit), EXR as linear radiance (sRGB-encoded and tone-clipped like our
  renders). ``scene`` is a label here (a built-in scene / pack / run directory gives its pack's name).

A list of many inputs is a TOML file (``camo evaluate --inputs LIST.toml``; relative paths are relative to it)::

    [[run]]
    path = "runs/gravel-ours"          # method = "..." relabels it

    [[asset]]
    path = "theirs/result.glb"
    scene = "gravel"                   # built-in name, pack .toml or a run directory
    method = "theirs"
    seconds = 812.0                    # optional: what producing it cost
    placement = "pack"                 # optional: auto (default), scene or pack
    name = "theirs-gravel"             # optional: folder name under renders/

    [[triplets]]
    path = "twod/gravel"
    method = "2d-inpaint"
    scene = "gravel"
    seconds = 3.5
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import re
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from camo_base.documents import read_toml
from camo_base.errors import CamoError, SettingError, literal

KINDS = ("run", "asset", "triplets")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")
_ROLE_SUFFIXES = {"obj": ("obj", "with", "with_object", "object"), "bg": ("bg", "background"), "mask": ("mask",),
                  "depth": ("depth",)}
_SUBFOLDERS = {"obj": "with_object", "bg": "background", "mask": "mask", "depth": "depth"}


@dataclasses.dataclass
class InputSpec:
    """One input as the user gives it (command line or ``--inputs`` list)."""

    kind: str  # run | asset | triplets
    path: str
    method: str | None = None
    scene: str | None = None
    name: str | None = None
    seconds: float | None = None
    placement: str = "auto"
    object: str | None = None


@dataclasses.dataclass
class Triplets:
    """Given images of one 2D method: ``(V, H, W, 3)`` uint8 sRGB with and without the object, ``(V, H, W)`` bool
    masks, optional ``(V, H, W)`` float32 depth (scene units), and the linear radiance when read from EXR."""

    views: list[str]  # the file stems, in order
    obj8: np.ndarray
    bg8: np.ndarray
    mask: np.ndarray
    depth: np.ndarray | None
    obj_linear: np.ndarray | None = None
    bg_linear: np.ndarray | None = None

    def key(self) -> str:
        h = hashlib.sha256()
        h.update(self.bg8.tobytes())
        return "images:" + h.hexdigest()[:12]


@dataclasses.dataclass
class Entry:
    """A resolved input: what to render (``pack`` + ``asset``) or the given images (``triplets``)."""

    kind: str
    path: Path
    name: str  # folder under renders/
    scene: str
    object: str
    method: str
    ablation: str
    seconds: dict[str, float]  # setup, stage1, stage2, total (NaN = unknown)
    pack: Any = None
    asset: Any = None
    run: Any = None
    triplets: Triplets | None = None
    warnings: list[str] = dataclasses.field(default_factory=list)
    placement: dict[str, str] = dataclasses.field(default_factory=dict)  # assets: {"scene": spec, "placement": p}


def finite_seconds(v: Any, where: str) -> float | None:
    """``v`` as seconds (None stays None); a SettingError naming ``inputs`` (``where``: the entry) otherwise."""
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise SettingError.of("inputs", f"{where}: seconds must be a number, got {v!r}") from None
    if not math.isfinite(f) or f < 0:
        raise SettingError.of("inputs", f"{where}: seconds must be a finite number >= 0, got {v!r}")
    return f


def read_input_list(path: str | Path) -> list[InputSpec]:
    """The inputs of a TOML list (see the module docstring)."""
    p = Path(path)
    try:
        doc = read_toml(p, "list")
    except CamoError as exc:  # "list ... not found": the CLI shows the setting as --inputs
        raise SettingError.of("inputs", f" {exc}") from None
    unknown = sorted(set(doc) - set(KINDS))
    if unknown:
        raise SettingError.of("inputs", f" {p}: unknown table(s) {', '.join(unknown)}; use [[run]], [[asset]], [[triplets]]")
    fields = {f.name for f in dataclasses.fields(InputSpec)} - {"kind"}
    out = []
    for kind in KINDS:
        items = doc.get(kind, [])
        if not isinstance(items, list):
            raise SettingError.of("inputs", f" {p}: {kind} must be an array of tables ([[{kind}]])")
        for i, item in enumerate(items):
            where = f" {p}: [[{kind}]] #{i + 1}"
            if not isinstance(item, dict) or "path" not in item:
                raise SettingError.of("inputs", f"{where}: needs a path")
            bad = sorted(set(item) - fields)
            if bad:
                raise SettingError.of("inputs", f"{where}: unknown key(s) {', '.join(bad)}; known: {', '.join(sorted(fields))}")
            item = dict(item)
            given = Path(str(item["path"])).expanduser()
            item["path"] = str(given if given.is_absolute() else p.parent / given)
            if isinstance(item.get("scene"), str) and kind != "run":
                cand = p.parent / item["scene"]
                if (cand.suffix == ".toml" or cand.is_dir()) and cand.exists():
                    item["scene"] = str(cand)
            item["seconds"] = finite_seconds(item.get("seconds"), where)
            for k in ("method", "scene", "name", "placement", "object"):
                if k in item and not isinstance(item[k], str):
                    raise SettingError.of("inputs", f"{where}: {k} must be a string")
            out.append(InputSpec(kind=kind, **item))
    if not out:
        raise SettingError.of("inputs", f" {p}: lists no input ([[run]], [[asset]] or [[triplets]])")
    return out


def scene_pack(scene: str, where: str):
    """The scene pack named by ``scene``: a run directory's resolved pack, a pack file or a built-in scene."""
    from optimizer.assets.rundir import is_run_dir, open_run
    from optimizer.scenes.builtin_scenes import resolve_scene

    if not scene:
        raise SettingError(f"{literal(where)}: needs a scene ({{0}} NAME, pack .toml or run directory)", "scene")
    if is_run_dir(scene):
        return open_run(scene).pack
    return resolve_scene(scene)


def _scene_source(scene: str) -> str:
    """``--scene`` as recorded: an absolute path for a pack file or run directory, else the built-in name."""
    p = Path(scene).expanduser()
    return str(p.resolve()) if p.exists() else scene


def _label(text: str | None, where: str, what: str) -> str:
    if text is None or not str(text).strip():
        raise SettingError(f"{literal(where)}: needs a method label ({{0}}, or method = \"...\" in the list)", "method")
    text = str(text).strip()
    if len(text) > 120 or "\n" in text:
        raise CamoError(f"{where}: {what} must be one line of at most 120 characters")
    return text


def safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or "input"


def resolve(specs: Sequence[InputSpec]) -> list[Entry]:
    """Read every input (CamoError, one line, before anything is rendered or written)."""
    from optimizer.assets.asset import PLACEMENTS, load_asset, place
    from optimizer.assets.rundir import open_run

    if not specs:
        raise SettingError("evaluate needs at least one input: {0}, {1}, {2} or {3}", "run_dirs", "asset", "triplets",
                           "inputs")
    nan = {"setup": math.nan, "stage1": math.nan, "stage2": math.nan, "total": math.nan}
    entries: list[Entry] = []
    for s in specs:
        where = f"{s.kind} {s.path}"
        if s.kind == "run":
            r = open_run(s.path)
            method = _label(s.method, where, "method") if s.method is not None else r.method
            e = Entry("run", r.path, safe_name(s.name) if s.name else r.name, r.scene, r.object, method,
                      r.ablation_label, r.seconds(), pack=r.pack, run=r)
            e.asset = r.asset()
        elif s.kind == "asset":
            if s.placement not in PLACEMENTS:
                raise CamoError(f"{where}: placement must be one of {', '.join(PLACEMENTS)}, got {s.placement!r}")
            method = _label(s.method, where, "method")
            pack = scene_pack(s.scene or "", where)
            asset = place(load_asset(s.path), pack, s.placement)
            p = Path(s.path)
            secs = dict(nan, total=s.seconds if s.seconds is not None else math.nan)
            e = Entry("asset", p, safe_name(s.name or p.stem), pack.name, s.object or p.stem, method, "none", secs,
                      pack=pack, asset=asset, placement={"scene_source": _scene_source(s.scene or ""),
                                                         "placement": s.placement,
                                                         "placed_as": asset.coordinates_from})
        elif s.kind == "triplets":
            method = _label(s.method, where, "method")
            scene = s.scene or Path(s.path).name
            try:
                scene = scene_pack(scene, where).name if s.scene else scene
            except CamoError:
                pass  # a plain label
            trip, warns = read_triplets(s.path)
            p = Path(s.path)
            secs = dict(nan, total=s.seconds if s.seconds is not None else math.nan)
            e = Entry("triplets", p, safe_name(s.name or f"{p.name}"), scene, s.object or "object", method, "none",
                      secs, triplets=trip, warnings=warns)
        else:
            raise CamoError(f"unknown input kind {s.kind!r}")
        entries.append(e)
    # renders/<name>/ must be distinct; the same input given twice is evaluated once
    unique: dict[tuple[str, str], Entry] = {}
    for e in entries:
        unique.setdefault((e.kind, str(e.path.resolve())), e)
    out = list(unique.values())
    seen: dict[str, Entry] = {}
    for e in out:
        if e.name in seen:
            other = seen[e.name]
            if e.kind != "run" and e.name == safe_name(e.path.stem if e.kind == "asset" else e.path.name):
                e.name = safe_name(f"{e.path.parent.name}-{e.name}")
            if e.name in seen:
                raise SettingError(f"two inputs are both named {literal(repr(e.name))} ({literal(other.path)}, "
                                   f"{literal(e.path)}); renders/<name>/ needs distinct names (give name = \"...\" in the "
                                   "{0} list)", "inputs")
        seen[e.name] = e
    return out


# --------------------------------------------------------------------------------------------------------------
# triplet folders
# --------------------------------------------------------------------------------------------------------------


def _natural(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def _triplet_files(folder: Path) -> dict[str, dict[str, Path]]:
    """``{view stem: {role: path}}`` of a triplet folder (flat suffixes or role subfolders)."""
    views: dict[str, dict[str, Path]] = {}
    if (folder / _SUBFOLDERS["obj"]).is_dir():
        for role, sub in _SUBFOLDERS.items():
            d = folder / sub
            if d.is_dir():
                for f in sorted(d.iterdir()):
                    if f.suffix.lower() in IMAGE_SUFFIXES + (".npy",):
                        views.setdefault(f.stem, {})[role] = f
        return views
    for f in sorted(folder.iterdir()):
        if f.suffix.lower() not in IMAGE_SUFFIXES + (".npy",):
            continue
        for role, suffixes in _ROLE_SUFFIXES.items():
            m = re.match(rf"^(.*?)[_-]({'|'.join(suffixes)})$", f.stem, flags=re.IGNORECASE)
            if m and m.group(1):
                views.setdefault(m.group(1), {})[role] = f
                break
    return views


def _read_rgb8(path: Path, warnings: list[str]) -> tuple[np.ndarray, np.ndarray | None]:
    """``(H, W, 3)`` uint8 sRGB (and the linear image for EXR input)."""
    from PIL import Image, UnidentifiedImageError

    from camo_base.imaging import linear_to_srgb, load_exr, to_uint8

    if path.suffix.lower() == ".exr":
        try:
            lin = np.asarray(load_exr(path), dtype=np.float32)
        except Exception as exc:  # OpenEXR raises several types
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise CamoError(f"{path}: cannot read EXR ({why})") from None
        lin = lin[..., :3] if lin.ndim == 3 else np.repeat(lin[..., None], 3, -1)
        if not np.isfinite(lin).all():
            raise CamoError(f"{path}: contains NaN or infinite values")
        return to_uint8(linear_to_srgb(lin)), lin
    try:
        with Image.open(path) as im:
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                a = np.round(np.asarray(im, dtype=np.float64) / 257.0).clip(0, 255).astype(np.uint8)
                return np.repeat(a[..., None], 3, -1), None
            if "A" in im.getbands():
                alpha = np.asarray(im.getchannel("A"))
                if alpha.min() < 255:
                    warnings.append(f"{path.name}: alpha channel ignored")
            a = np.asarray(im.convert("RGB"))
            if a.dtype != np.uint8:
                a = a.astype(np.uint8)
            return a, None
    except (UnidentifiedImageError, OSError) as exc:
        raise CamoError(f"{path}: cannot read image ({exc})") from None


def _read_mask(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    if path.suffix.lower() == ".npy":
        try:
            return np.asarray(np.load(path, allow_pickle=False)).astype(np.float64) >= 0.5
        except Exception as exc:
            raise CamoError(f"{path}: cannot read ({type(exc).__name__})") from None
    try:
        with Image.open(path) as im:
            a = np.asarray(im.convert("L"))
    except (UnidentifiedImageError, OSError) as exc:
        raise CamoError(f"{path}: cannot read mask ({exc})") from None
    return a >= 128


def _read_depth(path: Path) -> np.ndarray:
    from camo_base.imaging import load_exr

    try:
        d = np.load(path, allow_pickle=False) if path.suffix.lower() == ".npy" else load_exr(path)
    except Exception as exc:
        raise CamoError(f"{path}: cannot read depth ({type(exc).__name__})") from None
    d = np.asarray(d, dtype=np.float32)
    if d.ndim == 3:
        d = d[..., 0]
    if d.ndim != 2 or not np.isfinite(d).all() or (d < 0).any():
        raise CamoError(f"{path}: depth must be an (H, W) map of finite distances >= 0 (scene units, 0 = no hit)")
    return d


def read_triplets(folder: str | Path) -> tuple[Triplets, list[str]]:
    """Read a triplet folder (see the module docstring); CamoError for missing or mismatched files."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CamoError(f"triplet folder not found: {folder}")
    files = _triplet_files(folder)
    if not files:
        raise CamoError(f"{folder}: no triplets (expected <view>_obj.png, <view>_bg.png, <view>_mask.png, or "
                        "subfolders with_object/, background/, mask/)")
    warnings: list[str] = []
    stems = sorted(files, key=_natural)
    obj, bg, mask, depth, lin_o, lin_b = [], [], [], [], [], []
    for stem in stems:
        roles = files[stem]
        missing = [r for r in ("obj", "bg", "mask") if r not in roles]
        if missing:
            raise CamoError(f"{folder}: view {stem!r} lacks its {' and '.join(missing)} image")
        o, lo = _read_rgb8(roles["obj"], warnings)
        b, lb = _read_rgb8(roles["bg"], warnings)
        m = _read_mask(roles["mask"])
        if o.shape != b.shape or m.shape != o.shape[:2]:
            raise CamoError(f"{folder}: view {stem!r}: image sizes differ (with object {o.shape[1]}x{o.shape[0]}, "
                            f"background {b.shape[1]}x{b.shape[0]}, mask {m.shape[1]}x{m.shape[0]})")
        if obj and o.shape != obj[0].shape:
            raise CamoError(f"{folder}: view {stem!r} is {o.shape[1]}x{o.shape[0]} px, view {stems[0]!r} "
                            f"{obj[0].shape[1]}x{obj[0].shape[0]}; all views must have one size")
        obj.append(o)
        bg.append(b)
        mask.append(m)
        lin_o.append(lo)
        lin_b.append(lb)
        if "depth" in roles:
            d = _read_depth(roles["depth"])
            if d.shape != m.shape:
                raise CamoError(f"{roles['depth']}: depth is {d.shape[1]}x{d.shape[0]}, the images {m.shape[1]}x"
                                f"{m.shape[0]}")
            depth.append(d)
    if depth and len(depth) != len(stems):
        raise CamoError(f"{folder}: depth is given for {len(depth)} of {len(stems)} views; give it for all or none")
    exr = all(x is not None for x in lin_o + lin_b)
    return Triplets(stems, np.stack(obj), np.stack(bg), np.stack(mask), np.stack(depth) if depth else None,
                    np.stack(lin_o) if exr else None, np.stack(lin_b) if exr else None), warnings
