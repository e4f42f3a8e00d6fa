"""Study stimuli rendered for the study, not for metrics (``camo study build-stimuli``, default mode).

Evaluation renders (``camo evaluate``) come from orbit cameras aimed at the object, so the object always
sits at the frame centre and the images are as small as the training resolution. Here every evaluated input
-- a run directory, or an asset (glTF/GLB, OBJ) placed in its scene as the evaluation placed it, both read
again through :func:`evaluation.inputs.resolve` -- is rendered again at the study size (``size`` x ``size``,
default 512 px, independent of the training resolution) from the same evaluation camera *positions*
(``evaluation.views.evaluation_cameras`` with the evaluation's seed and jitter), but each camera is turned and
zoomed so that the object lands at a random, recorded place and size in the frame.

Distribution (per scene and view, the same for every method of that scene, so methods are compared on
identical framings and share one background render):

* **size**: the object's nominal extent (the pack's normalised object size, seen from the camera's
  distance) spans a fraction ``s ~ U(object_frac)`` of the frame width (default 0.10-0.30); the field of
  view is set to give that, clamped to 8-100 degrees;
* **position**: the object centre's image position, in normalised device coordinates, is uniform in the
  square where an object of extent ``s`` stays ``margin`` (default 2 % of the frame) inside the frame.

The camera keeps its position; its look-at target moves to ``origin + f'`` with
``f' = normalise(f - px tan(fov'/2) r - py tan(fov'/2) u)`` (``f, r, u`` the forward, right and up axes of
the original camera aimed at the object) as the first guess, then solved (yaw and pitch about the camera's
up vector, least squares) until the pinhole projection of the object centre is at ``(px, py)``. The
actual placement is *measured* on the rendered mask and recorded in the manifest (``centroid_x/y``,
``bbox``, ``area_share``, ``centre_hit``) next to the draw (``draw_px/py``, ``draw_object_frac``,
``fov``, ``target``). Background-only and with-object images use the same camera and sampler seed
(``evaluation.views.ViewRenderer``: common random numbers); only the region the object can change is rendered with
it, and pixels where that render is noisier than the background get more samples (``noise_match``, the default:
:mod:`optimizer.rendering.noise`), so a participant cannot find the object by its fireflies. With ``denoise``
a denoiser's name (``--denoise [VARIANT]``: ``oidn-raw``, ``oidn-through``; "" off, the default: the denoiser smooths
the ground seen through a see-through object, a give-away of its own), where the evaluation plan then denoises
(``plan.denoise``: the noise at ``spp`` above that denoiser's measured bias), both renders are denoised alike after
noise matching (:mod:`optimizer.rendering.denoise`); each stimulus records it (``denoise``).

Views whose mask is empty (object hidden, e.g. occluded) are skipped with a warning. A triplet folder (given
2D images) has no scene to render from new cameras, so an evaluation holding one needs ``--copy``
(:func:`study_site.stimuli.build_stimuli`: every input copied as evaluated); mixing copied triplets with
re-rendered inputs would compare methods on different framings, so it is refused with one line.
"""

from __future__ import annotations

import hashlib
import math
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from camo_base.errors import CamoError, SettingError, literal
from study_site.ranges import STIMULI_RANGES

from study_site.stimuli import (
    StimulusWriter,
    check_no_content_leak,
    check_no_leak,
    environment_key,
    phash,
    practice_split,
    synthetic_practice,
)

DEFAULT_SIZE = 512
DEFAULT_OBJECT_FRAC = (0.10, 0.30)
DEFAULT_MARGIN = 0.02


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def camera_basis(origin, target, up=(0.0, 0.0, 1.0)):
    """Forward, right, up unit vectors of a look-at camera."""
    f = _unit(np.asarray(target, float) - np.asarray(origin, float))
    r = np.cross(f, np.asarray(up, float))
    if np.linalg.norm(r) < 1e-9:  # looking straight up/down: any right vector
        r = np.cross(f, np.array([0.0, 1.0, 0.0]))
    r = _unit(r)
    u = np.cross(r, f)
    return f, r, u


def draw_placement(key: str, seed: int, object_frac=DEFAULT_OBJECT_FRAC, margin=DEFAULT_MARGIN) -> dict[str, float]:
    """The seeded draw of one (scene, view): object extent ``s`` (fraction of the frame width) and the
    object centre's NDC position ``(px, py)`` in [-1, 1] (x right, y up)."""
    h = hashlib.sha256(f"{seed}:{key}".encode()).digest()
    rng = np.random.default_rng(int.from_bytes(h[:8], "little"))
    lo, hi = object_frac
    s = float(rng.uniform(lo, hi))
    half = max(0.0, 1.0 - s - 2.0 * margin)  # NDC half-range of the centre: frame width = 2 NDC units
    return {"object_frac": s, "px": float(rng.uniform(-half, half)), "py": float(rng.uniform(-half, half))}


def place_camera(cam, centre, object_size: float, draw: dict[str, float], size: int):
    """A camera at ``cam.origin`` with field of view and target such that an object of nominal extent
    ``object_size`` at ``centre`` spans ``draw['object_frac']`` of the frame with its centre at NDC
    ``(draw['px'], draw['py'])``; returns ``(Camera, fov_deg, target)``."""
    from optimizer.scenes.cameras import Camera

    origin = np.asarray(cam.origin, float)
    c = np.asarray(centre, float)
    dist = float(np.linalg.norm(c - origin))
    if dist <= 1e-6:
        raise CamoError("a camera sits at the object's centre; cannot frame it")
    half_angle = math.atan(0.5 * object_size / dist)
    tan_h = math.tan(half_angle) / draw["object_frac"]
    fov = math.degrees(2.0 * math.atan(tan_h))
    fov = min(100.0, max(8.0, fov))
    tan_h = math.tan(math.radians(fov) / 2.0)
    from scipy.optimize import least_squares

    o, up = tuple(float(x) for x in origin), tuple(cam.up)
    w = _unit(np.asarray(up, float))
    e1 = _unit(np.cross(w, [1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.cross(w, [0.0, 1.0, 0.0]))
    e2 = np.cross(w, e1)

    def forward(a):  # yaw a[0] around ``up``, pitch a[1] towards it
        return math.cos(a[1]) * (math.cos(a[0]) * e1 + math.sin(a[0]) * e2) + math.sin(a[1]) * w

    def cam_for(a):
        return Camera(o, tuple(float(x) for x in origin + forward(a) * dist), float(fov), int(size), int(size), up)

    def residual(a):
        qx, qy = project_ndc(cam_for(a), c)
        return [qx - draw["px"], qy - draw["py"]]

    f, r, u = camera_basis(origin, c, up)
    f2 = _unit(f - draw["px"] * tan_h * r - draw["py"] * tan_h * u)  # first-order guess
    a0 = [math.atan2(f2 @ e2, f2 @ e1), math.asin(max(-1.0, min(1.0, f2 @ w)))]
    sol = least_squares(residual, a0, bounds=([-np.inf, -1.5], [np.inf, 1.5]), xtol=1e-12, ftol=1e-12, gtol=1e-12)
    if max(abs(x) for x in sol.fun) > 1e-4:
        raise CamoError(f"cannot aim the camera at {o} to put the object at ({draw['px']:.3f}, {draw['py']:.3f})")
    target = origin + forward(sol.x) * dist
    new = cam_for(sol.x)
    return new, fov, target


def project_ndc(cam, point) -> tuple[float, float]:
    """Pinhole projection of a world point into ``cam``'s NDC (x right, y up; +-1 at the frame edges)."""
    f, r, u = camera_basis(cam.origin, cam.target, cam.up)
    d = np.asarray(point, float) - np.asarray(cam.origin, float)
    tan_h = math.tan(math.radians(cam.fov) / 2.0)
    z = float(d @ f)
    return float(d @ r) / z / tan_h, float(d @ u) / z / tan_h * cam.width / cam.height


# ------------------------------------------------------------------------------------------------------------
# reading evaluation directories
# ------------------------------------------------------------------------------------------------------------


def inputs_of_eval_dir(eval_dir: str | Path) -> tuple[list[Any], dict[str, Any]]:
    """The inputs an evaluation scored (its ``eval_config.toml`` ``[[runs]]``: run directories and assets, with the
    labels, scene and placement it used) as :class:`evaluation.inputs.InputSpec` to read again, and its
    ``[evaluate]`` settings. A triplet folder is a one-line CamoError: it holds only given 2D images."""
    from evaluation.evaldir import read_eval_config
    from evaluation.inputs import InputSpec

    d = Path(eval_dir)
    if not d.is_dir():
        raise CamoError(f"{d}: not a directory")
    cfg = read_eval_config(d)
    if not cfg:
        raise CamoError(f"{d}: no readable eval_config.toml (is this an evaluation directory from `camo evaluate`?)")
    records = [r for r in cfg.get("runs") or [] if isinstance(r, dict)]
    if not records:
        raise CamoError(f"{d / 'eval_config.toml'}: lists no runs")
    specs = []
    for r in records:
        kind, path = str(r.get("kind", "run")), Path(str(r.get("path", "")))
        name = str(r.get("name") or path.name)
        gone = "is gone (stimuli are re-rendered from it; {0} uses the evaluation's renders instead)"
        if kind == "triplets":
            raise SettingError(f"{literal(d)}: input {literal(repr(name))} is given 2D images (triplets), with no scene to "
                               "render again at the study's size and a drawn framing; build with {0} (every input as "
                               "evaluated, object where the images have it) or leave this evaluation directory out",
                               "copy")
        if kind == "run":
            if not path.is_dir():
                raise SettingError(f"{literal(d)}: run directory {literal(path)} {gone}", "copy")
            specs.append(InputSpec("run", str(path), method=r.get("method"), name=name))
        elif kind == "asset":
            scene = str(r.get("scene_source") or r.get("scene") or "")
            if not path.is_file():
                raise SettingError(f"{literal(d)}: asset {literal(path)} {gone}", "copy")
            if Path(scene).is_absolute() and not Path(scene).exists():
                raise SettingError(f"{literal(d)}: scene {literal(scene)} of asset {literal(repr(name))} {gone}", "copy")
            specs.append(InputSpec("asset", str(path), method=r.get("method"), scene=scene, name=name,
                                   placement=str(r.get("placement") or "auto"), object=r.get("object")))
        else:
            raise CamoError(f"{d / 'eval_config.toml'}: input {name!r} has unknown kind {kind!r}")
    return specs, dict(cfg.get("evaluate") or {})


# ------------------------------------------------------------------------------------------------------------
# rendering
# ------------------------------------------------------------------------------------------------------------


def render_stimuli(
    eval_dirs: list[str | Path],
    out_dir: str | Path,
    practice_dirs: list[str | Path] | None = None,
    practice_scenes: list[str] | None = None,
    size: int = DEFAULT_SIZE,
    views: int = 8,
    spp: int = 64,
    seed: int = 0,
    object_frac: tuple[float, float] = DEFAULT_OBJECT_FRAC,
    margin: float = DEFAULT_MARGIN,
    synthetic_practice_n: int = 8,
    threads: int | None = None,
    force: bool = False,
    log: Callable[[str], None] | None = None,
    noise_match: bool = True,
    denoise: str = "",
) -> dict[str, Any]:
    """Render a stimulus set (see the module docstring); returns the manifest."""
    from evaluation.evaluate import srgb8
    from evaluation.inputs import resolve
    from evaluation.views import DEFAULT_JITTER, ViewRenderer, evaluation_cameras, evaluation_plan
    from optimizer import backend
    from optimizer.scenes.cameras import object_centre
    from optimizer.scenes.environments import get_environment

    log = log or (lambda msg: print(msg, file=sys.stderr))
    if not eval_dirs:
        raise CamoError("build-stimuli needs at least one EVAL_DIR")
    for name, value in (("size", size), ("views", views), ("spp", spp), ("margin", margin)):
        STIMULI_RANGES[name].check(value, name)
    lo, hi = object_frac
    if not (STIMULI_RANGES["object_size"].contains(lo) and STIMULI_RANGES["object_size"].contains(hi) and lo <= hi):
        raise SettingError.of("object_size", f" must be LO,HI with 0.01 <= LO <= HI <= 0.8, not {lo},{hi}")
    writer = StimulusWriter(out_dir, force)

    # every input (run directory or asset, :class:`evaluation.inputs.Entry`) is read and checked before anything
    # is rendered
    jobs: list[tuple[Any, bool, dict[str, Any]]] = []  # (input, practice, evaluation settings)
    for d, practice in [(Path(x), False) for x in eval_dirs] + [(Path(x), True) for x in (practice_dirs or [])]:
        specs, ev = inputs_of_eval_dir(d)
        jobs += [(e, practice, ev) for e in resolve(specs)]
    formal_scenes = {e.scene for e, p, _ in jobs if not p}
    named = practice_split(formal_scenes, {e.scene for e, p, _ in jobs if p}, practice_scenes)
    jobs = [(e, p or e.scene in named, ev) for e, p, ev in jobs]
    check_no_leak({e.scene for e, p, _ in jobs if not p}, {e.scene for e, p, _ in jobs if p}, "build-stimuli")
    env_of = {id(e): environment_key(e.pack.environment) for e, _, _ in jobs}
    # practice vs formal by what they show (the same environment), before anything is rendered; the images and
    # backgrounds are compared again by perceptual hash when the set is written
    check_no_content_leak([{"practice": p, "scene": e.scene, "view": "any", "environment": env_of[id(e)]}
                           for e, p, _ in jobs], "build-stimuli")

    def framing(e: Any, ev: dict[str, Any]) -> tuple[list[Any], list[dict[str, Any]]]:
        jitter = float(ev.get("jitter", DEFAULT_JITTER))
        base = evaluation_cameras(e.pack, views, jitter, int(ev.get("seed", 0)), (size, size)).cams
        centre = object_centre(e.pack)
        obj_size = float(e.pack.object.size)
        cams, draws = [], []
        for v, cam in enumerate(base):
            draw = draw_placement(f"{e.scene}:{v}", seed, object_frac, margin)
            new, fov, target = place_camera(cam, centre, obj_size, draw, size)
            cams.append(new)
            draws.append({"draw_px": draw["px"], "draw_py": draw["py"], "draw_object_frac": draw["object_frac"],
                          "fov": fov, "target": [float(x) for x in target], "origin": list(new.origin)})
        return cams, draws

    framings = {id(e): framing(e, ev) for e, _, ev in jobs}
    check_same_framing([(e.scene, e.name, framings[id(e)][1]) for e, _, _ in jobs])

    backend.init(threads=threads)
    renderer = ViewRenderer(spp, seed, noise_match=noise_match)
    normals_by_scene: dict[str, np.ndarray] = {}

    def normals_of(scene: str, env: Any, cams: list[Any]) -> np.ndarray:  # one geometry pass per scene's framings
        if scene not in normals_by_scene:
            normals_by_scene[scene] = background_normals(env, cams)
        return normals_by_scene[scene]
    skipped = 0
    plans: dict[str, Any] = {}  # one evaluation plan per scene (its pilot on the scene's first placed cameras)
    for e, practice, ev in jobs:
        env = get_environment(e.pack.environment)
        cams, draws = framings[id(e)]
        if e.scene not in plans:
            plans[e.scene] = evaluation_plan(e.pack, env, cams, spp, seed, denoise=denoise, noise_match=noise_match)
        plan = plans[e.scene]
        log(f"rendering {e.name} ({e.kind}, {e.scene}, {e.method}): {len(cams)} views, {size}x{size} px, {spp} spp"
            + (" [practice]" if practice else ""))
        bg = renderer.background(e.pack, env, cams, plan.integrator, plan.denoise)
        objr = renderer.with_object(env, e.asset.mesh, cams, plan.integrator, bg,
                                    plan.region_threshold if plan.region_search else None,
                                    object_spp=plan.object_spp)
        for v in range(len(cams)):
            mask = objr.mask[v]
            if not mask.any():
                skipped += 1
                log(f"warning: object not visible in {e.name} view {v}; skipped")
                continue
            meta = {"run": e.name, "scene": e.scene, "object": e.object, "method": e.method,
                    "ablation": e.ablation, "view": str(v), "source_kind": e.kind,
                    "source_run": str(e.path.resolve()), "spp": spp, "seed": seed, **draws[v],
                    "environment": env_of[id(e)], "background_phash": phash(srgb8(bg.image[v]))}
            if objr.noise is not None:  # the object's pixels got up to 8x the spp where it was noisier
                meta["spp_factor_max"] = int(objr.noise.factor[v].max())
            meta["denoise"] = objr.denoise or "off"
            meta["object_spp"] = int(plan.object_spp)
            writer.add(srgb8(objr.image[v]), mask, meta, practice)
            # the background of the same camera and seed is kept next to the set (not served), with its
            # surfaces' normals (the simulated observer's floor and walls)
            _save_background(writer.out, e.scene, v, srgb8(bg.image[v]))
            _save_normals(writer.out, e.scene, v, lambda: normals_of(e.scene, env, cams))
    if not any(s["practice"] for s in writer.stimuli) and synthetic_practice_n > 0:
        for rgb, mask, meta in synthetic_practice(synthetic_practice_n, (size, size), seed):
            writer.add(rgb, mask, meta, True)
    return writer.finish(
        [str(Path(d).resolve()) for d in list(eval_dirs) + list(practice_dirs or [])],
        mode="render",
        size=size,
        views=views,
        spp=spp,
        seed=seed,
        placement={
            "object_frac": list(object_frac),
            "margin": margin,
            "meaning": "per scene and view: object extent s ~ U(object_frac) of the frame width (field of view "
                       "set accordingly, 8-100 deg); object centre uniform in NDC [-(1-s-2 margin), +(1-s-2 "
                       "margin)]^2; measured placement recorded per stimulus",
        },
        skipped_empty_masks=skipped,
    )


def check_same_framing(framings: list[tuple[str, str, list[dict[str, Any]]]], tol: float = 1e-6) -> None:
    """One framing per scene and view: every input of a scene must be shown from the same cameras (origin, aim and
    field of view per view), since the methods are compared on the same framings and the set keeps one object-free
    render per scene and view (``backgrounds/``, the observer's background statistics). Runs made with different
    camera settings (views, resolution, a pack's ``[cameras]``) have different evaluation cameras:
    a one-line error names them, before anything is rendered. ``framings``: (scene, input name, per-view
    placement records with ``origin``, ``target`` and ``fov``)."""
    first: dict[str, tuple[str, list[dict[str, Any]]]] = {}
    for scene, name, draws in framings:
        if scene not in first:
            first[scene] = (name, draws)
            continue
        other, ref = first[scene]
        for v, (a, b) in enumerate(zip(ref, draws)):
            d = max(max(abs(x - y) for x, y in zip(a["origin"], b["origin"])),
                    max(abs(x - y) for x, y in zip(a["target"], b["target"])), abs(a["fov"] - b["fov"]))
            if d > tol:
                raise CamoError(f"scene {scene}: {name} and {other} are framed differently in view {v} (their runs' "
                                f"cameras differ: views, resolution or the pack's [cameras]); build their stimuli "
                                f"in separate sets, or evaluate runs made with the same camera settings")
        if len(ref) != len(draws):
            raise CamoError(f"scene {scene}: {name} has {len(draws)} views and {other} {len(ref)}; build their stimuli "
                            f"in separate sets")


def background_normals(env: Any, cams: list[Any]) -> np.ndarray:
    """World-space normals ``(V, H, W, 3)`` of the object-free scene ``env`` seen by ``cams`` (one ray a pixel
    centre, :func:`optimizer.rendering.render.surface_normals_views`): ~0.1 s a 256 px view, against seconds for
    the background's path-traced render."""
    from optimizer.rendering import scene as scn
    from optimizer.rendering.render import surface_normals_views

    return surface_normals_views(scn.build_scene(env.build()), cams)[0]


def _save_normals(out: Path, scene: str, view: int, normals: Callable[[], np.ndarray]) -> None:
    from study_site.stimuli import save_normals, surface_path

    path = surface_path(out, scene, view)
    if not path.exists():
        save_normals(path, normals()[view])


def add_surfaces(stim_dir: str | Path, threads: int | None = None, force: bool = False,
                 log: Callable[[str], None] | None = None) -> int:
    """Render the surface normals of every object-free view of a rendered stimulus set built before
    ``build-stimuli`` wrote them (``camo study surfaces``): the cameras are the manifest's (``origin``,
    ``target``, ``fov`` and size per stimulus), the scene that of the stimulus's source run (or its built-in
    scene). Returns how many files were written; existing ones are kept unless ``force``. Nothing else of the
    set changes; predictions made before stay as they were until ``camo study predict`` runs again."""
    from optimizer import backend
    from optimizer.scenes.cameras import Camera
    from optimizer.scenes.environments import get_environment
    from study_site.stimuli import StimulusSet, background_path, save_normals, surface_path

    log = log or (lambda msg: print(msg, file=sys.stderr))
    sset = StimulusSet(stim_dir)
    if sset.data.get("mode") != "render":
        raise CamoError(f"{stim_dir}: not a rendered set (mode {sset.data.get('mode')!r}): a set of copied images has "
                        f"no object-free render and no cameras")
    todo: dict[str, dict[str, dict[str, Any]]] = {}  # scene -> {view: the manifest's stimulus record}
    for r in sset.data["stimuli"]:
        if r.get("practice") or not background_path(sset.root, r["scene"], r["view"]).is_file():
            continue
        if not force and surface_path(sset.root, r["scene"], r["view"]).exists():
            continue
        todo.setdefault(r["scene"], {}).setdefault(str(r["view"]), r)
    if not todo:
        log(f"{stim_dir}: every object-free view has its surface normals")
        return 0
    backend.init(threads=threads)
    written = 0
    for scene, by_view in todo.items():
        recs = list(by_view.values())
        for r in recs:
            if not all(k in r for k in ("origin", "target", "fov")):
                raise CamoError(f"{stim_dir}: stimulus {r['id']} has no recorded camera (origin, target, fov)")
        pack = _pack_of(recs[0], scene)
        cams = [Camera(tuple(r["origin"]), tuple(r["target"]), float(r["fov"]), int(r["width"]), int(r["height"]))
                for r in recs]
        normals = background_normals(get_environment(pack.environment), cams)
        for r, n in zip(recs, normals):
            save_normals(surface_path(sset.root, scene, r["view"]), n)
            written += 1
        log(f"{scene}: surface normals of {len(recs)} views")
    return written


def _pack_of(rec: dict[str, Any], scene: str):
    """The scene pack a stimulus was rendered in: its source run's, else the built-in or registered scene."""
    from evaluation.inputs import scene_pack
    from optimizer.assets.rundir import open_run

    src = rec.get("source_run")
    if rec.get("source_kind") == "run" and src and Path(src).is_dir():
        return open_run(src).pack
    return scene_pack(scene, f"stimulus {rec['id']}")


def _save_background(out: Path, scene: str, view: int, rgb: np.ndarray) -> None:
    from study_site.stimuli import _save_png, background_path

    path = background_path(out, scene, view)
    if not path.exists():
        _save_png(path, rgb)
