"""Stage 1, background matching (paper Sec. III-C, Eq. 8-11).

For every iteration and view: map the parameters to the scene (vertex
positions through pose + displacement, BSDF maps), render with gradients,
compare to the background render of that view with the luminance-gated loss
(Eq. 9) inside the loss domain, back-propagate; then add L_disp (Eq. 5),
sanitise the gradients and take one Adam step.

The loss domain defaults to the object's visible mask united with its shadow
(the pixels where the object changes the image in an initial high-spp render),
dilated by ``domain_dilate`` of the image size: the shadow on the ground gives
the object away, so it must count. ``domain = "frame"`` uses the whole image.

Beyond the paper (``--preset fast``, the default; ``--preset paper`` turns both off):

* the albedo starts from the least-squares match to the background (:mod:`optimizer.optimise.warmstart`) instead of
  grey 0.5, computed once after the targets are rendered;
* a proximal L1 step on the displacement after each Adam step (``AppearanceConfig.displacement_shrink``), and the
  displacement's rate ramped up over each stage's first steps (``AppearanceConfig.displacement_warmup``: Adam's first
  step is a full rate for every texel, :mod:`optimizer.optimise.adam`);
* optionally, a cosine decay of every learning rate over the stage's progress (:mod:`optimizer.optimise.schedule`);
  ``time_budget`` (seconds of iterations) ends the stage early; progress is then the larger of the iteration
  and the time fraction;
* glint defences (issue 32, docs/results/hard_cases.md): ``loss_clamp`` compares renders and targets through
  :func:`~optimizer.optimise.loss.soft_clamp` at a white point relative to the background (a sun glint adds a
  bounded loss and no gradient; ``loss_linear`` in the log is the loss without it), ``grad_clip`` clips each
  parameter's gradient to a multiple of its running norm (:class:`~optimizer.optimise.adam.Adam`), and
  :meth:`Stage1.search_init` tries the start ``--init`` replaced (:mod:`optimizer.optimise.startsearch`).

Determinism: the primal and adjoint seeds differ and change per iteration and
view; one machine and one seed give the same numbers (resume included; a run ended
by ``time_budget`` depends on the machine's speed by design).
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from optimizer.rendering import scene as scn
from optimizer.optimise.adam import Adam, blur_texels, dr_numpy, smooth_texels
from optimizer.rendering.appearance import AppearanceConfig, Geometry, clamp_projections, initial_values, object_mesh, pose_record, world_positions
from optimizer.scenes.bsdf_maps import ALBEDO_MIN, MAPS
from optimizer.scenes.cameras import Camera
from optimizer.scenes.environments import Environment
from camo_base import seeds
from camo_base.imaging import REC709_LUMA
from optimizer.optimise.loss import gated_loss_terms, mse_loss, soft_clamp, soft_clamp_np, white_point
from optimizer.rendering.planner import Plan, training_integrator
from optimizer.rendering.render import coverage_and_depth, render_shaded, uses_batch
from optimizer.scenes.scenepack import ScenePack
from optimizer.optimise.schedule import lr_scale, progress, soft_threshold

if TYPE_CHECKING:
    from optimizer.optimise.startsearch import ClearSearchInfo, InitSearchInfo, StartSearchInfo


@dataclasses.dataclass
class Stage1Settings:
    """Stage 1's settings as a run spec records them (``[stage1]`` of a run's config.toml,
    :class:`optimizer.optimise.spec.RunSpec`). The loss and its domain (``loss`` to ``shadow_threshold``) are read
    by every method (the background targets, the summary's losses); the rest by ``ours`` only."""

    iterations: int = 50  # paper
    loss: str = "gated"  # or "mse" (paper Fig. 7)
    alpha: float = 1.0
    eps: float = 1e-2
    domain: str = "object+shadow"  # or "frame"
    domain_dilate: float = 0.04  # fraction of the image's larger side
    shadow_threshold: float = 0.05  # relative luminance change that marks the object's influence
    silhouette_every: int = 4  # projective: the silhouette term on a random 1/N of the views per step, weighted
    # The dataclass defaults are the paper's; `camo optimize` applies a preset (optimizer/optimise/presets.py: the
    # default "fast" turns on the warm start)
    warm_start: bool = False  # least-squares albedo start (optimizer/optimise/warmstart.py); paper: grey 0.5
    pose_search: int = 0  # > 0: try this many turns about the vertical axis first (optimizer/optimise/posesearch.py)
    lr_schedule: str = "constant"  # or "cosine" (optimizer/optimise/schedule.py); both presets: constant
    lr_floor: float = 0.1  # cosine: final learning rate as a fraction of the initial one
    average: float = 0.0  # > 0: the result is the moving average of the iterates with this decay (optimise/adam.py)
    # starting roughness values tried on the held-out views before Stage 1 (optimizer/optimise/startsearch.py); [] off
    roughness_search: tuple[float, ...] = ()
    # > 0: the loss compares soft-clamped images, w tanh(x / w) with the white point w = loss_clamp x the background
    # targets' 99th percentile in the loss domain (optimizer/optimise/loss.py soft_clamp: glints bounded); 0: linear
    loss_clamp: float = 0.0
    # > 0: each parameter's gradient is clipped to this many times its running norm (optimizer/optimise/adam.py)
    grad_clip: float = 0.0
    # when `init` set maps: also try the start without it (warm-started) on the held-out views (startsearch.py)
    init_search: bool = False
    # > 0: add this weight x the mean LPIPS of the views' renders against their targets (optimizer/optimise/
    # perceptual.py: texture the per-pixel losses miss, issue 29); 0: off
    perceptual: float = 0.0
    perceptual_net: str = "alex"  # or "vgg": the LPIPS v0.1 trunk of the perceptual term
    # > 0: add this weight x the mismatch of the body's pixel-scale texture energy with the background's in the same
    # pixels (optimizer/optimise/detail.py: the squared error's multi-view optimum is too smooth, issue 29); 0: off
    detail_match: float = 0.0
    # > 0: add this weight x the squared error of the body's mean colour per view (the mask's coverage-weighted mean
    # against the background target's in the same pixels: the glassy tint, optimizer/optimise/tint.py, issue 29); 0: off
    tint_match: float = 0.0
    tint_scale: float = 0.0  # the mean-colour term's scale: 0 the mask's mean per view, > 0 a Gaussian low-pass of S px
    # > 1: after the other start searches, also try clear glass on the held-out views: this shared index of
    # refraction with a smooth start (startsearch.CLEAR_ROUGHNESS), kept with its IOR when it scores better
    # (optimizer/optimise/startsearch.py, issue 29); 0: off
    clear_candidate: float = 0.0
    # the clear-glass candidate's uniform starting roughness; 0: startsearch.CLEAR_ROUGHNESS (0.2). Rougher glass
    # spreads the sunlight it focuses (its caustic in the shadow) and blurs the ground seen through it
    clear_roughness: float = 0.0
    # > 0: the albedo and transmittance maps get a coarse level of this many cells a side (1: one offset per channel
    # for the whole body), added before rendering and optimised by Adam at its own rate (optimizer/optimise/coarse.py:
    # the body's colour moved as a whole, issue 29); 0: off
    coarse_grid: int = 0
    coarse_lr: float = 0.0  # the coarse level's learning rate; 0: the maps' (appearance.lr_maps)
    # > 0: add this gain x a fixed grain layer to the albedo: the ground's own texture projected from each texel's best
    # training view, minus the warm start's multi-view mean (optimizer/optimise/grain.py, issue 29: the body is too
    # smooth); needs the warm start; 0: off
    grain: float = 0.0
    # > 0: the grain layer's best view reads the background targets sharpened by an unsharp mask of this amount
    # (B + A (B - Gauss_0.7px B)): it undoes the blur of resampling the target at the texel's projection and of the
    # render's pixel box (optimizer/optimise/grain.py); 0: the targets as they are
    grain_sharpen: float = 0.0
    # > the start's transmittance: the warm start solves the transmittance map with the albedo, per texel in [start,
    # this], so texels too dark to match at albedo 1 let more light through (optimizer/optimise/warmstart.py, issue 29:
    # the albedo clips on most of meadow's body); 0: the albedo alone
    warm_transmittance: float = 0.0
    # < 1: the same solve may also lower the transmittance to this floor (a more diffuse, sunlit body where light
    # through it is darker than the ground); 1: the start is the floor
    warm_transmittance_low: float = 1.0
    # where the same solve may lower the transmittance, by the scene's sun (optimizer/optimise/warmstart.py, issue 29:
    # an opaque body's dark cast shadow): "facing" only on the texels facing away from it (the sun-facing ones, where
    # the sunlight enters the body, keep at least the start's), "shadow" only on the texels whose shadow on the ground
    # (z = 0) no training view sees; "off" everywhere. Needs a floor below the start and a sunsky/sun/directional sun
    warm_transmittance_sun: str = "off"
    # the Stage 1 loss weight of the loss domain's pixels outside the object and its 1-px ring (its cast shadow, its
    # reflections on the ground, the rest of the dilated domain) against the object's pixels' 1 (shadow_weighted,
    # issue 29: the cast shadow gives the object away); 1: the plain domain, 0: the object alone
    shadow_weight: float = 1.0


@dataclasses.dataclass
class Stage1Config(Stage1Settings):
    """What a :class:`Stage1` runs with: its settings plus what the run spec holds once for every stage (the
    seed, the spp) and this stage's share of the time budget (``RunSpec.stage1_config`` builds it)."""

    spp: int = 4  # each training render (the run spec's spp.train)
    target_spp: int = 64  # background targets, the domain estimate, the warm start, final renders (spp.target)
    seed: int = 0  # the run seed: every stream of camo_base.seeds derives from it
    time_budget: float | None = None  # seconds of iterations for this stage (None: iterations decide)


@dataclasses.dataclass
class Targets:
    background: np.ndarray  # (V, H, W, 3) linear
    coverage: np.ndarray  # (V, H, W)
    domain: np.ndarray  # (V, H, W) float32 weights in {0, 1}
    depth: np.ndarray  # (V, H, W)


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation of ``(H, W)`` by a disc of ``radius`` pixels."""
    if radius <= 0:
        return mask.copy()
    from scipy.ndimage import binary_dilation

    yy, xx = np.mgrid[-radius: radius + 1, -radius: radius + 1]
    return binary_dilation(mask, structure=(xx**2 + yy**2) <= radius**2)


def influence_domain(bg: np.ndarray, obj: np.ndarray, coverage: np.ndarray, threshold: float, dilate_px: int) -> np.ndarray:
    """Object mask united with the pixels the object visibly changes (its shadow), dilated; ``(H, W)`` float32."""
    yb, yo = bg @ REC709_LUMA, obj @ REC709_LUMA
    changed = np.abs(yo - yb) > threshold * np.maximum(yb, 1e-3)
    # Isolated noisy pixels are not a shadow: keep changed pixels with changed neighbours.
    from scipy.ndimage import uniform_filter

    changed &= uniform_filter(changed.astype(np.float32), 3) > 0.5
    return dilate((coverage > 0) | changed, dilate_px).astype(np.float32)


def shadow_weighted(domain: np.ndarray, coverage: np.ndarray, weight: float) -> np.ndarray:
    """The loss weights ``(H, W)`` float32 of a view's domain ``(H, W)`` with its pixels outside the object
    (``coverage`` ``(H, W)`` in [0, 1], 0 = not covered) and outside the object's 1-px ring scaled by ``weight``:
    the cast shadow, reflections on the ground and the rest of the dilated domain weigh ``weight``, the object and
    the partly covered edge pixels next to it (coloured by its silhouette) 1. ``weight`` 1 returns the domain."""
    near = dilate(np.asarray(coverage) > 0, 1)
    out = np.asarray(domain, np.float32).copy()
    out[(out > 0) & ~near] *= np.float32(weight)
    return out


def target_seed(seed: int) -> int:
    """Sampler seed of the background targets, the initial render and the warm start's renders (common random
    numbers: paths that miss the object give the same radiance in all of them): stream ``targets`` of
    :mod:`camo_base.seeds`."""
    return seeds.seed("targets", seed)


def render_targets(env: Environment, cams: list[Camera], obj_mesh, integrator: dict, cfg: Stage1Config,
                   region: bool = False, region_threshold: float | None = None) -> tuple[Targets, np.ndarray]:
    """Background targets, coverage, depth and loss domain of every view, and the initial render ``(V, H, W, 3)``
    of the object ``obj_mesh`` (its initial appearance; it marks the object+shadow domain). Stage 1 and every
    baseline render them here, so a baseline and ``ours`` with the same settings see bit-identical targets.

    ``region`` (a measured plan): the initial render covers only the region the object can change
    (:func:`optimizer.rendering.region.render_region`; threshold ``region_threshold``), the rest is the background
    target (the same seed: the same paths)."""
    sc_obj = scn.build_scene(env.build(), obj_mesh)
    sc_bg = scn.build_scene(env.build())
    cov, depth = [], []
    for c in cams:
        cov.append(coverage_and_depth(sc_obj, c, obj_mesh)[0])
        depth.append(coverage_and_depth(sc_bg, c)[1])
    coverage = np.stack(cov)
    bg = render_shaded(env.build(), None, cams, integrator, cfg.target_spp, target_seed(cfg.seed))
    if region and integrator.get("type") == "path":
        from optimizer.rendering.render import render_with_region

        init = render_with_region(env.build, obj_mesh, cams, integrator, cfg.target_spp, target_seed(cfg.seed), bg,
                                  coverage, region_threshold)[0]
    else:
        init = render_shaded(env.build(), obj_mesh, cams, integrator, cfg.target_spp, target_seed(cfg.seed))
    px = max(1, round(cfg.domain_dilate * max(cams[0].width, cams[0].height)))
    dom = [influence_domain(bg[i], init[i], coverage[i], cfg.shadow_threshold, px) for i in range(len(cams))]
    return Targets(bg, coverage, np.stack(dom), np.stack(depth)), init


def training_windows(domain: np.ndarray, mode: str, shared: bool = True) -> list[tuple[int, int, int, int]] | None:
    """Per view, the window ``(x0, y0, x1, y1)`` of the training render: the bounding box of the loss domain
    ``(V, H, W)`` (pixels outside it weigh 0 in the loss, so the loss and its gradient are those of the full frame;
    the silhouette pass is splatted into the window, :func:`optimizer.rendering.projective.silhouette_pass`).
    None (full frames) for ``mode == "frame"``; a view with an empty domain keeps a 1 x 1 window.

    ``shared`` (the default): every view gets the one window bounding all views' domains. Mitsuba bakes a film's
    crop (its size and offset: the sensor's sample-to-camera transform, the image block's size and offset, the
    wavefront's width) into each kernel as literals, so a window per view compiles every render and silhouette
    kernel once per view (measured on meadow, 4 views at 64 px: ~5-6 CPU s per view's first silhouette pass,
    docs/results/planner.md); one window for all views compiles them once. Still exact: a larger window renders
    more pixels the loss weighs 0."""
    from optimizer.rendering.region import bbox

    if mode == "frame":
        return None
    if shared:
        b = bbox(np.any(np.asarray(domain) > 0, axis=0))
        return [b if b is not None else (0, 0, 1, 1)] * len(domain)
    out = []
    for d in domain:
        b = bbox(np.asarray(d) > 0)
        out.append(b if b is not None else (0, 0, 1, 1))
    return out


def shading_integrator(plan: Plan) -> dict:
    """The plain path tracer matching a training plan's depth and Russian roulette (targets, final renders)."""
    return plan.shading_integrator()


class Stage1:
    """One Stage 1 optimisation. The constructor only reads its settings; the preparation is four named steps
    that :func:`optimizer.optimise.run.optimize` calls (and a user may call, or :meth:`prepare` for all four):

    1. :meth:`search_pose`: the turn search (``cfg.pose_search``), or a recorded turn;
    2. :meth:`render_targets`: the background targets, coverage, depth and loss domain (or an earlier stage's);
    3. :meth:`warm_start`: a recorded starting roughness, then the least-squares albedo (``cfg.warm_start``);
    4. :meth:`build`: the optimiser and the training scene.

    Then optionally :meth:`search_start` (the start search, before the first step), and :meth:`step` per iteration.

    >>> s1 = Stage1(pack, env, prepared, cams, plan, cfg, app).prepare()  # doctest: +SKIP
    >>> rec = s1.step()  # doctest: +SKIP
    """

    STAGE = 1
    #: One training window for every view (:func:`training_windows`); False: a window per view (the bench's "before").
    shared_window = True

    def __init__(self, pack: ScenePack, env: Environment, prepared, cams: list[Camera], plan: Plan,
                 cfg: Stage1Config, app: AppearanceConfig, log: Callable[[str], None] = lambda s: None,
                 initial: dict[str, np.ndarray] | None = None):
        """``initial`` overrides the paper's initial values (e.g. a Stage 1 result for Stage 2; then neither the
        pose search nor the warm start runs)."""
        self.pack, self.env, self.cams, self.plan, self.cfg, self.app = pack, env, cams, plan, cfg, app
        self.geometry = Geometry.build(prepared, pack.object, app)
        self._initial_given = initial is not None
        self.values = {k: v.copy() for k, v in (initial or initial_values(app, pack.material)).items()}
        self.project = clamp_projections(app, pack.object.size)
        self.iteration = 0
        self.elapsed = 0.0  # seconds of this stage's iterations so far (the schedule's clock)
        self.total_iterations = cfg.iterations  # the schedule's length (Stage 2 sets its own)
        self.time_budget = cfg.time_budget
        self.stop_requested = False  # set by the run loop (held-out patience spent): the stage ends after this step
        self.history: list[dict[str, Any]] = []
        self._log = log
        self.pose_search_info = None
        self.start_search_info = None
        self.init_search_info = None
        self.clear_search_info = None
        self.warm_start_info = None
        self.targets: Targets | None = None
        self.initial_render: np.ndarray | None = None
        self._unprepared: dict[str, np.ndarray] | None = None  # the start before the warm start
        self._warm_cache: dict = {}  # the warm start's geometry-only work, shared by the start search's candidates
        self._warm = bool(cfg.warm_start and not self._initial_given)
        self.opt = None  # built by build()
        self.windows: list[tuple[int, int, int, int]] | None = None  # per view, the training render's window (build)
        self._batched = uses_batch(plan.integrator)
        self._perceptual = None  # the perceptual term's network (build)
        self._last_perceptual = 0.0
        self._detail = None  # the detail term (build; optimizer/optimise/detail.py)
        self._tint = None  # the mean-colour term (build; optimizer/optimise/tint.py)
        self._coarse = None  # the maps' coarse level (_make_optimiser; optimizer/optimise/coarse.py)
        self._grain = None  # the albedo's grain layer, (R, R, 3) NumPy and Dr.Jit (_make_optimiser; grain.py)

    # --- preparation: the named steps ------------------------------------------------
    def prepare(self, pose_search_info=None, start_search_info=None, targets: Targets | None = None) -> "Stage1":
        """Every preparation step in order (class doc); returns ``self``. ``targets``: an earlier stage's (then the
        turn is that stage's: no pose search); the ``*_info`` records: a resumed run's choices."""
        if targets is None:
            self.search_pose(pose_search_info)
        self.render_targets(targets)
        self.warm_start(start_search_info)
        self.build()
        return self

    def search_pose(self, info=None):
        """Step 1: start from the best of ``cfg.pose_search`` turns about the vertical axis
        (:mod:`optimizer.optimise.posesearch`), when the pose is optimised and no initial values were given.
        ``info`` (a resumed run's :class:`~optimizer.optimise.posesearch.PoseSearchInfo`) sets the turn the search
        chose instead of searching again (the renders at more than one thread are not bit-stable, and the turn
        decides the loss domain). Returns the record (or None)."""
        cfg, app = self.cfg, self.app
        if not cfg.pose_search or "rotation" not in app.trainable() or self._initial_given:
            return None
        from optimizer.optimise.posesearch import SPP, VIEWS, pose_search

        if info is not None:
            self.values["rotation"] = np.array([info.rotation], np.float32)
            self.pose_search_info = info
        else:
            self.values, self.pose_search_info = pose_search(
                self.values, self.geometry, app, self.env, self.cams, self.shading_integrator(), cfg.pose_search,
                VIEWS, SPP, seeds.seed("pose_search", cfg.seed), self._log)
        return self.pose_search_info

    def render_targets(self, targets: Targets | None = None) -> Targets:
        """Step 2: the background targets, coverage, depth and loss domain of every view, and the initial render
        (:func:`render_targets` at the current start); ``targets``: reuse an earlier stage's."""
        if targets is not None:
            self.targets = targets
        else:
            self._log("rendering background targets and the loss domain")
            self.targets, self.initial_render = render_targets(
                self.env, self.cams, self._object(), self.shading_integrator(), self.cfg,
                region=getattr(self.plan, "region_search", False),
                region_threshold=getattr(self.plan, "region_threshold", None))
        return self.targets

    def warm_start(self, start_search_info=None):
        """Step 3: the start Stage 1 takes: a recorded starting roughness (``start_search_info``, a resumed run's
        :class:`~optimizer.optimise.startsearch.StartSearchInfo`), then the least-squares albedo warm start
        (``cfg.warm_start``) and the albedo floor. Returns the warm start's record (or None)."""
        if self.targets is None:
            raise RuntimeError("Stage 1's warm start needs the targets (render_targets first)")
        self.start_search_info = start_search_info
        if start_search_info is not None and not self._initial_given:
            self.values["roughness"] = np.full_like(self.values["roughness"], start_search_info.chosen)
        self._unprepared = {k: v.copy() for k, v in self.values.items()}
        self.values, self.warm_start_info = self._prepare(self.values)
        return self.warm_start_info

    def build(self) -> "Stage1":
        """Step 4: the optimiser (:class:`~optimizer.optimise.adam.Adam` over the trainable parameters) and the
        training scene with its parameter keys and per-view targets."""
        import drjit as dr
        import mitsuba as mi

        if self.targets is None:
            raise RuntimeError("Stage 1 is built after its targets (render_targets first)")
        self._make_optimiser()
        # the window of each view the loss reads (its domain's bounding box): training renders only it
        self.windows = training_windows(self.targets.domain, self.cfg.domain, self.shared_window) \
            if getattr(self.plan, "region", False) else None
        self._batched = uses_batch(self.plan.integrator) and self.windows is None
        self.scene = self._training_scene()
        self.params = mi.traverse(self.scene)
        self._keys = self._param_keys()
        self._w = [self.window(v, self.targets.domain[v]) for v in range(len(self.cams))] \
            if self.cfg.domain != "frame" else [None] * len(self.cams)
        sw = float(getattr(self.cfg, "shadow_weight", 1.0))
        if sw != 1.0 and self.STAGE == 1:  # the shadow's pixels weigh sw in the loss (Stage 2's loss is its own)
            cov = [self.window(v, self.targets.coverage[v]) for v in range(len(self.cams))]
            self._w = [shadow_weighted(np.ones(c.shape[:2], np.float32) if w is None else w, c, sw)
                       for w, c in zip(self._w, cov)]  # (the frame: every pixel outside the object)
        self.white = white_point(self.targets.background, self.targets.domain if self.cfg.domain != "frame" else None,
                                 self.cfg.loss_clamp) if self.cfg.loss_clamp > 0 and self.STAGE == 1 else None
        # (Stage 2's loss is its own, on gamma-encoded renders clipped at 1: no clamp there)
        bg = [self.window(v, self.targets.background[v]) for v in range(len(self.cams))]
        self._bg = [mi.TensorXf(self._tonemap_np(b)) for b in bg]
        self._bg_linear = [mi.TensorXf(b) for b in bg] if self.white is not None else self._bg
        self._batch_key = None
        self._perceptual = None  # the perceptual term's network (Stage 1 only; optimizer/optimise/perceptual.py)
        if getattr(self.cfg, "perceptual", 0.0) > 0 and self.STAGE == 1:
            from optimizer.optimise.perceptual import network

            self._perceptual = network(self.cfg.perceptual_net)
            self._bg_np = [np.ascontiguousarray(b, np.float32) for b in bg]
        self._detail = self._detail_term() if getattr(self.cfg, "detail_match", 0.0) > 0 and self.STAGE == 1 else None
        self._tint = self._tint_term() if getattr(self.cfg, "tint_match", 0.0) > 0 and self.STAGE == 1 else None
        dr.eval()
        return self

    def _detail_term(self):
        """The detail term (:mod:`optimizer.optimise.detail`) on this stage's training windows (or the batch film):
        the tonemapped background targets, the object's fully covered pixels and their share of the loss domain."""
        from optimizer.optimise.detail import FULL, DetailTerm, interior_taps

        V = len(self.cams)
        targets = [self._tonemap_np(self.window(v, self.targets.background[v])) for v in range(V)]
        covered = [self.window(v, self.targets.coverage[v]) >= FULL for v in range(V)]
        share = []
        for v in range(V):
            dom = float(self._w[v].sum()) if self._w[v] is not None else float(covered[v].size)
            share.append(interior_taps(covered[v]).shape[1] / max(dom, 1.0))
        H, W = self.cams[0].height, self.cams[0].width
        return DetailTerm(targets, covered, share, self.cfg.detail_match, film=(H, W, V) if self._batched else None)

    def _tint_term(self):
        """The mean-colour term (:mod:`optimizer.optimise.tint`) on this stage's training windows (or the batch film):
        the background targets as the loss compares them, the object's coverage inside the loss domain and its share
        of the domain's pixels."""
        from optimizer.optimise.tint import TintTerm, mask_weights

        V = len(self.cams)
        targets = [self._tonemap_np(self.window(v, self.targets.background[v])) for v in range(V)]
        weights, share = [], []
        for v in range(V):
            dom = self.window(v, self.targets.domain[v]) if self.cfg.domain != "frame" else None
            w = mask_weights(self.window(v, self.targets.coverage[v]), dom)
            weights.append(w)
            share.append(float(w.sum()) / max(float((dom > 0).sum()) if dom is not None else float(w.size), 1.0))
        H, W = self.cams[0].height, self.cams[0].width
        return TintTerm(targets, weights, share, self.cfg.tint_match, film=(H, W, V) if self._batched else None,
                        sigma=self.cfg.tint_scale)

    def _image_terms(self, imgs: list, keys: list[tuple[int, int]]):
        """The sum of the active terms on the tone-mapped renders (the detail and the mean-colour term; each gives its
        surrogate, or None when it has nothing to add this step), or None when none adds anything. ``imgs``: the
        step's renders (one batch film, or one per view); ``keys``: (view, index into ``imgs``) per view."""
        terms = [t for t in (self._detail, self._tint) if t is not None]
        if not terms:
            return None
        mapped = [self._tonemap(i) for i in imgs]  # tone-mapped once for every term
        parts = [x for x in (t.surrogate(mapped, keys) for t in terms) if x is not None]
        return sum(parts[1:], parts[0]) if parts else None

    # --- set-up -------------------------------------------------------------
    def _prepare(self, values: dict[str, np.ndarray], warm: bool | None = None):
        """A start as Stage 1 takes it: the warm-started albedo (when on; ``warm`` overrides the stage's choice),
        clipped above ``ALBEDO_MIN`` (a zero albedo channel has an infinite gradient under transmission); returns
        ``(values, warm-start info or None)``."""
        info = None
        if self._warm if warm is None else warm:
            from optimizer.optimise.warmstart import warm_start_albedo

            values, info = warm_start_albedo(
                values, self.geometry, self.app, self.env, self.cams, self.shading_integrator(),
                self.targets.background, self.targets.coverage, self.cfg.target_spp, target_seed(self.cfg.seed),
                self._log, cache=self._warm_cache, region=getattr(self.plan, "region", False),
                grain=self._grain_gain() > 0, grain_sharpen=float(getattr(self.cfg, "grain_sharpen", 0.0) or 0.0),
                transmittance_max=self._warm_transmittance()[1], transmittance_min=self._warm_transmittance()[0],
                sun=self._warm_sun())  # (direction, mode) or None
        values = dict(values)
        values["albedo"] = np.clip(values["albedo"], ALBEDO_MIN, 1.0).astype(np.float32)
        return values, info

    def _make_optimiser(self) -> None:
        import drjit as dr
        import mitsuba as mi

        uniform = tuple(n for n in MAPS if self.app.map_update == "large_steps")
        lrs = self.app.learning_rates()
        self._coarse = self._coarse_level()
        self._grain = self._grain_layer()
        if self._coarse is not None:
            from optimizer.optimise.coarse import OFFSET_BOUND, coarse_key

            rate = self.cfg.coarse_lr or self.app.lr_maps
            lrs.update({coarse_key(n): rate for n in self._coarse.channels})
            bound = lambda x: dr.clip(dr.select(dr.isfinite(x), x, 0.0), -OFFSET_BOUND, OFFSET_BOUND)  # noqa: E731
            self.project.update({coarse_key(n): bound for n in self._coarse.channels})
        warmup = {"displacement": self.app.displacement_warmup} if "displacement" in lrs else None
        self.opt = Adam(lrs, average=self.cfg.average, uniform=uniform, clip=self.cfg.grad_clip, warmup=warmup)
        for name in self.app.trainable():
            v = self.values[name]
            self.opt.add(name, mi.TensorXf(v) if v.ndim == 3 else mi.Float(v))
        if self._coarse is not None:
            for name in self._coarse.channels:
                self.opt.add(coarse_key(name), mi.TensorXf(self._coarse.initial(name)))

    def _warm_transmittance(self) -> tuple[float | None, float]:
        """The warm start's transmittance ``(floor or None, ceiling)`` (``cfg.warm_transmittance_low``,
        ``cfg.warm_transmittance``) when the transmittance is optimised, else ``(None, 0)`` (the albedo alone)."""
        if "transmittance" not in self.app.trainable():
            return None, 0.0
        low = float(getattr(self.cfg, "warm_transmittance_low", 1.0))
        return (low if low < 1.0 else None), float(getattr(self.cfg, "warm_transmittance", 0.0) or 0.0)

    def _warm_sun(self):
        """``(the world unit vector towards the scene's sun, mode)`` when the warm start lowers the transmittance only
        where the sun allows (``cfg.warm_transmittance_sun``), else None; a scene without a sun is an error."""
        mode = getattr(self.cfg, "warm_transmittance_sun", "off") or "off"
        if mode == "off" or self._warm_transmittance()[0] is None:
            return None
        from camo_base.errors import CamoError
        from optimizer.scenes.environments import sun_of

        sun = sun_of(self.env)
        if sun is None:
            raise CamoError(f"environment {self.env.name!r} has no sun (sunsky, sun or directional emitter): the warm "
                            "start cannot tell the sun-facing texels from the others")
        return sun, mode

    def _grain_gain(self) -> float:
        """The grain layer's gain (``cfg.grain``) in Stage 1 when the albedo is optimised, else 0."""
        if self.STAGE != 1 or "albedo" not in self.app.trainable():
            return 0.0
        return float(getattr(self.cfg, "grain", 0.0) or 0.0)

    def _grain_layer(self):
        """The albedo's grain layer (:mod:`optimizer.optimise.grain`): ``(map (R, R, 3) NumPy, the same times the
        gain as a Dr.Jit tensor)`` from the chosen start's warm start, or None (off, or no warm start ran)."""
        gain = self._grain_gain()
        g = getattr(self.warm_start_info, "grain", None)
        if gain <= 0 or g is None:
            return None
        import mitsuba as mi

        return g, mi.TensorXf(np.ascontiguousarray(gain * g, np.float32))

    def _coarse_level(self):
        """The coarse level of the albedo and transmittance maps (:mod:`optimizer.optimise.coarse`) when
        ``cfg.coarse_grid`` > 0 in Stage 1 and one of them is optimised, else None."""
        grid = int(getattr(self.cfg, "coarse_grid", 0) or 0)
        if grid <= 0 or self.STAGE != 1:
            return None
        from optimizer.optimise.coarse import COARSE_MAPS, CoarseLevel

        names = [n for n in COARSE_MAPS if n in self.app.trainable()]
        if not names:
            return None
        return CoarseLevel(self.values[names[0]].shape[0], grid, {n: MAPS[n].channels for n in names})

    def search_start(self, candidates, score) -> "StartSearchInfo":
        """Restart from the best starting roughness among ``candidates``, each warm-started and scored by
        ``score(values)`` (lower is better; the run's held-out views), before the first step
        (:mod:`optimizer.optimise.startsearch`). The start already prepared is reused for its own roughness.
        Returns the search's record; its seconds exclude the chosen start's warm start (``warm_start_info``)."""
        from optimizer.optimise.startsearch import start_search

        if self.iteration or self.opt is None:
            raise RuntimeError("the start search runs after Stage 1 is built and before its first step")
        t0 = time.perf_counter()
        have = (float(self.values["roughness"].flat[0]), self.values, self.warm_start_info)
        before = self.warm_start_info.seconds if self.warm_start_info is not None else 0.0

        def prepare(values):
            if np.all(values["roughness"] == have[0]):
                return have[1], have[2]
            return self._prepare(values)

        self.values, self.warm_start_info, info = start_search(candidates, self._unprepared, prepare, score,
                                                               self._log)
        chosen = self.warm_start_info.seconds if self.warm_start_info is not None else 0.0
        info.seconds = time.perf_counter() - t0 + before - chosen
        self._make_optimiser()
        self.start_search_info = info
        return info

    def search_init(self, alternatives: dict[str, dict[str, np.ndarray]], score) -> "InitSearchInfo":
        """Start from the best of the prepared start (``"init"``: what ``--init`` set) and each of
        ``alternatives`` (label -> BSDF map values replacing the start's; warm-started), scored by
        ``score(values)`` (lower is better; the run's held-out views), before the first step
        (:func:`optimizer.optimise.startsearch.init_search`). The turn and displacement stay the start's."""
        from optimizer.optimise.startsearch import init_search

        if self.iteration or self.opt is None:
            raise RuntimeError("the init search runs after Stage 1 is built and before its first step")
        have = (self.values, self.warm_start_info)

        def prepare(label: str, maps: dict[str, np.ndarray] | None):
            if maps is None:
                return have
            return self._prepare({**self.values, **maps}, warm=True)

        self.values, self.warm_start_info, info = init_search(["init", *alternatives],
                                                              {"init": None, **alternatives}, prepare, score,
                                                              self._log)
        self._make_optimiser()
        self.init_search_info = info
        return info

    def search_clear(self, eta: float, score) -> "ClearSearchInfo":
        """Start from the better of the prepared start (at the run's IOR) and clear glass: IOR ``eta``, a uniform
        roughness (``clear_roughness``, else :data:`~optimizer.optimise.startsearch.CLEAR_ROUGHNESS`), the other maps the start's, warm-started
        at that IOR; ``score(values) -> (score, bias2, variance)`` on the run's held-out views, which render with
        this stage's ``app`` (:func:`optimizer.optimise.startsearch.clear_search`). When clear glass wins the
        stage's IOR becomes ``eta`` and the training scene is rebuilt."""
        from optimizer.optimise.startsearch import CLEAR_ROUGHNESS, clear_search

        if self.iteration or self.opt is None:
            raise RuntimeError("the clear-glass search runs after Stage 1 is built and before its first step")
        have = (self.values, self.warm_start_info, self.app)

        def prepare(label: str, candidate_eta: float):
            if label == "start":
                self.app = have[2]
                return have[0], have[1]
            self.app = dataclasses.replace(have[2], eta=float(candidate_eta))
            rough = float(getattr(self.cfg, "clear_roughness", 0.0) or CLEAR_ROUGHNESS)
            values = {**self.values, "roughness": np.full_like(self.values["roughness"], rough)}
            return self._prepare(values)  # warm-started (when the stage warm-starts) at the candidate's IOR

        before = have[1].seconds if have[1] is not None else 0.0
        values, warm, info = clear_search(have[2].eta, eta, prepare, score, self._log)
        self.values, self.warm_start_info = values, warm
        # the search's seconds hold the candidate's warm start; the chosen start's is warm_start_info's (counted once)
        info.seconds += before - (warm.seconds if warm is not None else 0.0)
        if info.chosen == "start":
            self.app = have[2]
        else:
            self.use_eta(info.chosen_eta)
        self.clear_search_info = info
        return info

    def use_eta(self, eta: float) -> None:
        """Render with shared index of refraction ``eta`` from now on (the clear-glass search's choice, or a resumed
        run's record of it): the appearance config and the training scene (rebuilt, with the optimiser, from the
        current values)."""
        self.app = dataclasses.replace(self.app, eta=float(eta))
        self.build()

    def _object(self):
        return object_mesh(self.geometry, self.values, self.app)

    def shading_integrator(self) -> dict:
        """A path tracer consistent with the training integrator (same depth) for targets and final renders."""
        return shading_integrator(self.plan)

    def window(self, view: int, image: np.ndarray) -> np.ndarray:
        """The part of a full-frame ``image`` (``(H, W, ...)``) of ``view`` that its training render covers."""
        if self.windows is None:
            return image
        x0, y0, x1, y1 = self.windows[view]
        return image[y0:y1, x0:x1]

    def _training_scene(self):
        if self._batched:
            sensors = [scn.batch(self.cams, self.cfg.spp)]
        else:
            sensors = [scn.perspective(c, self.cfg.spp, sample_border=True,
                                       crop=None if self.windows is None else self.windows[v])
                       for v, c in enumerate(self.cams)]
        self.scene_integrator, self.render_spp = training_integrator(
            self.plan, self.cfg.spp, (self.cams[0].width, self.cams[0].height))
        return scn.build_scene(self.env.build(), self._object(), sensors, dict(self.scene_integrator))

    def _param_keys(self) -> dict[str, str]:
        keys = {}
        names = list(self.params.keys())

        def find(suffix: str) -> str | None:
            hits = [k for k in names if k.startswith(scn.OBJECT_ID + ".") and k.endswith(suffix)]
            return hits[0] if hits else None

        keys["positions"] = find("vertex_positions")
        if self.app.bsdf:
            for name, m in MAPS.items():
                keys[name] = find(f"{m.principled}.data")
        else:
            keys["albedo"] = find("reflectance.data")
        missing = [k for k, v in keys.items() if v is None]
        if missing:
            raise RuntimeError(f"scene parameters not found for {missing}; have {names}")
        return keys

    # --- one iteration ------------------------------------------------------
    def _mapped(self) -> dict[str, Any]:
        """Scene parameter key -> its value computed from the optimised variables (with their AD graph)."""
        import mitsuba as mi

        opt, keys, g, v = self.opt, self._keys, self.geometry, self.values
        out: dict[str, Any] = {}
        if {"displacement", "translation", "rotation"} & set(opt.values):
            # Trainable parts carry their AD graph; fixed parts (an earlier stage's pose) are constants.
            d = opt["displacement"] if "displacement" in opt else (mi.TensorXf(v["displacement"]) if self.app.displacement else None)
            dt = opt["translation"] if "translation" in opt else mi.Float(v["translation"])
            th = opt["rotation"] if "rotation" in opt else mi.Float(v["rotation"])
            out[keys["positions"]] = g.positions_dr(d, dt, th)
        for name, m in MAPS.items():
            if name in opt and name in keys:
                x = opt[name]
                if self._grain is not None and name == "albedo":  # clip(fine + G grain), fixed grain (grain.py)
                    import drjit as dr

                    x = mi.TensorXf(dr.clip(x.array + self._grain[1].array, m.low, 1.0), x.shape)
                if self._coarse is not None and name in self._coarse.channels:  # fine + U coarse, clipped
                    from optimizer.optimise.coarse import coarse_key

                    x = self._coarse.add(x, opt[coarse_key(name)], m.low)
                out[keys[name]] = m.rendered(x)  # (the roughness' safe minimum)
        return out

    def _apply(self) -> None:
        """Push the current parameters (with their AD graph) into the scene."""
        for key, value in self._mapped().items():
            self.params[key] = value
        self.params.update()

    def views_for_step(self) -> list[int]:
        """The views whose loss this iteration averages (Stage 1: all of them, Eq. 10)."""
        return list(range(len(self.cams)))

    def _choose_silhouette_views(self, views: list[int]) -> None:
        """Budgeted projective integrators (optimizer/rendering/projective.py) compute the primary-silhouette term on a
        random ``1 / silhouette_every`` of this step's views, weighted ``V / k`` so its expectation is the sum
        over all views. The term's variance is ~1e-4 of the continuous term's, and skipping it saves the
        silhouette precomputation and the tracing of its two passes (~1/3 of a step at 1 spp)."""
        integ = self.scene.integrator()
        if not hasattr(integ, "silhouette_views"):
            return
        from optimizer.rendering.projective import silhouette_view_weights

        sensors = self.scene.sensors()
        integ.silhouette_views = silhouette_view_weights([sensors[v].id() for v in views], self.cfg.silhouette_every,
                                                         self.iteration, self.cfg.seed)

    def _seeds(self, view: int) -> tuple[int, int]:
        """Primal and adjoint sampler seeds of this iteration's render of ``view`` (streams ``step`` and
        ``step_grad`` of :mod:`camo_base.seeds`)."""
        s, it = self.cfg.seed, self.iteration
        return seeds.seed("step", s, iteration=it, view=view), seeds.seed("step_grad", s, iteration=it, view=view)

    def _batch_loss(self, img, views: list[int]):
        """Eq. 10 on a batch film ``(H, V*W, 3)`` in one expression: each view's domain weights are
        normalised to sum 1/V, so the weighted mean over the whole film is the mean over views of the
        per-view losses. (Slicing the film per view costs a gather per view in the backward pass.)"""
        import mitsuba as mi

        key = tuple(views)
        if getattr(self, "_batch_key", None) != key:
            H, W = self.cams[0].height, self.cams[0].width
            weight = np.zeros((H, W * len(self.cams)), np.float64)
            for v in views:
                w = np.ones((H, W)) if self._w[v] is None else self._w[v].astype(np.float64)
                weight[:, v * W:(v + 1) * W] = w / max(w.sum(), 1e-12) / len(views)
            film = np.concatenate(list(self.targets.background), axis=1)
            self._batch_bg = mi.TensorXf(self._tonemap_np(film))
            self._batch_bg_linear = mi.TensorXf(film) if self.white is not None else self._batch_bg
            self._batch_w = weight.astype(np.float32)
            self._batch_key = key
        cfg = self.cfg
        img = self._tonemap(img)
        if cfg.loss == "mse":
            return mse_loss(img, self._batch_bg, self._batch_w), None
        t = gated_loss_terms(img, self._batch_bg, self._batch_w, cfg.alpha, cfg.eps)
        return t.total, t

    def _linear_loss(self, img, view: int | None):
        """The configured loss of ``img`` on linear radiance (no soft clamp; detached): what ``loss_clamp`` changed,
        logged as ``loss_linear``. ``view`` None: the batch film."""
        import drjit as dr

        img = dr.detach(img)
        bg, w = (self._batch_bg_linear, self._batch_w) if view is None else (self._bg_linear[view], self._w[view])
        if self.cfg.loss == "mse":
            return mse_loss(img, bg, w)
        return gated_loss_terms(img, bg, w, self.cfg.alpha, self.cfg.eps).total

    def _tonemap(self, img):
        """The loss domain's image: ``img`` soft-clamped at the white point (``loss_clamp``), or as it is."""
        return img if self.white is None else soft_clamp(img, self.white)

    def _tonemap_np(self, img: np.ndarray) -> np.ndarray:
        return img if self.white is None else soft_clamp_np(img, self.white).astype(np.float32)

    def _view_loss(self, img, view: int):
        cfg = self.cfg
        img = self._tonemap(img)
        if cfg.loss == "mse":
            return mse_loss(img, self._bg[view], self._w[view]), None
        t = gated_loss_terms(img, self._bg[view], self._w[view], cfg.alpha, cfg.eps)
        return t.total, t

    def gradient(self) -> tuple[float, dict[str, np.ndarray]]:
        """The photometric loss of this iteration's renders and its gradient with respect to every trainable
        parameter (NumPy arrays shaped like the values; raw: before sanitising, blurring and Adam), without taking a
        step (the bench's probe; the seeds are this iteration's, so the result is what :meth:`step` would use)."""
        import drjit as dr

        photo, _, _, _, _ = self._photometric_backward(self.views_for_step())
        out = {}
        for name in self.opt.values:
            x = self.opt[name]
            g = dr_numpy(dr.grad(x))
            out[name] = g.reshape(self.values[name].shape) if name in self.values else g  # (a coarse level: its own)
            dr.clear_grad(x)
        return photo, out

    def _photometric_backward(self, views: list[int]) -> tuple[float, float, float, float, bool]:
        """Render ``views`` with the current parameters, evaluate the loss (Eq. 10) and back-propagate it into the
        parameters' gradients; returns ``(loss, luminance term, chroma term, loss without the soft clamp (0 when
        off), has_terms)``."""
        import drjit as dr
        import mitsuba as mi

        if self.opt is None:
            raise RuntimeError("Stage 1 steps once prepared (prepare(), or its four steps)")
        V = len(views)
        # Loss terms stay Dr.Jit values (detached) and are read back once, after all views: a
        # read-back per view would stall the pipeline.
        photo, lum, chroma, linear = mi.Float(0.0), mi.Float(0.0), mi.Float(0.0), mi.Float(0.0)
        has_terms = False
        if self._batched:
            self._apply()
            s, sg = self._seeds(0)
            img = mi.render(self.scene, self.params, spp=self.render_spp, seed=s, seed_grad=sg)
            total, terms = self._batch_loss(img, views)
            if self.white is not None:
                linear = self._linear_loss(img, None)
            if terms is not None:
                has_terms = True
                lum, chroma = dr.detach(terms.luminance), dr.detach(terms.chroma)
            photo = dr.detach(total)
            if self._perceptual is not None:
                W = self.cams[0].width
                _, perc = self._perceptual_surrogate([img], [(v, slice(v * W, (v + 1) * W)) for v in views])
                total = total + perc
            extra = self._image_terms([img], [(v, 0) for v in views])
            if extra is not None:
                total = total + extra
            dr.backward(total)
        else:
            # One backward per iteration: the parameter mapping (displacement sampling, pose, roughness
            # remap) is applied once, every view is rendered from the same scene state and the mean of the
            # view losses (Eq. 10) is differentiated in one pass. Dr.Jit calls each view's render op
            # (``render_backward``) in that traversal and sums their gradients at the mapped parameters,
            # which flow back through the mapping once. This is the gradient of re-applying the mapping
            # before every view (tests/test_stage1_gradients.py) at one BVH build and one mapping per
            # iteration instead of one per view, bit-reproducible on one thread. All V views' loss graphs are
            # held until the backward (a few H x W x 3 tensors per view).
            self._apply()
            self._choose_silhouette_views(views)
            total = mi.Float(0.0)
            imgs = []
            for v in views:
                s, sg = self._seeds(v)
                img = mi.render(self.scene, self.params, sensor=v, spp=self.render_spp, seed=s, seed_grad=sg)
                imgs.append(img)
                lv, terms = self._view_loss(img, v)
                total += lv / V
                if self.white is not None:
                    linear += self._linear_loss(img, v) / V
                if terms is not None:
                    has_terms = True
                    lum += dr.detach(terms.luminance) / V
                    chroma += dr.detach(terms.chroma) / V
            photo = dr.detach(total)
            dr.schedule(photo, lum, chroma, linear)
            if self._perceptual is not None:
                _, perc = self._perceptual_surrogate(imgs, [(v, None) for v in views])
                total = total + perc
            extra = self._image_terms(imgs, [(v, k) for k, v in enumerate(views)])
            if extra is not None:
                total = total + extra
            if dr.grad_enabled(total):
                dr.backward(total)
        return float(photo[0]), float(lum[0]), float(chroma[0]), float(linear[0]), has_terms

    def _perceptual_surrogate(self, imgs, parts) -> tuple[float, Any]:
        """The perceptual term (:mod:`optimizer.optimise.perceptual`) of this step's renders: ``imgs`` are the
        renders (one per view, or the batch film once), ``parts`` ``(view, columns of the film or None)``. Reads
        the renders back once, gets the mean LPIPS over the views and its gradient from the network, and returns
        ``(weight x mean LPIPS, surrogate)``: a Dr.Jit scalar ``weight / V x sum(I * G)`` whose gradient with
        respect to the scene parameters is the term's; its value is not the term's (logged separately as
        ``self._last_perceptual``)."""
        import drjit as dr
        import mitsuba as mi

        from optimizer.optimise.perceptual import perceptual_grad

        dr.eval(*imgs)
        arrays = [dr_numpy(dr.detach(i)) for i in imgs]
        film = len(imgs) == 1 and parts[0][1] is not None
        xs = [arrays[0][:, cols] if film else arrays[k] for k, (_, cols) in enumerate(parts)]
        ys = [self._bg_np[v] for v, _ in parts]
        if len({x.shape for x in xs}) == 1:  # one batch for the network
            values, grads = perceptual_grad(self._perceptual, np.stack(xs), np.stack(ys))
        else:  # training windows of different sizes: one call per view
            pairs = [perceptual_grad(self._perceptual, x[None], y[None]) for x, y in zip(xs, ys)]
            values, grads = np.concatenate([p[0] for p in pairs]), [p[1][0] for p in pairs]
        w = float(self.cfg.perceptual) / len(parts)
        self._last_perceptual = w * float(np.sum(values))
        if film:
            g = np.zeros_like(arrays[0])
            for k, (_, cols) in enumerate(parts):
                g[:, cols] = grads[k]
            return self._last_perceptual, dr.sum(imgs[0].array * mi.Float(g.ravel() * w))
        surrogate = mi.Float(0.0)
        for img, g in zip(imgs, grads):
            surrogate += dr.sum(img.array * mi.Float(np.ascontiguousarray(g).ravel() * w))
        return self._last_perceptual, surrogate

    def step(self) -> dict[str, Any]:
        import drjit as dr

        t0 = time.perf_counter()
        photo, lum, chroma, linear, has_terms = self._photometric_backward(self.views_for_step())
        disp = 0.0
        if "displacement" in self.opt:
            l_disp = self.app.displacement_weight * dr.mean(dr.abs(self.opt["displacement"].array))
            dr.backward(l_disp)
            disp = float(l_disp[0])
        nonfinite = self.opt.sanitise_grads()
        if self.app.grad_blur > 0:
            self._blur_map_grads(self.app.grad_blur)
        if self.app.map_update == "large_steps":
            self._smooth_map_grads(self.app.map_smoothness)
        scale = self.lr_scale()
        self.opt.step(self.project, scale)
        if "displacement" in self.opt and self.app.displacement_shrink > 0:
            self._shrink_displacement(scale)
        self.iteration += 1
        seconds = time.perf_counter() - t0
        self.elapsed += seconds
        rec = {
            "iteration": self.iteration,
            "stage": self.STAGE,
            "loss": photo + disp,
            "loss_photo": photo,
            "loss_disp": disp,
            "seconds": seconds,
            "nonfinite_grads": nonfinite,
            "lr_scale": scale,
        }
        if self.white is not None:
            rec["loss_linear"] = linear  # the photometric loss without the soft clamp
        if self.opt.clip:
            rec["grad_clipped"] = sorted(self.opt.clipped)
        if has_terms:
            rec.update(loss_luminance=lum, loss_chroma=chroma)
        if self._perceptual is not None:
            rec["loss_perceptual"] = self._last_perceptual  # weight x mean LPIPS of the step's views
        if self._detail is not None:
            # the detail term's value and sqrt(E / E*) over the step's views (NaN on the first step: no previous render)
            rec.update(loss_detail=self._detail.last["value"], detail_energy_ratio=self._detail.last["ratio"])
        if self._tint is not None:
            # the mean-colour term's value and the mean |m - m*| (linear RGB) over the step's views
            rec.update(loss_tint=self._tint.last["value"], tint_error=self._tint.last["error"])
        if self._coarse is not None:
            # the coarse levels' offsets after the step, averaged over their cells, per channel
            from optimizer.optimise.coarse import coarse_key

            rec["coarse_offset"] = {n: np.round(dr_numpy(self.opt[coarse_key(n)]).reshape(-1, c).mean(0), 5).tolist()
                                    for n, c in self._coarse.channels.items()}
        self.history.append(rec)
        return rec

    def _blur_map_grads(self, sigma: float) -> None:
        """Blur each BSDF map's gradient by :func:`~optimizer.optimise.adam.blur_texels` (``AppearanceConfig.
        grad_blur`` says why). Runs after the gradients are sanitised (finite)."""
        import drjit as dr

        for name in MAPS:
            if name in self.opt:
                x = self.opt[name]
                dr.set_grad(x, type(x)(blur_texels(dr_numpy(dr.grad(x)), sigma)))

    def _smooth_map_grads(self, smoothness: float) -> None:
        """Precondition each BSDF map's gradient by :func:`~optimizer.optimise.adam.smooth_texels`
        (``AppearanceConfig.map_update`` "large_steps")."""
        import drjit as dr

        for name in MAPS:
            if name in self.opt:
                x = self.opt[name]
                g = dr_numpy(dr.grad(x))
                dr.set_grad(x, type(x)(smooth_texels(g, smoothness) if g.ndim >= 2 else g))

    def _shrink_displacement(self, scale: float) -> None:
        """Proximal L1 step on the normalised displacement: ``d <- sign(d) max(|d| - k lr_t, 0)``, k =
        ``displacement_shrink``, ``lr_t`` the step's rate (schedule and warm-up included). A texel whose photometric
        gradient keeps one sign moves by ~lr_t per Adam step and keeps (1 - k) of it; one pushed back and forth by
        gradient noise returns to 0."""
        import drjit as dr

        k = self.app.displacement_shrink * self.opt.rate("displacement", scale)
        new = soft_threshold(self.opt["displacement"], k)
        dr.enable_grad(new)
        self.opt.values["displacement"] = new
        dr.eval(new)

    def lr_scale(self) -> float:
        """This step's learning-rate multiplier (:func:`optimizer.optimise.schedule.lr_scale` at the stage's progress)."""
        p = progress(self.iteration, self.total_iterations, self.elapsed, self.time_budget)
        return lr_scale(p, self.cfg.lr_schedule, self.cfg.lr_floor)

    def done(self) -> bool:
        """All iterations taken, the stage's time budget spent, or a stop requested (held-out patience)."""
        if self.stop_requested or self.iteration >= self.total_iterations:
            return True
        return bool(self.time_budget) and self.elapsed >= self.time_budget

    # --- results --------------------------------------------------------------
    def current_values(self) -> dict[str, np.ndarray]:
        """The stage's current result: the iterate, or with ``average`` > 0 the moving average of the iterates
        (:class:`~optimizer.optimise.adam.Adam`; the gradients are taken at the iterate)."""
        out = dict(self.values)
        coarse = {}
        for name in self.opt.values:
            arr = dr_numpy(self.opt.averaged(name))
            if name in self.values:
                out[name] = arr.reshape(self.values[name].shape)
            else:  # a coarse level: folded into its map (optimizer/optimise/coarse.py)
                coarse[name] = arr
        if self._grain is not None and "albedo" in self.opt.values:  # the grain layer, folded first (as rendered)
            from optimizer.optimise.grain import fold as fold_grain

            out = fold_grain(out, self._grain[0], self._grain_gain(), MAPS["albedo"].low)
        if self._coarse is not None:
            from optimizer.optimise.coarse import coarse_key, fold

            out = fold(out, {n: coarse[coarse_key(n)].reshape(self._coarse.initial(n).shape)
                             for n in self._coarse.channels}, {n: MAPS[n].low for n in self._coarse.channels})
        return out

    def pose(self) -> dict[str, Any]:
        return pose_record(self.pack.object, self.current_values())

    def world_positions(self) -> np.ndarray:
        return world_positions(self.geometry, self.current_values(), self.app)

    def checkpoint_state(self) -> dict[str, np.ndarray]:
        st = self.opt.state()
        st["iteration"] = np.array(self.iteration)
        if self._detail is not None:
            st.update(self._detail.state())
        return st

    def load_checkpoint_state(self, st: dict[str, np.ndarray]) -> None:
        from camo_base.errors import CamoError

        it = st.get("iteration")
        if it is None or it.shape != () or not np.issubdtype(it.dtype, np.integer) or int(it) < 0:
            raise CamoError("checkpoint is corrupt: no valid iteration count")
        self.opt.load_state(st)
        self.iteration = int(it)
        if self._detail is not None:
            self._detail.load_state(st)
