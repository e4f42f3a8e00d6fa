"""Stimulus sets for the click-to-find study (``camo study build-stimuli``).

Input: one or more evaluation directories (see CONTRIBUTING.md); each has a
``renders.json`` listing ``{run, scene, object, method, ablation, view, image,
background, mask, ...}`` with paths relative to the directory. ``image`` is the
sRGB PNG of the render *with* the object, ``mask`` a PNG (0/255) of the
object's visible pixels.

Output (``STIMULI_DIR``)::

    STIMULI_DIR/
      manifest.json        server-side only: id -> run/scene/method/view/files
      images/<id>.png      what a participant sees (re-encoded, no metadata)
      reveal/<rid>.png     image with the object's outline drawn; served only
                           after the participant answered that trial
      masks/<id>.png       server-side only (hit test)

``<id>`` and ``<rid>`` are independent random tokens (``secrets``), so nothing
that reaches a browser before the click (URL, file name, bytes) carries the
scene, the method, the mask or the outline. Images are decoded and re-encoded
with Pillow so PNG text chunks of the source files are dropped.
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

from optimizer.atomic import atomic_path, write_json
from optimizer.errors import CamoError

MANIFEST_VERSION = 1
REQUIRED_KEYS = ("run", "scene", "method", "view", "image", "mask")
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

    @property
    def condition(self) -> str:
        """Method label used in the analysis: ``method`` or ``method+ablation``."""
        return condition_label(self.method, self.ablation)


def condition_label(method: str, ablation: str | None) -> str:
    ab = (ablation or "").strip()
    if ab.lower() in ("", "none", "full", "null"):
        return method
    return f"{method}+{ab}"


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
            if data.get("version") != MANIFEST_VERSION:
                raise CamoError(f"{mpath}: unsupported manifest version {data.get('version')!r}")
            self.stimuli = [Stimulus(**{k: s[k] for k in Stimulus.__dataclass_fields__}) for s in data["stimuli"]]
        except CamoError:
            raise
        except (ValueError, KeyError, TypeError) as exc:
            raise CamoError(f"{mpath}: malformed manifest ({exc})") from None
        if not any(not s.practice for s in self.stimuli):
            raise CamoError(f"{mpath}: the stimulus set has no (non-practice) stimuli")
        self.by_id = {s.id: s for s in self.stimuli}
        self.by_reveal = {s.reveal_id: s for s in self.stimuli}
        self._masks: dict[str, np.ndarray] = {}

    # files ---------------------------------------------------------------
    def image_path(self, stim: Stimulus) -> Path:
        return self.root / "images" / f"{stim.id}.png"

    def reveal_path(self, stim: Stimulus) -> Path:
        return self.root / "reveal" / f"{stim.reveal_id}.png"

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
        """Dedicated practice stimuli if the set has any, else every stimulus."""
        dedicated = [s for s in self.stimuli if s.practice]
        return dedicated or list(self.stimuli)


def load_mask(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        arr = np.asarray(im.convert("L"))
    return arr > 127


# ---------------------------------------------------------------------------
# building a stimulus set
# ---------------------------------------------------------------------------


def _read_renders(eval_dir: Path) -> list[dict[str, Any]]:
    rj = eval_dir / "renders.json"
    if not eval_dir.is_dir():
        raise CamoError(f"{eval_dir}: not a directory")
    if not rj.is_file():
        raise CamoError(f"{eval_dir}: no renders.json (is this an evaluation directory from `camo evaluate`?)")
    try:
        entries = json.loads(rj.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise CamoError(f"{rj}: not valid JSON ({exc})") from None
    if not isinstance(entries, list):
        raise CamoError(f"{rj}: expected a JSON list of render entries")
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise CamoError(f"{rj}: entry {i} is not an object")
        missing = [k for k in REQUIRED_KEYS if e.get(k) in (None, "")]
        if missing:
            raise CamoError(f"{rj}: entry {i} lacks {', '.join(missing)}")
        for k, limit in (("run", 256), ("scene", 256), ("object", 256), ("method", 120), ("ablation", 120), ("view", 64)):
            if len(str(e.get(k) or "")) > limit:
                raise CamoError(f"{rj}: entry {i}: {k} is longer than {limit} characters")
    return entries


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


def build_stimuli(
    eval_dirs: list[str | Path],
    out_dir: str | Path,
    practice_dirs: list[str | Path] | None = None,
    force: bool = False,
    log=None,
) -> dict[str, Any]:
    """Export a stimulus set from evaluation directories; returns the manifest dict.

    Entries whose mask is empty (object fully hidden in that view) are skipped
    with a warning: nothing could be clicked. Duplicate ``(run, view)`` entries
    are kept once. ``practice_dirs`` provide dedicated practice stimuli
    (recommended: other scenes than the formal ones, so practice trials do not
    reveal where the object sits in a formal scene).
    """
    log = log or (lambda msg: print(msg, file=sys.stderr))
    out = Path(out_dir)
    if (out / "manifest.json").exists() and not force:
        raise CamoError(
            f"{out}: already holds a stimulus set; a rebuild gives new ids, which breaks a running study "
            "(use another --out, or --force)"
        )
    if not eval_dirs:
        raise CamoError("build-stimuli needs at least one EVAL_DIR")

    sources: list[tuple[Path, bool]] = [(Path(d), False) for d in eval_dirs]
    sources += [(Path(d), True) for d in (practice_dirs or [])]
    plan: list[tuple[Path, dict[str, Any], bool]] = []
    for d, practice in sources:
        for e in _read_renders(d):
            plan.append((d, e, practice))

    seen: set[tuple[str, str, bool]] = set()
    stimuli: list[dict[str, Any]] = []
    skipped_empty = 0
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
        sid = secrets.token_urlsafe(12)
        rid = secrets.token_urlsafe(12)
        _save_png(out / "images" / f"{sid}.png", rgb)
        _save_png(out / "masks" / f"{sid}.png", mask.astype(np.uint8) * 255)
        _save_png(out / "reveal" / f"{rid}.png", outline_overlay(rgb, mask))
        stimuli.append(
            {
                "id": sid,
                "reveal_id": rid,
                "run": str(e["run"]),
                "scene": str(e["scene"]),
                "object": str(e.get("object") or ""),
                "method": str(e["method"]),
                "ablation": str(e.get("ablation") or ""),
                "view": str(e["view"]),
                "practice": practice,
                "width": int(rgb.shape[1]),
                "height": int(rgb.shape[0]),
                "mask_pixels": int(mask.sum()),
                "source_image": str((d / str(e["image"])).resolve()),
            }
        )
    if not any(not s["practice"] for s in stimuli):
        raise CamoError("no usable stimuli: every formal render entry was skipped")
    manifest = {
        "version": MANIFEST_VERSION,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "sources": [str(d.resolve()) for d, _ in sources],
        "skipped_empty_masks": skipped_empty,
        "stimuli": stimuli,
    }
    write_json(out / "manifest.json", manifest)  # written last: a set without manifest is incomplete
    return manifest


def summarize(manifest: dict[str, Any]) -> str:
    formal = [s for s in manifest["stimuli"] if not s["practice"]]
    scenes = sorted({s["scene"] for s in formal})
    conds = sorted({condition_label(s["method"], s["ablation"]) for s in formal})
    cells = {(s["scene"], condition_label(s["method"], s["ablation"])) for s in formal}
    n_practice = len(manifest["stimuli"]) - len(formal)
    missing = len(scenes) * len(conds) - len(cells)
    text = (
        f"{len(formal)} stimuli: {len(scenes)} scenes x {len(conds)} methods ({', '.join(conds)}), "
        f"{len(cells)} cells"
    )
    if missing:
        text += f" ({missing} scene x method cells have no render)"
    if n_practice:
        text += f"; {n_practice} dedicated practice stimuli"
    return text
