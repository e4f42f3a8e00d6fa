"""Turntable videos of results: a continuous orbit around the object, path-traced like the evaluation (``camo video``).

Camouflage is judged in motion; this renders what a reader of the paper's supplementary video sees, for our
results and anyone else's, on the evaluation's terms:

* **Cameras** (:func:`evaluation_orbit`): one orbit around the object at the evaluation's radius and elevation
  (the pack's rig: :func:`optimizer.scenes.cameras.rig_radius`, its orbit elevation, or the mean elevation of a
  camera list), looking at the object centre, with the rig's field of view; ``frames`` evenly spaced azimuths over
  ``arc`` degrees from ``start`` (default: the rig's first camera). A full turn (360) leaves out the end point, so
  the video loops without a repeated frame. No jitter.
* **Integrator** (:func:`video_integrator`): the evaluation's path tracer
  (:func:`evaluation.views.evaluation_plan`, deep enough for any method's material so that every panel is rendered
  alike), made deeper where a run's recorded plan (:meth:`optimizer.assets.rundir.RunDir.recorded_plan`) asks for
  more bounces.
* **Panels** (:func:`panels_of`): the background (the scene without the object) and one panel per input (run
  directory or external asset, read as :mod:`evaluation.inputs` reads them), all in one scene, rendered from the
  same camera with the same sampler seed per frame (stream ``turntable_render`` of :mod:`camo_base.seeds`: common
  random numbers, so paths that miss the object agree in every panel and the difference row shows the object, not
  noise). Side by side, labelled, optionally with a row of ``4 x |panel - background|`` (sRGB) under them
  (:func:`compose`).
* **Resumable** (:class:`FrameCache`): every panel of every frame is a PNG (8-bit sRGB) in a cache folder, named by
  a hash of what decides its pixels (scene, object content, camera, spp, integrator, seed); written atomically. A
  run interrupted by Ctrl-C (or killed) continues where it stopped; changing a setting renders only what changed
  (a new baseline beside cached ones renders that panel only).
* **Time budget** (:func:`choose_spp`): a pilot renders one frame's panels at 1 and 4 spp, fits
  ``seconds = a + b * spp`` per panel, and takes the largest spp whose estimate fits what is left of the budget.

Images are linear float32 ``(H, W, 3)`` out of the renderer and ``uint8`` sRGB ``(H, W, 3)`` from the cache on.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from camo_base import seeds
from camo_base.errors import CamoError, SettingError
from optimizer.scenes.cameras import Camera

DEFAULT_FRAMES = 120
DEFAULT_RESOLUTION = 256
DEFAULT_SPP = 64
DEFAULT_FPS = 30.0
#: Amplification of the difference row (as in a run's previews: ``optimizer.assets.result.preview_strip``).
DIFF_GAIN = 4.0
#: spp the pilot of ``--time-budget`` renders at.
PILOT_SPP = (1, 4)
MAX_SPP = 4096
LIMITS = {"frames": (2, 10000), "resolution": (16, 4096), "spp": (1, MAX_SPP), "fps": (1.0, 120.0),
          "elevation": (-89.0, 89.0)}


# --------------------------------------------------------------------------------------------------------------
# cameras
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Orbit:
    """A circular camera path around ``centre`` (world space, Z-up, scene units; angles in degrees)."""

    centre: tuple[float, float, float]
    radius: float
    elevation: float  # above the horizontal plane through the centre
    start: float  # azimuth of frame 0, from +x towards +y
    arc: float  # azimuth covered, in (0, 360]
    frames: int
    fov: float  # horizontal, as Camera.fov
    width: int
    height: int

    @property
    def full_turn(self) -> bool:
        return abs(self.arc - 360.0) < 1e-9

    def azimuths(self) -> list[float]:
        """Azimuth of each frame (degrees): a full turn leaves out the end (seamless loop); an arc includes both
        ends."""
        n = self.frames
        if n == 1:
            return [self.start]
        step = self.arc / n if self.full_turn else self.arc / (n - 1)
        return [self.start + step * i for i in range(n)]

    def cameras(self) -> list[Camera]:
        el = math.radians(self.elevation)
        cx, cy, cz = self.centre
        out = []
        for az_deg in self.azimuths():
            az = math.radians(az_deg)
            o = (cx + self.radius * math.cos(el) * math.cos(az), cy + self.radius * math.cos(el) * math.sin(az),
                 cz + self.radius * math.sin(el))
            out.append(Camera(o, self.centre, self.fov, self.width, self.height))
        return out


def evaluation_orbit(pack, frames: int = DEFAULT_FRAMES, arc: float = 360.0, start: float | None = None,
                     resolution: int = DEFAULT_RESOLUTION, elevation: float | None = None,
                     radius: float | None = None) -> Orbit:
    """The orbit of the evaluation's cameras without their jitter (module docstring); ``elevation`` and ``radius``
    override the rig's."""
    from optimizer.scenes.cameras import cameras, object_centre, rig_radius

    training = cameras(pack, (resolution, resolution))
    c = pack.cameras
    if c.mode == "orbit":
        centre = object_centre(pack)
        el, az0 = float(c.elevation), float(c.azimuth_offset)
    else:
        centre = tuple(float(x) for x in np.mean([t.target for t in training], axis=0))
        d = np.array([np.subtract(t.origin, centre) for t in training], dtype=np.float64)
        r = np.linalg.norm(d, axis=1)
        el = float(np.degrees(np.mean(np.arcsin(np.clip(d[:, 2] / np.maximum(r, 1e-9), -1, 1)))))
        az0 = float(np.degrees(math.atan2(d[0, 1], d[0, 0])))
    return Orbit(tuple(centre), float(radius if radius is not None else rig_radius(pack, training)),
                 float(el if elevation is None else elevation), float(az0 if start is None else start), float(arc),
                 int(frames), float(c.fov), int(resolution), int(resolution))


def frame_seed(seed: int, frame: int) -> int:
    """Sampler seed of every panel of frame ``frame`` (stream ``turntable_render``)."""
    return seeds.seed("turntable_render", int(seed), frame=int(frame))


# --------------------------------------------------------------------------------------------------------------
# what is rendered: panels and the integrator
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Panel:
    """One column of the video: the background (``entry`` None) or one input (:class:`evaluation.inputs.Entry`)."""

    label: str
    key: str  # content identity (scene; and the object's geometry and maps)
    entry: Any = None

    @property
    def is_background(self) -> bool:
        return self.entry is None

    @property
    def folder(self) -> str:
        from evaluation.inputs import safe_name

        return f"{'background' if self.is_background else safe_name(self.entry.name)}-{self.key[:12]}"

    def mesh(self):
        return None if self.entry is None else self.entry.asset.mesh()


def _digest(*parts: Any) -> str:
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(str((p.dtype.str, p.shape)).encode())
            h.update(np.ascontiguousarray(p).tobytes())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()


def scene_key(pack) -> str:
    """Identity of a scene's environment (what the background panel shows)."""
    return _digest({"environment": dataclasses.asdict(pack.environment)})


def asset_key(asset) -> str:
    """Identity of an object's content: geometry, maps as rendered, index of refraction, BSDF kind, wrap."""
    maps = [asset.maps[k] for k in sorted(asset.maps)]
    return _digest(asset.vertices, asset.faces, asset.uvs if asset.uvs is not None else "no uv", *maps,
                   {"eta": asset.eta, "lambertian": asset.lambertian, "wrap": asset.wrap, "maps": sorted(asset.maps)})


def panels_of(entries: Sequence[Any], background: bool = True) -> list[Panel]:
    """The background panel (when ``background``) and one panel per entry, labelled with their Table II labels
    (the input's name is added where two would read the same)."""
    from evaluation.report import method_label

    if not entries:
        raise SettingError("video needs at least one input: {0}, {1} or {2}", "run_dirs", "asset", "inputs")
    bad = [e for e in entries if e.kind == "triplets"]
    if bad:
        raise CamoError(f"{bad[0].path}: triplets are given images of fixed views; a turntable needs a 3D result "
                        "(a run directory or a glTF/OBJ asset)")
    first = entries[0]
    skey = scene_key(first.pack)
    for e in entries[1:]:
        if scene_key(e.pack) != skey:
            raise CamoError(f"inputs are in different scenes ({first.name}: {first.scene}, {e.name}: {e.scene}); "
                            "one video shows one scene: make one video per scene")
    labels = [method_label(e.method, e.ablation) for e in entries]
    panels = [Panel("background", skey)] if background else []
    for e, lab in zip(entries, labels):
        if labels.count(lab) > 1:
            lab = f"{lab} ({e.name})"
        panels.append(Panel(lab, _digest(skey, asset_key(e.asset)), e))
    return panels


def video_integrator(pack, env, entries: Sequence[Any]) -> tuple[dict[str, Any], list[str]]:
    """The path tracer every panel is rendered with, and why (module docstring): the evaluation's plan, deepened
    to the deepest ``max_depth`` a run's recorded plan names (unbounded = the planner's full depth)."""
    from evaluation.views import evaluation_plan
    from optimizer.rendering.planner import FULL_MAX_DEPTH

    base = evaluation_plan(pack, env)
    depth = int(base.integrator.get("max_depth", base.max_depth))
    why = [f"evaluation path tracer ({base.integrator['type']}, max_depth {depth}): "
           + "; ".join(f"{k}: {v}" for k, v in base.reasons if k == "max_depth")]
    for e in entries:
        if e.run is None:
            continue
        rec = e.run.recorded_plan().max_depth
        if rec is None:
            continue
        rec = FULL_MAX_DEPTH if rec < 0 else rec
        if rec > depth:
            why.append(f"max_depth {rec}: the recorded plan of {e.name} renders that deep")
            depth = rec
    integ = dict(base.integrator, max_depth=depth)  # the evaluation's Russian roulette kept (unbiased)
    return integ, why


# --------------------------------------------------------------------------------------------------------------
# frame cache
# --------------------------------------------------------------------------------------------------------------


def frame_key(panel: Panel, cam: Camera, spp: int, integrator: dict, seed: int) -> str:
    """Hash of everything that decides one panel's pixels in one frame."""
    return _digest(panel.key, dataclasses.astuple(cam), int(spp), integrator, int(seed))[:20]


class FrameCache:
    """Panel frames as 8-bit sRGB PNGs: ``ROOT/<panel folder>/<frame key>.png`` (atomic writes)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def path(self, panel: Panel, key: str) -> Path:
        return self.root / panel.folder / f"{key}.png"

    def has(self, panel: Panel, key: str) -> bool:
        return self.path(panel, key).is_file()

    def save(self, panel: Panel, key: str, linear: np.ndarray) -> None:
        from camo_base.imaging import linear_to_srgb, save_png

        save_png(self.path(panel, key), linear_to_srgb(np.asarray(linear, np.float32)))

    def load(self, panel: Panel, key: str) -> np.ndarray:
        from PIL import Image

        with Image.open(self.path(panel, key)) as im:
            return np.asarray(im.convert("RGB"))


# --------------------------------------------------------------------------------------------------------------
# rendering
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Job:
    """What to render: panels x cameras at ``spp`` with ``integrator``; ``seed`` is the video's (``--seed``)."""

    env: Any  # optimizer.scenes.environments.Environment
    panels: list[Panel]
    cams: list[Camera]
    integrator: dict[str, Any]
    spp: int
    seed: int = 0

    def keys(self, frame: int) -> list[str]:
        return [frame_key(p, self.cams[frame], self.spp, self.integrator, frame_seed(self.seed, frame))
                for p in self.panels]


class PanelScene:
    """One panel's loaded scene with one perspective sensor per frame it must render (each frame its own seed)."""

    def __init__(self, env, panel: Panel, cams: Sequence[Camera], frames: Sequence[int], integrator: dict, spp: int):
        from optimizer.rendering import scene as scn

        self.spp = int(spp)
        self.sensor = {f: i for i, f in enumerate(frames)}
        self.scene = scn.build_scene(env.build(), panel.mesh(), [scn.perspective(cams[f], spp) for f in frames],
                                     integrator)

    def render(self, frame: int, seed: int) -> np.ndarray:
        """Linear radiance ``(H, W, 3)`` of ``frame``."""
        import mitsuba as mi

        try:
            img = mi.render(self.scene, sensor=self.sensor[frame], spp=self.spp, seed=frame_seed(seed, frame))
        except RuntimeError as exc:  # Dr.Jit wraps a Ctrl-C during a render in a RuntimeError
            if _caused_by_interrupt(exc):
                raise KeyboardInterrupt from None
            raise
        return np.asarray(img, dtype=np.float32)[..., :3]


def render_missing(job: Job, cache: FrameCache, progress: bool = True, say: Callable[[str], None] = print,
                   label: str = "rendering") -> dict[str, Any]:
    """Render every panel frame of ``job`` that ``cache`` lacks, frame by frame (an interrupted video has whole
    frames up to where it stopped), each panel's scene loaded once. Returns counts and seconds (a panel frame's
    seconds include its share of loading the scene: the first frame of a panel carries it)."""
    n_frames, n_panels = len(job.cams), len(job.panels)
    keys = [job.keys(f) for f in range(n_frames)]
    todo = [(f, p) for f in range(n_frames) for p in range(n_panels) if not cache.has(job.panels[p], keys[f][p])]
    cached = n_frames * n_panels - len(todo)
    seconds: list[float] = []
    scenes: dict[int, PanelScene] = {}
    bar = _bar(n_frames * n_panels, cached, label, progress)
    try:
        for f, p in todo:
            t = time.perf_counter()
            if p not in scenes:
                scenes[p] = PanelScene(job.env, job.panels[p], job.cams, [g for g, q in todo if q == p],
                                       job.integrator, job.spp)
            cache.save(job.panels[p], keys[f][p], scenes[p].render(f, job.seed))
            seconds.append(time.perf_counter() - t)
            bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        done = sum(all(cache.has(job.panels[p], keys[f][p]) for p in range(n_panels)) for f in range(n_frames))
        say(f"interrupted: {done} of {n_frames} frames are cached in {cache.root}; run the same command again to "
            "continue")
        raise
    bar.close()
    return {"rendered": len(seconds), "cached": cached, "seconds": float(sum(seconds)),
            "seconds_per_panel_frame": float(np.mean(seconds)) if seconds else math.nan}


def _caused_by_interrupt(exc: BaseException) -> bool:
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def _bar(total: int, initial: int, label: str, progress: bool):
    if not progress:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc=label, unit="panel", dynamic_ncols=True, smoothing=0.1,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} panel frames "
                           "[{elapsed}<{remaining}, {rate_fmt}]")


# --------------------------------------------------------------------------------------------------------------
# time budget
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Pilot:
    spp: int  # chosen
    fixed: float  # a: seconds per panel frame independent of spp
    per_sample: float  # b: seconds per panel frame per spp
    renders: int  # panel frames the chosen spp must render
    pilot_seconds: float
    estimate: float  # a * renders + b * spp * renders

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def fit_cost(t1: float, t2: float, spp1: int, spp2: int) -> tuple[float, float]:
    """``(a, b)`` of ``seconds = a + b * spp`` through two timings (``a, b >= 0``; b at least 1e-9 s).

    >>> fit_cost(1.0, 2.5, 1, 4)
    (0.5, 0.5)
    """
    b = max((t2 - t1) / max(spp2 - spp1, 1), 1e-9)
    a = max(t1 - b * spp1, 0.0)
    return a, b


def spp_for_budget(budget: float, renders: int, fixed: float, per_sample: float) -> int:
    """The largest spp (<= :data:`MAX_SPP`) with ``renders * (fixed + per_sample * spp) <= budget``; 0 if none.

    >>> spp_for_budget(100.0, 10, 1.0, 0.5)
    18
    """
    if renders <= 0:
        return MAX_SPP
    per = budget / renders - fixed
    return int(min(MAX_SPP, max(0, math.floor(per / per_sample))))


def choose_spp(job: Job, budget: float, missing: int, say: Callable[[str], None] = print) -> Pilot:
    """Pilot (module docstring): time frame 0's panels at :data:`PILOT_SPP` (after one untimed warm-up render that
    compiles the kernels), fit the cost per panel frame and choose the spp for ``missing`` panel frames within
    what is left of ``budget`` seconds after the pilot and the scenes' loading (measured in the pilot). CamoError
    when even 1 spp does not fit."""
    t0 = time.perf_counter()
    timings = []
    scenes = [PanelScene(job.env, panel, job.cams, [0], job.integrator, 1) for panel in job.panels]
    load = time.perf_counter() - t0  # the video loads each panel's scene once more
    for spp in (PILOT_SPP[0],) + PILOT_SPP:  # the first pass warms up (JIT compilation), untimed
        total = 0.0
        for sc in scenes:
            sc.spp = spp
            t = time.perf_counter()
            sc.render(0, job.seed)
            total += time.perf_counter() - t
        timings.append(total / len(job.panels))
    a, b = fit_cost(timings[1], timings[2], *PILOT_SPP)
    spent = time.perf_counter() - t0
    left = budget - spent - load
    spp = spp_for_budget(left, missing, a, b)
    if spp < 1:
        need = missing * (a + b)
        raise SettingError(f"{{0}} {budget:g} s is too short: after the {spent:.1f} s pilot, {missing} panel frames at 1 "
                           f"spp need about {need:.0f} s; raise it, or lower {{1}} / {{2}}", "time_budget", "frames",
                           "resolution")
    est = missing * (a + b * spp)
    say(f"pilot ({spent:.1f} s): {a:.3f} s + {b:.4f} s/spp per panel frame -> {spp} spp for {missing} panel frames "
        f"(about {est:.0f} s)")
    return Pilot(spp, a, b, missing, spent, est)


# --------------------------------------------------------------------------------------------------------------
# frame layout
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where panels go in a frame: one row of panels (labels in a bar above them) and an optional difference row
    under it (no labels: it lines up with the panels above)."""

    panel: tuple[int, int]  # (width, height) of one panel
    columns: int
    difference: bool
    labels: bool
    gap: int
    bar: int  # label bar height (0 without labels)
    font_px: int

    @property
    def size(self) -> tuple[int, int]:
        w, h = self.panel
        rows = 2 if self.difference else 1
        return self.columns * w + (self.columns - 1) * self.gap, self.bar + rows * h + (rows - 1) * self.gap

    def origin(self, row: int, col: int) -> tuple[int, int]:
        """Top-left pixel ``(x, y)`` of the panel image at ``row``, ``col``."""
        w, h = self.panel
        return col * (w + self.gap), self.bar + row * (h + self.gap)


def layout_for(width: int, height: int, columns: int, difference: bool, labels: bool) -> Layout:
    font_px = max(10, round(min(width, 512) / 11))
    bar = font_px + max(4, font_px // 3) if labels else 0
    return Layout((width, height), columns, difference, labels, max(2, width // 64), bar, font_px)


def _font(px: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=px)


def _fit(draw, text: str, font, width: int) -> str:
    """``text`` shortened with "..." until it fits ``width`` pixels."""
    if draw.textlength(text, font=font) <= width:
        return text
    while text and draw.textlength(text + "...", font=font) > width:
        text = text[:-1]
    return text + "..."


BACKDROP = (20, 20, 20)
LABEL_COLOUR = (235, 235, 235)


def compose(layout: Layout, images: Sequence[np.ndarray], labels: Sequence[str],
            background_index: int | None = 0) -> np.ndarray:
    """One video frame ``(H, W, 3)`` uint8: ``images`` (sRGB uint8 panels) side by side with ``labels`` above; with
    ``layout.difference`` a second row of ``DIFF_GAIN * |image - background|`` (sRGB) under each non-background
    panel (the background's slot says what the row is)."""
    from PIL import Image, ImageDraw

    W, H = layout.size
    canvas = Image.new("RGB", (W, H), BACKDROP)
    draw = ImageDraw.Draw(canvas)
    font = _font(layout.font_px) if layout.labels or layout.difference else None
    pw, ph = layout.panel
    bg = images[background_index].astype(np.float32) if background_index is not None else None
    for col, (img, lab) in enumerate(zip(images, labels)):
        x, y = layout.origin(0, col)
        canvas.paste(Image.fromarray(img), (x, y))
        if layout.labels:
            draw.text((x + pw / 2, layout.bar / 2), _fit(draw, lab, font, pw - 4), fill=LABEL_COLOUR, font=font,
                      anchor="mm")
        if not (layout.difference and bg is not None):
            continue
        dx, dy = layout.origin(1, col)
        if col == background_index:
            for k, line in enumerate((f"{DIFF_GAIN:g}x |panel -", "background|")):
                draw.text((dx + pw / 2, dy + ph / 2 + (k - 0.5) * layout.font_px * 1.25),
                          _fit(draw, line, font, pw - 4), fill=LABEL_COLOUR, font=font, anchor="mm")
        else:
            diff = np.clip(DIFF_GAIN * np.abs(img.astype(np.float32) - bg), 0, 255).astype(np.uint8)
            canvas.paste(Image.fromarray(diff), (dx, dy))
    return np.asarray(canvas)


# --------------------------------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class VideoSettings:
    frames: int = DEFAULT_FRAMES
    arc: float = 360.0
    start: float | None = None
    elevation: float | None = None
    radius: float | None = None
    resolution: int = DEFAULT_RESOLUTION
    spp: int | None = None  # None: DEFAULT_SPP, or chosen by time_budget
    time_budget: float | None = None
    seed: int = 0
    fps: float = DEFAULT_FPS
    codec: str = "h264"
    quality: int | None = None
    side_by_side: bool = False
    difference: bool = False
    preview: str | None = ""  # "" = OUT with .webp; None = no preview
    preview_width: int = 480
    preview_frames: int = 60
    cache: str | None = None  # None = OUT + ".frames"
    threads: int | None = None
    progress: bool = True


def _number(name: str, v: Any, lo: float | None = None, hi: float | None = None, integer: bool = False,
            open_lo: bool = False) -> None:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    if ok and integer:
        ok = float(v).is_integer()
    if ok and lo is not None:
        ok = v > lo if open_lo else v >= lo
    if ok and hi is not None:
        ok = v <= hi
    if not ok:
        rng = (f" in {'(' if open_lo else '['}{lo:g}, {hi:g}]" if lo is not None and hi is not None else
               f" > {lo:g}" if lo is not None and open_lo else f" >= {lo:g}" if lo is not None else "")
        raise SettingError.of(name, f" must be a{'n integer' if integer else ' number'}{rng}, got {v!r}")


def check_settings(s: VideoSettings, out: str | Path) -> None:
    """Every setting in range, the codec known for ``out``'s container (one-line CamoError)."""
    from evaluation.video import PREVIEW_SUFFIXES, check_codec

    _number("frames", s.frames, *LIMITS["frames"], integer=True)
    _number("arc", s.arc, 0.0, 360.0, open_lo=True)
    if s.start is not None:
        _number("start", s.start, -3600.0, 3600.0)
    if s.elevation is not None:
        _number("elevation", s.elevation, *LIMITS["elevation"])
    if s.radius is not None:
        _number("radius", s.radius, 0.0, 1e6, open_lo=True)
    _number("resolution", s.resolution, *LIMITS["resolution"], integer=True)
    if s.spp is not None:
        _number("spp", s.spp, *LIMITS["spp"], integer=True)
    if s.time_budget is not None:
        if s.spp is not None:
            raise SettingError("give {0} or {1}, not both (the budget chooses the spp)", "spp", "time_budget")
        _number("time_budget", s.time_budget, 0.0, 1e7, open_lo=True)
    _number("seed", s.seed, 0, 2**31 - 1, integer=True)
    _number("fps", s.fps, *LIMITS["fps"])
    _number("preview-width", s.preview_width, 16, 4096, integer=True)
    _number("preview-frames", s.preview_frames, 1, 10000, integer=True)
    if s.threads is not None:
        _number("threads", s.threads, 1, 1024, integer=True)
    check_codec(s.codec, out, s.quality)
    if s.preview and Path(s.preview).suffix.lower() not in PREVIEW_SUFFIXES:
        raise SettingError.of("preview", f" {s.preview}: an animated image must end in {' or '.join(PREVIEW_SUFFIXES)}")


def preview_path(out: Path, s: VideoSettings) -> Path | None:
    if s.preview is None:
        return None
    return Path(s.preview) if s.preview else out.with_suffix(".webp")


def make_video(specs: Sequence[Any], out: str | Path, s: VideoSettings, say: Callable[[str], None] = print) -> dict:
    """``camo video``: read the inputs, render the missing panel frames, compose and encode; returns the record
    written beside the video (``OUT.json``). Nothing is written before every input and setting has been checked."""
    from camo_base import atomic
    from camo_base.provenance import versions
    from evaluation.inputs import resolve
    from evaluation.video import preview_frames, write_animation, write_video
    from optimizer import backend
    from optimizer.scenes.environments import get_environment

    out = Path(out)
    if out.is_dir():
        raise SettingError.of("out", f" {out} is a folder; give a video file (.mp4, .webm, .mkv)")
    check_settings(s, out)
    prev = preview_path(out, s)
    if prev is not None and prev.resolve() == out.resolve():
        raise SettingError.of("preview", f" {prev} is the video itself")
    entries = resolve(specs)
    side = s.side_by_side or s.difference or len(entries) > 1
    panels = panels_of(entries, background=side)
    pack = entries[0].pack
    backend.init(threads=s.threads)
    env = get_environment(pack.environment)
    integrator, why = video_integrator(pack, env, entries)
    orbit = evaluation_orbit(pack, s.frames, s.arc, s.start, s.resolution, s.elevation, s.radius)
    cams = orbit.cameras()
    cache = FrameCache(s.cache or str(out) + ".frames")
    for e in entries:
        for w in e.asset.warnings if e.asset is not None else ():
            say(f"warning: {e.name}: {w}")
    t_start = time.perf_counter()
    pilot = None
    if s.time_budget is not None:
        pilot = _budget_choice(cache, panels, cams, integrator, s)
        if pilot is None:
            probe = Job(env, panels, cams, integrator, 1, s.seed)
            missing = sum(not cache.has(panels[p], k) for f in range(len(cams)) for p, k in enumerate(probe.keys(f)))
            pilot = choose_spp(probe, s.time_budget, max(missing, 1), say)
            atomic.write_json(_budget_file(cache, panels, cams, integrator, s), pilot.to_dict())
        else:
            say(f"spp {pilot.spp}: chosen by this budget's pilot earlier (cached in {cache.root})")
        spp = pilot.spp
    else:
        spp = int(s.spp if s.spp is not None else DEFAULT_SPP)
    job = Job(env, panels, cams, integrator, spp, s.seed)
    say(f"{len(cams)} frames x {len(panels)} panel(s) ({', '.join(p.label for p in panels)}) at "
        f"{orbit.width}x{orbit.height} px, {spp} spp, {integrator['type']} max_depth {integrator['max_depth']}; "
        f"frames cached in {cache.root}")
    stats = render_missing(job, cache, s.progress, say)
    t_render = time.perf_counter() - t_start

    layout = layout_for(orbit.width, orbit.height, len(panels), side and s.difference, len(panels) > 1)
    labels = [p.label for p in panels]
    bg_index = 0 if panels[0].is_background else None
    kept: list[np.ndarray] = []
    step = max(1, math.ceil(len(cams) / s.preview_frames))

    def frames() -> Iterator[np.ndarray]:
        for f in range(len(cams)):
            keys = job.keys(f)
            imgs = [cache.load(p, k) for p, k in zip(panels, keys)]
            frame = compose(layout, imgs, labels, bg_index)
            if prev is not None and f % step == 0:
                kept.extend(preview_frames([frame], s.preview_width, 1)[0])  # scaled down now: little memory
            yield frame

    t = time.perf_counter()
    info = write_video(out, frames(), s.fps, s.codec, s.quality)
    t_encode = time.perf_counter() - t
    preview_bytes = write_animation(prev, kept, s.fps / step) if prev is not None else None
    record = {
        "video": str(out), "preview": str(prev) if prev is not None else None, "preview_bytes": preview_bytes,
        "cache": str(cache.root),
        "inputs": [{"label": p.label, "name": p.entry.name, "kind": p.entry.kind, "path": str(p.entry.path),
                    "method": p.entry.method, "ablation": p.entry.ablation}
                   for p in panels if not p.is_background],
        "panels": labels, "scene": pack.name, "orbit": dataclasses.asdict(orbit), "integrator": integrator,
        "plan_reasons": why, "spp": spp, "seed": s.seed, "seed_stream": "turntable_render",
        "difference": layout.difference, "layout": {"width": info["width"], "height": info["height"]},
        "encoding": info, "time_budget": s.time_budget, "pilot": pilot.to_dict() if pilot else None,
        "seconds": {"render": t_render, "encode": t_encode, **stats,
                    "per_frame": (stats["seconds"] / stats["rendered"] * len(panels)) if stats["rendered"] else None},
        "versions": versions(),
    }
    atomic.write_json(sidecar_path(out), record)
    return record


def sidecar_path(out: str | Path) -> Path:
    """The record written beside a video: ``OUT.json`` (``turntable.mp4`` -> ``turntable.mp4.json``)."""
    return Path(str(out) + ".json")


def _budget_file(cache: FrameCache, panels, cams, integrator, s: VideoSettings) -> Path:
    key = _digest([p.key for p in panels], [dataclasses.astuple(c) for c in cams], integrator, s.seed,
                  float(s.time_budget))[:16]
    return cache.root / f"budget-{key}.json"


def _budget_choice(cache: FrameCache, panels, cams, integrator, s: VideoSettings) -> Pilot | None:
    """The spp an earlier run with the same budget and settings chose (so a resumed video keeps its spp)."""
    p = _budget_file(cache, panels, cams, integrator, s)
    if not p.is_file():
        return None
    try:
        return Pilot(**json.loads(p.read_text(encoding="utf-8")))
    except (ValueError, TypeError):
        return None


def read_sidecar(video: str | Path) -> dict | None:
    """The record ``camo video`` wrote beside ``video`` (None when absent or unreadable)."""
    p = sidecar_path(video)
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None
