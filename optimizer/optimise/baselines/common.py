"""What every baseline shares: scene set-up, background targets, radiance -> albedo, the run directory.

Set-up (:func:`setup`) is the same as Stage 1's: the prepared object, the
environment, the training cameras, the effect planner's plan and its shading
integrator, and the background targets rendered by Stage 1's own
:func:`optimizer.optimise.stage1.render_targets` (a baseline and ``ours`` run
with the same settings see bit-identical backgrounds, coverage, depth and
loss domain).

Every baseline's result is one set of appearance parameters (the ``values``
dict of :mod:`optimizer.rendering.appearance`: maps, zero displacement, zero pose) that
goes through :func:`optimizer.assets.result.write_result`, i.e. it is re-rendered with
the same path tracer, lighting and spp as ``ours`` and exported the same way.
The planner is asked about the full parameter set (what ``ours`` optimises
without ablations), so every method gets the same integrator; ``--ablate``
does not apply to baselines.

Radiance -> albedo (``albedo_mode``)
------------------------------------
The paper's baselines paint the *observed* background colour onto the object
as its albedo (Owens et al. print the photo colours; GANmouflage's texture is
image colour). A rendered background is linear radiance, whose scale depends
on the lighting (0.05 for the sunlit gravel yard): used directly as albedo it
would make every painted object nearly black, which is not what painting a
photograph means. A photograph has an exposure and a white balance; the
colour printed from it is the pixel value under that exposure. We therefore
convert with a single **global white level** per scene (default
``"global"``)::

    W_c   = mean over the object's pixels in all training views of the radiance of a
            white Lambertian (albedo 1) copy of the object, per channel c
    albedo = clip(L / W, 0, 1)

``W`` is the object's mean irradiance / pi, so the painted object has the
right brightness *on average*, while light-facing parts still come out too
bright and shadowed parts too dark -- the failure the paper describes for
these baselines (Sec. IV-C, Fig. 1). Other modes: ``"local"`` divides each
observation by the white copy's radiance at the same pixel (per view, per
texel: a de-lit, shading-compensated albedo, stronger than the paper's
baselines) and ``"photo"`` uses ``clip(L, 0, 1)`` as the albedo (no exposure;
equal to decoding the clipped sRGB-encoded pixel).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from camo_base import seeds
from optimizer.rendering.appearance import AppearanceConfig, Geometry, initial_values, object_bsdf
from optimizer.scenes.bsdf_maps import MAPS
from optimizer.scenes.cameras import Camera
from camo_base.errors import CamoError
from optimizer.scenes.scenepack import ScenePack
from optimizer.optimise.stage1 import Stage1Config, Targets, render_targets, shading_integrator
from optimizer.rendering import projection

ALBEDO_MODES = ("global", "local", "photo")


@dataclasses.dataclass
class BaselineOptions:
    """Options shared by the projection baselines (Python API; the CLI uses the defaults)."""

    albedo_mode: str = "global"  # see the module doc
    visibility_eps: float = 0.01  # first-hit tolerance, fraction of the object's size


@dataclasses.dataclass
class Setup:
    """Everything a baseline needs about its scene (built by :func:`setup`)."""

    pack: ScenePack
    env: Any
    cams: list[Camera]
    plan: Any
    integrator: dict
    app: AppearanceConfig  # the baseline's appearance config (maps at --map-resolution, no pose/displacement)
    geometry: Geometry
    targets: Targets
    initial_render: np.ndarray  # (V, H, W, 3) the object with the pack's initial material
    stage1: Stage1Config  # the targets' settings (target spp, loss and domain), from the run spec
    say: Callable[[str], None]
    seed: int = 0  # the run seed (RunSpec.seed): streams of camo_base.seeds derive from it
    _white: np.ndarray | None = None
    _vis_scene: Any = None

    @property
    def positions(self) -> np.ndarray:
        """World positions ``(Nu, 3)`` of the UV mesh (no displacement, no pose offset)."""
        return self.geometry.positions_np()

    @property
    def size(self) -> float:
        return float(self.pack.object.size)

    def visibility_scene(self):
        """``(scene, object_shape)``: the full scene with the object, for visibility rays (cached)."""
        if self._vis_scene is None:
            g = self.geometry
            self._vis_scene = projection.object_scene(self.env, self.positions, g.faces, g.uvs)
        return self._vis_scene

    def white_render(self) -> np.ndarray:
        """``(V, H, W, 3)``: the scene with a white Lambertian (albedo 1) copy of the object (cached)."""
        if self._white is None:
            from optimizer.rendering import scene as scn
            from optimizer.rendering.render import render_shaded

            g = self.geometry
            mesh = scn.object_mesh(self.positions, g.faces, g.uvs, {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}})
            self._white = render_shaded(self.env.build(), mesh, self.cams, self.integrator, self.stage1.target_spp,
                                        seeds.seed("baseline_white", self.seed))
        return self._white

    def white_level(self) -> np.ndarray:
        """``(3,)`` the global white level ``W`` (module doc): mean white-object radiance over its pixels."""
        cov = self.targets.coverage >= 0.999
        if not cov.any():
            cov = self.targets.coverage >= 0.5
        if not cov.any():
            raise CamoError("the object is not visible in any training view; nothing to camouflage")
        w = self.white_render()[cov].mean(0).astype(np.float32)
        return np.maximum(w, 1e-6)

    def texel_surface(self) -> projection.TexelSurface:
        g = self.geometry
        return projection.rasterise_texels(self.positions, g.faces, g.uvs, self.app.map_resolution, g.normal)

    def observe(self, surface: projection.TexelSurface, eps: float) -> projection.Observations:
        sc, shape = self.visibility_scene()
        return projection.observe(sc, shape, self.cams, surface, eps * self.size)


def to_albedo(setup: Setup, colours: np.ndarray, mode: str, white: np.ndarray | None = None) -> np.ndarray:
    """Observed linear colours -> albedo in [0, 1] (module doc).

    ``colours (..., 3)``; for ``mode == "local"``, ``white`` holds the white
    object's radiance at the same observations (same shape).
    """
    c = np.asarray(colours, np.float32)
    if mode == "photo":
        return np.clip(c, 0.0, 1.0)
    if mode == "global":
        return np.clip(c / setup.white_level(), 0.0, 1.0)
    if mode == "local":
        if white is None:
            raise ValueError("albedo mode 'local' needs the white render at the observations")
        return np.clip(c / np.maximum(np.asarray(white, np.float32), 1e-4), 0.0, 1.0)
    raise CamoError(f"unknown albedo mode {mode!r}; choose one of: {', '.join(ALBEDO_MODES)}")


def observed_albedo(setup: Setup, obs: projection.Observations, images: np.ndarray, mode: str,
                    view: int | None = None) -> np.ndarray:
    """Albedo ``(V, N, 3)`` (or ``(N, 3)`` for one view) from per-view linear ``images`` at the texels' projections."""
    col = obs.sample(images, view)
    white = obs.sample(setup.white_render(), view) if mode == "local" else None
    return to_albedo(setup, col, mode, white)


def setup(spec, say: Callable[[str], None] = lambda s: None, env=None) -> Setup:
    """Prepare the scene and render the targets of ``spec`` (the run's :class:`optimizer.optimise.spec.RunSpec`).

    ``env``: an :class:`optimizer.scenes.environments.Environment` to use instead of the pack's.
    """
    from optimizer.scenes.cameras import cameras
    from optimizer.scenes.environments import get_environment
    from optimizer.rendering.placement import prepare_object
    from optimizer.optimise.planning import run_plan

    pack, stage1 = spec.pack, spec.stage1_config()
    prepared = prepare_object(pack)
    env = env if env is not None else get_environment(pack.environment)
    full = AppearanceConfig()  # the planner sees the full parameter set: one renderer for every method
    cams = cameras(pack)
    pl = run_plan(spec, pack, env, prepared, cams, full, say)
    env = pl.environment(env)
    integ = shading_integrator(pl)
    app = dataclasses.replace(spec.appearance, pose=False, displacement=False, bsdf=True, transmittance=True)
    geometry = Geometry.build(prepared, pack.object, app)
    # The loss domain uses the object with the initial appearance of `ours` (same domain as Stage 1).
    init_app = spec.appearance
    init_vals = initial_values(init_app, pack.material)
    from optimizer.rendering import scene as scn

    obj = scn.object_mesh(geometry.positions_np(), geometry.faces, geometry.uvs, object_bsdf(init_vals, init_app))
    say("rendering background targets and the loss domain")
    targets, init = render_targets(env, cams, obj, integ, stage1, region=pl.region_search, region_threshold=pl.region_threshold)
    return Setup(pack, env, cams, pl, integ, app, geometry, targets, init, stage1, say, seed=spec.seed)


def painted_values(setup: Setup, albedo: np.ndarray) -> dict[str, np.ndarray]:
    """Parameters of a painted (Lambertian-like) object: the ``albedo`` map and every other BSDF map at its
    ``painted`` value (:data:`optimizer.scenes.bsdf_maps.MAPS`: metallic 0, roughness 1, transmittance 0)."""
    vals = initial_values(setup.app, setup.pack.material)
    r = setup.app.map_resolution
    a = np.asarray(albedo, np.float32)
    if a.shape != (r, r, 3):
        raise ValueError(f"albedo map must be ({r}, {r}, 3), got {a.shape}")
    for name, m in MAPS.items():
        vals[name] = np.clip(a, 0.0, 1.0) if m.painted is None else np.full((r, r, m.channels), m.painted, np.float32)
    return vals


def run_directory(spec, out: str | Path,
                  compute: Callable[[Setup], tuple[dict[str, np.ndarray], list[dict[str, Any]], dict[str, Any]]],
                  progress: bool = True, threads: int | None = None,
                  provenance: dict[str, Any] | None = None) -> Path:
    """Set up ``spec`` (a baseline's :class:`optimizer.optimise.spec.RunSpec`), run ``compute(setup) -> (values,
    history, info)``, and write the run directory into the folder ``out`` (the staging folder of
    :func:`optimizer.optimise.run.run`, which moves it into place).

    The directory has the layout of ``ours`` (CONTRIBUTING.md): ``config.toml``
    (the spec, with a ``[baseline]`` table = ``info``; ``provenance``: its ``[versions]`` and ``[[history]]``),
    ``log.jsonl`` (one record per training iteration; empty for one-shot methods), maps, ``result.glb`` /
    ``.obj`` / ``.ply``, ``scene.xml``, ``pose.json``, previews, ``renders.npz``
    and ``summary.json``. There is no ``checkpoint.npz``: baselines are
    one-shot runs and cannot be resumed.
    """
    from optimizer import backend
    from optimizer.assets.result import Result
    from camo_base.provenance import versions
    from optimizer.assets.rundir import write_config, write_log
    from optimizer.optimise.finish import finish
    from optimizer.optimise.planning import config_record

    out = Path(out)
    backend.init(threads=threads)
    say = (lambda s: print(s, file=sys.stderr)) if progress else (lambda s: None)
    t0 = time.perf_counter()
    st = setup(spec, say)
    seconds_setup = time.perf_counter() - t0
    t1 = time.perf_counter()
    values, history, info = compute(st)
    seconds_method = time.perf_counter() - t1
    write_config(out, spec.to_dict(), {
        **(provenance or {"versions": versions()}),
        "plan": config_record(st.plan),
        "fingerprint": {"value": spec.fingerprint()},
        "baseline": {"method": spec.method, **info},
    })
    write_log(out, history)
    say("rendering the result")
    res = Result(spec.pack, st.env, st.cams, st.geometry, values, st.app, st.integrator, st.stage1.target_spp, st.targets)
    finish(out, res, history, st.stage1, st.initial_render, method=spec.method,
           seconds={"setup": seconds_setup, "method": seconds_method},
           extra={"fingerprint": spec.fingerprint(), "plan": st.plan.to_dict()})
    return out
