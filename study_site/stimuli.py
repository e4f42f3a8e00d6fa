"""Stimulus sets for the click-to-find study (``camo study build-stimuli``).

Input: one or more evaluation directories (see CONTRIBUTING.md); each has a
``renders.json`` listing ``{run, scene, object, method, ablation, view, image,
background, mask, ...}`` with paths relative to the directory. ``image`` is the
sRGB PNG of the render *with* the object, ``mask`` a PNG (0/255) of the
object's visible pixels.

Output (``STIMULI_DIR``)::

    STIMULI_DIR/
      manifest.json        server-side only: id -> run/scene/method/view/files
      images/<id>.webp     what a participant sees: lossless WebP (checked pixel-identical when written)
      images/<id>.png      the same pixels as PNG (fallback; re-encoded, no metadata)
      reveal/<rid>.webp    image with the object's outline drawn (and .png); served only
                           after the participant answered that trial
      masks/<id>.png       server-side only (hit test)

``<id>`` and ``<rid>`` are independent random tokens (``secrets``), so nothing
that reaches a browser before the click (URL, file name, bytes) carries the
scene, the method, the mask or the outline. Images are decoded and re-encoded
with Pillow so PNG text chunks of the source files are dropped.

Two ways to make the images: :mod:`study_site.render_stimuli` re-renders every
evaluated run at study size with the object at varied, recorded positions and
sizes (``camo study build-stimuli``, the default), and :func:`build_stimuli`
here copies the evaluation renders as they are (``--copy``; their object sits at
the frame centre, which the summary reports). Both record per stimulus where the
object is (``centroid_x/y`` as fractions of width/height, ``bbox``, ``area_share``,
``centre_hit``: whether a click on the centre pixel would hit).

Practice never shares a scene with the formal trials: practice stimuli come from
``--practice`` evaluation directories, from scenes named with
``--practice-scenes`` (taken out of the formal pool), or, by default, from a
synthetic practice set (procedural textures with a low-contrast blob; scene
names ``practice_synthetic_NN``). A set whose practice and formal scenes overlap
is refused when built and when loaded.
"""

from __future__ import annotations

import json
import secrets
import sys
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from camo_base.atomic import atomic_path, write_json
from camo_base.errors import CamoError, SettingError, literal
from evaluation.evaldir import read_renders
from optimizer.assets.conditions import condition

MANIFEST_VERSION = 3  # 3: condition, label, phash, environment, background_phash; WebP beside every PNG
READABLE_VERSIONS = (1, 2, 3)
SYNTHETIC_SCENE = "practice_synthetic"
PRACTICE_METHOD = "practice"  # the synthetic practice images' method (no condition of the study)
OUTLINE_RGB = (255, 40, 200)  # magenta: rarely present in natural backgrounds


@dataclass(frozen=True)
class Stimulus:
    """One entry of a stimulus set's manifest (server-side)."""

    id: str
    reveal_id: str
    run: str
    scene: str
    object: str
    method: str
    ablation: str
    view: str
    practice: bool
    width: int
    height: int
    mask_pixels: int
    centroid_x: float | None = None  # object's mask centroid, fraction of the width (0 left)
    centroid_y: float | None = None  # fraction of the height (0 top)
    area_share: float | None = None  # mask pixels / image pixels
    centre_hit: bool | None = None  # the centre pixel (width // 2, height // 2) lies on the object
    #: the condition's id and label (:mod:`optimizer.assets.conditions`), always derived from method + ablation
    condition: str = ""
    label: str = ""

    def __post_init__(self):
        c = condition(self.method, self.ablation)
        object.__setattr__(self, "condition", c.id)
        object.__setattr__(self, "label", c.label)
        object.__setattr__(self, "ablation", c.ablation)


# ---------------------------------------------------------------------------
# reading a stimulus set
# ---------------------------------------------------------------------------


class StimulusSet:
    """A built stimulus set loaded from ``manifest.json``; masks are cached on first use."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        mpath = self.root / "manifest.json"
        if not mpath.is_file():
            raise CamoError(f"{self.root}: no manifest.json (build it with `camo study build-stimuli`)")
        try:
            data = json.loads(mpath.read_text(encoding="utf-8"))
            if data.get("version") not in READABLE_VERSIONS:
                raise CamoError(f"{mpath}: unsupported manifest version {data.get('version')!r}")
            self.stimuli = [
                Stimulus(**{k: s[k] for k in Stimulus.__dataclass_fields__ if k in s}) for s in data["stimuli"]
            ]
        except CamoError:
            raise
        except (ValueError, KeyError, TypeError) as exc:
            raise CamoError(f"{mpath}: malformed manifest ({exc})") from None
        if not any(not s.practice for s in self.stimuli):
            raise CamoError(f"{mpath}: the stimulus set has no (non-practice) stimuli")
        check_no_leak(
            {s.scene for s in self.stimuli if not s.practice}, {s.scene for s in self.stimuli if s.practice}, mpath
        )
        self.data = data
        self._check_content(mpath)
        self.by_id = {s.id: s for s in self.stimuli}
        self.by_reveal = {s.reveal_id: s for s in self.stimuli}
        self._masks: dict[str, np.ndarray] = {}

    def _check_content(self, where) -> None:
        """Practice vs formal by content (:func:`check_no_content_leak`); hashes of a manifest written before they
        were recorded are computed from the images."""
        entries = self.data["stimuli"]
        if not any(e.get("practice") for e in entries):
            return
        rows = []
        for e, st in zip(entries, self.stimuli):
            row = dict(e)
            if not row.get("phash"):
                row["phash"] = phash(_load_rgb(self.image_path(st)))
            rows.append(row)
        check_no_content_leak(rows, where)

    # files ---------------------------------------------------------------
    def image_path(self, stim: Stimulus, ext: str = ".png") -> Path:
        return self.root / "images" / f"{stim.id}{ext}"

    def reveal_path(self, stim: Stimulus, ext: str = ".png") -> Path:
        return self.root / "reveal" / f"{stim.reveal_id}{ext}"

    def image_names(self, stim: Stimulus) -> tuple[str, str]:
        """``(preferred, fallback)`` file names under ``/i/``: ``<id>.webp`` and ``<id>.png`` (a set built before
        WebP: the PNG twice)."""
        png = f"{stim.id}.png"
        return (f"{stim.id}.webp", png) if self.image_path(stim, ".webp").is_file() else (png, png)

    def static_files(self) -> dict:
        """``{file name: serving.StaticFile}`` of every stimulus image (both formats), with content-hash ETags."""
        from study_site.serving import static_file

        out = {}
        for st in self.stimuli:
            for name in set(self.image_names(st)):
                p = self.root / "images" / name
                if not p.is_file():
                    raise CamoError(f"{p}: stimulus image missing (rebuild the set with `camo study build-stimuli`)")
                out[name] = static_file(p)
        return out

    def mask_path(self, stim: Stimulus) -> Path:
        return self.root / "masks" / f"{stim.id}.png"

    def mask(self, stim: Stimulus) -> np.ndarray:
        """``(H, W)`` bool mask of the object's visible pixels (cached)."""
        m = self._masks.get(stim.id)
        if m is None:
            m = load_mask(self.mask_path(stim))
            self._masks[stim.id] = m
        return m

    def hit(self, stim: Stimulus, x: int, y: int, tolerance_px: int = 0) -> bool:
        """Whether image pixel ``(x, y)`` (column, row) lies on the object (within ``tolerance_px``)."""
        m = self.mask(stim)
        h, w = m.shape
        if not (0 <= x < w and 0 <= y < h):
            return False
        if tolerance_px <= 0:
            return bool(m[y, x])
        y0, y1 = max(0, y - tolerance_px), min(h, y + tolerance_px + 1)
        x0, x1 = max(0, x - tolerance_px), min(w, x + tolerance_px + 1)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        near = (yy - y) ** 2 + (xx - x) ** 2 <= tolerance_px**2
        return bool(np.any(m[y0:y1, x0:x1] & near))

    # pools ---------------------------------------------------------------
    def formal_pool(self) -> dict[str, dict[str, list[Stimulus]]]:
        """scene -> condition -> stimuli (one per view), non-practice stimuli only."""
        pool: dict[str, dict[str, list[Stimulus]]] = {}
        for s in self.stimuli:
            if not s.practice:
                pool.setdefault(s.scene, {}).setdefault(s.condition, []).append(s)
        return pool

    def practice_pool(self) -> list[Stimulus]:
        """The set's dedicated practice stimuli (their scenes are never formal scenes); may be empty."""
        return [s for s in self.stimuli if s.practice]


def check_no_leak(formal_scenes: set[str], practice_scenes: set[str], where: Any = "stimulus set") -> None:
    """CamoError when a practice scene is also a formal scene (practice would show where the object sits)."""
    both = sorted(formal_scenes & practice_scenes)
    if both:
        raise CamoError(
            f"{where}: practice scene(s) {', '.join(both)[:200]} also appear in the formal trials (practice would "
            "reveal where the object is); use other scenes for practice"
        )


#: Largest Hamming distance (of 64 bits) between the perceptual hashes of a practice and a formal image (or
#: background) that counts as "the same picture". Measured on 24 real 512-px stimuli (gravel, meadow, panorama;
#: docs/study.md): a JPEG q80 re-encode 0-2; backgrounds of different framings 16 at least (median 32); images of
#: other views or scenes 18 at least. The object moves an image's hash by 2-34 bits (the same framing with another
#: object is not "the same picture"), which is why backgrounds are compared with backgrounds as well.
PHASH_MAX_DISTANCE = 8


def background_path(root: str | Path, scene: str, view: str | int) -> Path:
    """Where a rendered set keeps the object-free render of ``scene``'s view ``view`` (``backgrounds/``, shared by
    every method of that framing; never served). It may not exist (``--copy`` sets, practice)."""
    import hashlib

    return Path(root) / "backgrounds" / f"{hashlib.sha256(f'{scene}:{view}'.encode()).hexdigest()[:16]}.png"


def surface_path(root: str | Path, scene: str, view: str | int) -> Path:
    """Where a rendered set keeps the world-space surface normals of the object-free render of ``scene``'s view
    ``view`` (beside :func:`background_path`; ``normals`` ``(H, W, 3)`` float16, zeros where no surface is seen):
    the simulated observer's surfaces (:func:`evaluation.observer.surface_labels`). Absent in sets built before
    it (``camo study surfaces`` adds it) and in ``--copy`` sets."""
    p = background_path(root, scene, view)
    return p.with_name(p.stem + "_normals.npz")


def save_normals(path: Path, normals: np.ndarray) -> None:
    """Write ``normals`` ``(H, W, 3)`` to ``path`` (:func:`surface_path`), atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, normals=np.asarray(normals, np.float16))


def load_normals(path: Path, shape: tuple[int, int]) -> np.ndarray | None:
    """The normals of :func:`surface_path` as float32 ``(H, W, 3)``, or None when the file is absent or of another
    size than ``shape`` (``(H, W)``: not this framing's)."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            n = np.asarray(z["normals"], np.float32)
    except (OSError, KeyError, ValueError) as e:
        raise CamoError(f"{path}: unreadable surface normals ({e})") from None
    return n if n.shape == (*shape, 3) else None


def phash(rgb: np.ndarray) -> str:
    """64-bit DCT perceptual hash (``imagehash.phash``: 32 x 32 greyscale, 8 x 8 lowest frequencies against their
    median) of an ``(H, W, 3)`` uint8 sRGB image, as 16 hex digits."""
    import imagehash
    from PIL import Image

    return str(imagehash.phash(Image.fromarray(np.asarray(rgb, dtype=np.uint8))))


def phash_distance(a: str, b: str) -> int:
    """Hamming distance of two :func:`phash` values."""
    return bin(int(a, 16) ^ int(b, 16)).count("1")


def environment_key(env_spec) -> str:
    """What a scene pack's ``[environment]`` shows, by content: ``builtin:NAME``, or the SHA-256 (first 16 hex) of
    its panorama or Mitsuba XML file, so a panorama copied under another name is still the same environment."""
    import hashlib

    if env_spec.builtin:
        return f"builtin:{env_spec.builtin}"
    path = env_spec.panorama or env_spec.xml
    kind = "panorama" if env_spec.panorama else "xml"
    try:
        digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    except OSError:
        digest = f"missing:{Path(path).name}"
    return f"{kind}:{digest}"


def check_no_content_leak(stimuli: list[dict[str, Any]], where: Any = "stimulus set") -> None:
    """CamoError (one line) when practice shows what a formal trial shows, judged by content, not names:

    * the same environment (:func:`environment_key`: a built-in, or the same panorama/XML bytes) -- e.g. practice
      ``meadow:teapot`` with formal ``meadow``: same grass, sun and camera orbit;
    * a practice image or background whose perceptual hash is within :data:`PHASH_MAX_DISTANCE` bits of a formal
      one's (the same view under another scene name, copied renders).

    ``stimuli``: manifest entries with ``practice``, ``scene`` and, where known, ``environment``, ``phash`` and
    ``background_phash``."""
    formal = [s for s in stimuli if not s["practice"]]
    practice = [s for s in stimuli if s["practice"]]
    envs = {s["environment"]: s["scene"] for s in formal if s.get("environment")}
    for p in practice:
        if p.get("environment") and p["environment"] in envs:
            raise CamoError(
                f"{where}: practice scene {p['scene']} shows the same environment ({p['environment']}) as formal "
                f"scene {envs[p['environment']]} (practice would reveal the formal backgrounds); use another "
                "environment for practice")
    for key in ("phash", "background_phash"):
        fh = [(s[key], s) for s in formal if s.get(key)]
        for p in practice:
            if not p.get(key):
                continue
            for h, f in fh:
                d = phash_distance(p[key], h)
                if d <= PHASH_MAX_DISTANCE:
                    what = "image" if key == "phash" else "background"
                    raise CamoError(
                        f"{where}: practice {what} of scene {p['scene']} (view {p['view']}) looks like formal scene "
                        f"{f['scene']} (view {f['view']}; perceptual hashes {d} of 64 bits apart, <= "
                        f"{PHASH_MAX_DISTANCE}); use other images for practice")


def placement(mask: np.ndarray) -> dict[str, Any]:
    """Where the object is in the frame: centroid (fractions), bbox (px, half-open), area share, centre hit."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return {"centroid_x": None, "centroid_y": None, "bbox": None, "area_share": 0.0, "centre_hit": False}
    return {
        "centroid_x": float((xs.mean() + 0.5) / w),
        "centroid_y": float((ys.mean() + 0.5) / h),
        "bbox": [int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1],
        "area_share": float(len(xs) / (w * h)),
        "centre_hit": bool(mask[h // 2, w // 2]),
    }


def load_mask(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        arr = np.asarray(im.convert("L"))
    return arr > 127


# ---------------------------------------------------------------------------
# building a stimulus set
# ---------------------------------------------------------------------------


def _load_rgb(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise CamoError(f"{path}: file not found")
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError) as exc:
        raise CamoError(f"{path}: cannot read image ({exc})") from None


def _load_mask_checked(path: Path) -> np.ndarray:
    from PIL import UnidentifiedImageError

    if not path.is_file():
        raise CamoError(f"{path}: file not found")
    try:
        return load_mask(path)
    except (UnidentifiedImageError, OSError) as exc:
        raise CamoError(f"{path}: cannot read mask ({exc})") from None


def outline_overlay(rgb: np.ndarray, mask: np.ndarray, thickness: int | None = None) -> np.ndarray:
    """``rgb`` (H, W, 3) uint8 with the boundary of ``mask`` drawn as a solid line.

    The line is the mask's inner boundary (mask minus its erosion) dilated by
    ``thickness`` pixels (default: ~0.4% of the smaller image side, at least 2),
    drawn with a dark halo so it stays visible on light and dark backgrounds.
    """
    from scipy import ndimage

    h, w = mask.shape
    t = thickness if thickness is not None else max(2, round(min(h, w) / 250))
    boundary = mask & ~ndimage.binary_erosion(mask, border_value=0)
    line = ndimage.binary_dilation(boundary, iterations=t)
    halo = ndimage.binary_dilation(line, iterations=max(1, t // 2)) & ~line
    out = rgb.copy()
    out[halo] = (out[halo].astype(np.uint16) // 3).astype(np.uint8)
    out[line] = OUTLINE_RGB
    return out


def _save_png(path: Path, arr: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG", optimize=False)


def _save_webp_lossless(path: Path, arr: np.ndarray) -> None:
    """Lossless WebP of an ``(H, W, 3)`` uint8 image, decoded again and compared with ``arr``: a pixel that differs
    is an error (CamoError), never a silently changed stimulus.

    Effort ``method=2, quality=75``: measured on a 480 x 320 noisy image, 0.5 s and 156 KB, against 77 s and 155 KB
    for the maximum (``method=6, quality=100``) and 260 KB for the PNG (libwebp 1.x through Pillow 13)."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="WEBP", lossless=True, quality=75, method=2, exact=True)
        with Image.open(tmp) as im:
            back = np.asarray(im.convert("RGB"))
        if back.shape != arr.shape or not np.array_equal(back, arr):
            raise CamoError(f"{path}: the WebP encoder changed pixels (lossless expected); Pillow's libwebp is broken")


def _save_image(stem: Path, arr: np.ndarray) -> None:
    """``stem.png`` and ``stem.webp`` (lossless, verified pixel-identical) of one served image."""
    _save_png(stem.with_suffix(".png"), arr)
    _save_webp_lossless(stem.with_suffix(".webp"), arr)


class StimulusWriter:
    """Writes images/, masks/, reveal/ of a new stimulus set, then manifest.json (last, atomically)."""

    def __init__(self, out_dir: str | Path, force: bool = False):
        self.out = Path(out_dir)
        if (self.out / "manifest.json").exists() and not force:
            raise SettingError(
                f"{literal(self.out)}: already holds a stimulus set; a rebuild gives new ids, which breaks a running "
                "study (use another {0}, or {1})", "out", "force"
            )
        self.stimuli: list[dict[str, Any]] = []

    def add(self, rgb: np.ndarray, mask: np.ndarray, meta: dict[str, Any], practice: bool) -> dict[str, Any]:
        cond = condition(str(meta["method"]), meta.get("ablation"))
        sid = secrets.token_urlsafe(12)
        rid = secrets.token_urlsafe(12)
        _save_image(self.out / "images" / sid, rgb)
        _save_png(self.out / "masks" / f"{sid}.png", mask.astype(np.uint8) * 255)
        _save_image(self.out / "reveal" / rid, outline_overlay(rgb, mask))
        entry = {
            "phash": phash(rgb),
            "id": sid,
            "reveal_id": rid,
            "run": str(meta["run"]),
            "scene": str(meta["scene"]),
            "object": str(meta.get("object") or ""),
            "method": str(meta["method"]),
            "ablation": cond.ablation,
            "condition": cond.id,
            "label": cond.label,
            "view": str(meta["view"]),
            "practice": bool(practice),
            "width": int(rgb.shape[1]),
            "height": int(rgb.shape[0]),
            "mask_pixels": int(mask.sum()),
            **placement(mask),
            **{k: v for k, v in meta.items() if k not in ("run", "scene", "object", "method", "ablation", "view", "condition", "label")},
        }
        self.stimuli.append(entry)
        return entry

    def finish(self, sources: list[str], **extra) -> dict[str, Any]:
        if not any(not s["practice"] for s in self.stimuli):
            raise CamoError("no usable stimuli: every formal render entry was skipped")
        check_no_leak(
            {s["scene"] for s in self.stimuli if not s["practice"]},
            {s["scene"] for s in self.stimuli if s["practice"]},
            self.out,
        )
        check_no_content_leak(self.stimuli, self.out)
        manifest = {
            "version": MANIFEST_VERSION,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "sources": sources,
            **extra,
            "stimuli": self.stimuli,
        }
        write_json(self.out / "manifest.json", manifest)  # written last: a set without manifest is incomplete
        return manifest


def practice_split(
    formal_scenes: set[str], practice_dir_scenes: set[str], practice_scenes: list[str] | None
) -> set[str]:
    """Scenes taken out of the formal pool for practice (``--practice-scenes``); refuses a leaking set."""
    named = {s.strip() for s in (practice_scenes or []) if s.strip()}
    unknown = sorted(named - formal_scenes - practice_dir_scenes)
    if unknown:
        raise SettingError.of("practice_scenes", f": no such scene {', '.join(unknown)} (scenes: {', '.join(sorted(formal_scenes))})")
    if named and named >= formal_scenes:
        raise SettingError.of("practice_scenes", " names every scene: no formal scene would be left")
    check_no_leak(formal_scenes - named, practice_dir_scenes, "--practice")
    return named


def synthetic_practice(n: int, size: tuple[int, int], seed: int = 0):
    """``n`` procedural practice images: ``[(rgb uint8 (H, W, 3), mask (H, W) bool, meta)]``.

    Background: smooth random colour field with pixel noise. Object: an ellipse (axes 6-13 % of the smaller
    side, centre uniform where it fits) filled with a shifted copy of the background, tinted and 25 %
    brighter or darker, so it is findable with some search. Scenes are named ``practice_synthetic_NN``.
    """
    from PIL import Image

    rng = np.random.default_rng(10_000 + seed)
    w, h = size
    out = []
    for i in range(n):
        gh, gw = max(2, h // 48), max(2, w // 48)
        lum = rng.uniform(60, 200, (gh, gw, 1))
        tint = rng.normal(0, 1, 3) * 20 + rng.normal(0, 1, (gh, gw, 3)) * 12
        coarse = np.clip(lum + tint, 0, 255).astype(np.uint8)
        bg = np.asarray(Image.fromarray(coarse).resize((w, h), Image.BICUBIC), dtype=np.float32)
        bg += rng.normal(0, 7, (h, w, 1))
        m = min(w, h)
        ax, ay = rng.uniform(0.06, 0.13) * m, rng.uniform(0.06, 0.13) * m
        cx, cy = rng.uniform(ax + 2, w - ax - 2), rng.uniform(ay + 2, h - ay - 2)
        yy, xx = np.mgrid[0:h, 0:w]
        mask = ((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2 <= 1.0
        shifted = np.roll(bg, (int(rng.integers(h // 4, h // 2)), int(rng.integers(w // 4, w // 2))), axis=(0, 1))
        gain = 1.25 if rng.random() < 0.5 else 0.8
        obj = np.clip(shifted * gain + rng.normal(0, 6, 3), 0, 255)
        img = np.where(mask[..., None], obj, bg)
        meta = {"run": SYNTHETIC_SCENE, "scene": f"{SYNTHETIC_SCENE}_{i:02d}", "object": "blob",
                "method": PRACTICE_METHOD, "ablation": "", "view": "0", "environment": "synthetic"}
        out.append((np.clip(img, 0, 255).astype(np.uint8), mask, meta))
    return out


def environments_of_eval_dir(eval_dir: Path) -> dict[str, str]:
    """``{input name: environment_key}`` of the inputs an evaluation directory lists (its eval_config.toml), read
    from each run's config.toml or each asset's scene; inputs whose scene can no longer be read are left out (their
    images are still compared by perceptual hash)."""
    from evaluation.evaldir import read_eval_config

    out: dict[str, str] = {}
    try:
        records = [r for r in (read_eval_config(eval_dir) or {}).get("runs") or [] if isinstance(r, dict)]
    except CamoError:
        return out
    for r in records:
        name, kind, path = str(r.get("name", "")), str(r.get("kind", "run")), Path(str(r.get("path", "")))
        try:
            if kind == "run":
                from optimizer.assets.rundir import pack_from_config, read_config

                pack = pack_from_config(read_config(path), path)
            elif kind == "asset":
                from optimizer.scenes.builtin_scenes import resolve_scene

                pack = resolve_scene(str(r.get("scene_source") or r.get("scene") or ""))
            else:
                continue
        except (CamoError, OSError):
            continue
        out[name] = environment_key(pack.environment)
    return out


def build_stimuli(
    eval_dirs: list[str | Path],
    out_dir: str | Path,
    practice_dirs: list[str | Path] | None = None,
    force: bool = False,
    log=None,
    practice_scenes: list[str] | None = None,
    synthetic_practice_n: int = 8,
) -> dict[str, Any]:
    """Export a stimulus set by copying evaluation renders as they are (``--copy``); returns the manifest.

    Entries whose mask is empty (object fully hidden in that view) are skipped
    with a warning: nothing could be clicked. Duplicate ``(run, view)`` entries
    are kept once. Practice: ``practice_dirs`` (scenes must differ from the formal
    ones), ``practice_scenes`` (named scenes of ``eval_dirs`` become practice only),
    else ``synthetic_practice_n`` synthetic images (0: none).
    """
    log = log or (lambda msg: print(msg, file=sys.stderr))
    writer = StimulusWriter(out_dir, force)
    if not eval_dirs:
        raise CamoError("build-stimuli needs at least one EVAL_DIR")

    sources: list[tuple[Path, bool]] = [(Path(d), False) for d in eval_dirs]
    sources += [(Path(d), True) for d in (practice_dirs or [])]
    plan: list[tuple[Path, dict[str, Any], bool]] = []
    for d, practice in sources:
        for e in read_renders(d):
            plan.append((d, e, practice))
    formal_scenes = {str(e["scene"]) for _, e, p in plan if not p}
    named = practice_split(formal_scenes, {str(e["scene"]) for _, e, p in plan if p}, practice_scenes)
    plan = [(d, e, p or str(e["scene"]) in named) for d, e, p in plan]

    envs = {str(d): environments_of_eval_dir(d) for d, _ in sources}
    seen: set[tuple[str, str, bool]] = set()
    skipped_empty = 0
    sizes = []
    for d, e, practice in plan:
        key = (str(e["run"]), str(e["view"]), practice)
        if key in seen:
            log(f"warning: duplicate render entry run={e['run']} view={e['view']} in {d}; kept once")
            continue
        seen.add(key)
        rgb = _load_rgb(d / str(e["image"]))
        mask = _load_mask_checked(d / str(e["mask"]))
        if mask.shape != rgb.shape[:2]:
            raise CamoError(
                f"{d / str(e['mask'])}: mask is {mask.shape[1]}x{mask.shape[0]} but the image is "
                f"{rgb.shape[1]}x{rgb.shape[0]}"
            )
        if not mask.any():
            skipped_empty += 1
            log(f"warning: empty mask for run={e['run']} view={e['view']} (object not visible); skipped")
            continue
        sizes.append((rgb.shape[1], rgb.shape[0]))
        meta = {k: e.get(k) for k in ("run", "scene", "object", "method", "ablation", "view")}
        meta["source_image"] = str((d / str(e["image"])).resolve())
        if envs[str(d)].get(str(e["run"])):
            meta["environment"] = envs[str(d)][str(e["run"])]
        if e.get("background") and (d / str(e["background"])).is_file():
            meta["background_phash"] = phash(_load_rgb(d / str(e["background"])))
        writer.add(rgb, mask, meta, practice)
    has_practice = any(s["practice"] for s in writer.stimuli)
    if not has_practice and synthetic_practice_n > 0 and sizes:
        size = max(set(sizes), key=sizes.count)
        for rgb, mask, meta in synthetic_practice(synthetic_practice_n, size):
            writer.add(rgb, mask, meta, True)
    return writer.finish(
        [str(d.resolve()) for d, _ in sources],
        mode="copy",
        placement="as rendered by `camo evaluate` (orbit cameras aimed at the object: it sits at the centre)",
        skipped_empty_masks=skipped_empty,
    )


def summarize(manifest: dict[str, Any]) -> str:
    formal = [s for s in manifest["stimuli"] if not s["practice"]]
    scenes = sorted({s["scene"] for s in formal})
    conds = sorted({condition(s["method"], s["ablation"]).label for s in formal})
    cells = {(s["scene"], condition(s["method"], s["ablation"]).id) for s in formal}
    practice = [s for s in manifest["stimuli"] if s["practice"]]
    missing = len(scenes) * len(conds) - len(cells)
    text = (
        f"{len(formal)} stimuli: {len(scenes)} scenes x {len(conds)} methods ({', '.join(conds)}), "
        f"{len(cells)} cells"
    )
    if missing:
        text += f" ({missing} scene x method cells have no render)"
    if practice:
        pscenes = sorted({s["scene"] for s in practice})
        text += f"; {len(practice)} practice stimuli from {len(pscenes)} other scene(s)"
    b = location_baselines(manifest)
    if b["n"]:
        text += (
            f"; centre click hits {b['centre_hits']}/{b['n']} ({100 * b['centre_hit_rate']:.1f} %), "
            f"mean object area share {100 * b['mean_area_share']:.1f} %"
        )
    return text


def location_baselines(manifest: dict[str, Any]) -> dict[str, Any]:
    """Formal stimuli: how often a click at the centre pixel hits, next to the object's mean area share.

    Under a uniform spread of positions the centre-click hit rate is close to the area share; an object
    always at the centre gives 100 %.
    """
    formal = [s for s in manifest["stimuli"] if not s["practice"] and s.get("centre_hit") is not None]
    n = len(formal)
    hits = sum(bool(s["centre_hit"]) for s in formal)
    share = float(np.mean([s["area_share"] for s in formal])) if n else float("nan")
    return {"n": n, "centre_hits": hits, "centre_hit_rate": hits / n if n else float("nan"), "mean_area_share": share}
