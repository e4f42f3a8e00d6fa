"""Projective integrators whose primary-silhouette samples are a budget per view, not per pixel.

Mitsuba's ``prb_projective`` and ``direct_projective`` estimate the gradient of the primarily visible
silhouettes (the object's outline and its folds, which carry the pose and displacement gradients) with
``sppp`` samples *per pixel*: ``W * H * sppp`` silhouette samples per view, at least one per pixel. A
silhouette is a 1-D curve of a few hundred pixels at 128^2, so one sample per pixel already puts ~50 samples
on every outline pixel, and each sample traces a path on both sides of the edge. That pass was ~40 % of
Stage 1's kernel time.

``camo_prb_projective`` / ``camo_direct_projective`` are Mitsuba's integrators with two additions:

* ``silhouette_samples`` (N, a plugin property): the primary-silhouette pass draws N samples per view and
  weights each by ``W * H / N`` (:func:`equivalent_spp`), the same Monte Carlo estimator with another sample
  count; tests/test_projective.py checks it against finite differences and against Mitsuba's pass. ``0``
  leaves Mitsuba's pass unchanged.
* ``silhouette_views`` (an attribute Stage 1 sets per step, :func:`silhouette_view_weights`): the silhouette
  term only for a random subset of the views, weighted so its expectation over steps is the full sum.

Everything else (continuous derivatives by path replay, indirect silhouettes when ``sppi > 0``) is
Mitsuba's code, untouched. The budgeted sample stream is reseeded from the render's gradient seed, so
iterations and views stay decorrelated and a run stays reproducible.
"""

from __future__ import annotations

NAMES = {"prb_projective": "camo_prb_projective", "direct_projective": "camo_direct_projective"}
_SEED_SALT = 0x2545F491  # decorrelates the budgeted silhouette stream from Mitsuba's own streams


def equivalent_spp(width: int, height: int, samples: int) -> float:
    """The ``spp`` that Mitsuba's silhouette pass divides each sample by, for N samples per view.

    ``W, H`` is the film's crop size. Mitsuba draws ``M = W' * H' * sppp`` samples over the *sampled* film
    (``W' = W + 2 * border`` with ``sample_border``) and weights each by ``1 / sppp``; the estimate is
    unbiased only when ``M / sppp = W * H``, so with a filter border (Gaussian, ``sample_border``) Mitsuba
    3.9's silhouette gradient is ``W' * H' / (W * H)`` too large (x1.27 at 32^2, measured against finite
    differences in tests/test_projective.py; camo's training films use the box filter, border 0). With N
    samples each is weighted ``W * H / N``: ``sppp -> N / (W * H)``, unbiased with or without a border.
    """
    if samples <= 0:
        raise ValueError("silhouette_samples must be positive")
    return samples / float(width * height)


def silhouette_view_weights(sensor_ids: list[str], every: int, iteration: int, seed: int) -> dict[str, float] | None:
    """The views whose silhouette term is computed at ``iteration``: a random ``1/every`` share, each weighted
    by ``V / k`` (``k`` views chosen out of ``V``), so the expected sum over views is unchanged. ``every <= 1``:
    all views (None). Deterministic in ``(seed, iteration)``."""
    if every <= 1 or len(sensor_ids) <= 1:
        return None
    from camo_base import seeds

    n = len(sensor_ids)
    k = max(1, -(-n // every))
    rng = seeds.generator("silhouette_views", int(seed), iteration=int(iteration))
    chosen = rng.choice(n, size=k, replace=False)
    return {sensor_ids[i]: n / k for i in sorted(chosen)}


def register() -> None:
    """Register ``camo_prb_projective`` and ``camo_direct_projective`` with Mitsuba (idempotent per variant;
    needs an AD variant set)."""
    import mitsuba as mi

    if getattr(register, "_variant", None) == mi.variant():
        return
    from mitsuba.ad.integrators.direct_projective import DirectProjectiveIntegrator
    from mitsuba.ad.integrators.prb_projective import PathProjectiveIntegrator

    for base_name, base in (("prb_projective", PathProjectiveIntegrator), ("direct_projective", DirectProjectiveIntegrator)):
        cls = _budgeted(base)
        mi.register_integrator(NAMES[base_name], lambda props, cls=cls: cls(props))
    register._variant = mi.variant()


def _budgeted(base):
    """Subclass of Mitsuba's projective integrator ``base`` with the ``silhouette_samples`` budget.
    (Mitsuba's classes are nanobind types: single inheritance only, so no mixin.)"""
    import mitsuba as mi

    class Budgeted(base):
        def __init__(self, props):
            super().__init__(props)
            self.silhouette_samples = int(props.get("silhouette_samples", 0))
            self._seed = 0
            # Optional view subset for the silhouette term: sensor id -> weight (> 0). Views not listed skip
            # the primary-silhouette pass; listed ones are weighted so the sum over views keeps its
            # expectation (see :func:`silhouette_view_weights`). None: every view, weight 1.
            self.silhouette_views: dict[str, float] | None = None
            self._view_weight = 1.0

        def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
            if isinstance(sensor, int):
                sensor = scene.sensors()[sensor]
            views = self.silhouette_views
            self._view_weight = 1.0 if views is None else float(views.get(sensor.id(), 0.0))
            if self._view_weight > 0.0:
                return super().render_backward(scene, params, grad_in, sensor, seed, spp)
            saved = self.sppp
            self.sppp = 0  # no silhouette pass (and no render_ad at all when sppi = 0) for this view
            try:
                return super().render_backward(scene, params, grad_in, sensor, seed, spp)
            finally:
                self.sppp = saved

        def render_ad(self, scene, sensor, seed, spp, mode):
            self._seed = seed  # the gradient seed of this render: the budgeted stream is derived from it
            return super().render_ad(scene, sensor, seed, spp, mode)

        def render_primarily_visible_silhouette(self, scene, sensor, sampler, spp):
            weight = self._view_weight  # Mitsuba divides each sample by spp: dividing spp multiplies the term
            if self.silhouette_samples <= 0:
                return silhouette_pass(self, scene, sensor, sampler, spp / weight)
            w, h = sensor.film().crop_size()
            sampler.set_samples_per_wavefront(1)
            sampler.seed(mi.UInt32(self._seed) ^ _SEED_SALT, self.silhouette_samples)
            return silhouette_pass(self, scene, sensor, sampler,
                                   equivalent_spp(int(w), int(h), self.silhouette_samples) / weight)

        def to_string(self):
            return f"Budgeted{base.__name__}[silhouette_samples={self.silhouette_samples}]"

    Budgeted.__name__ = Budgeted.__qualname__ = f"Budgeted{base.__name__}"
    return Budgeted


def silhouette_pass(integrator, scene, sensor, sampler, spp: float):
    """The primary-silhouette term of ``integrator`` (a Mitsuba projective integrator): Mitsuba 3.9's
    ``render_primarily_visible_silhouette`` with one correction, the splat position under a film crop window.

    Each sample picks a point on a silhouette seen from the sensor, evaluates the radiance difference across it and
    the point's motion, and splats ``difference * motion * J / pdf / spp`` where the point projects. The sensor's
    ``sample_direction`` returns that position *relative to the crop window*, while the film's image block
    subtracts the window's offset again; Mitsuba's pass thus drops or misplaces every sample of a cropped film
    (measured: the z-translation gradient of a sphere -1.23 full frame, -0.05 cropped). Adding the offset back
    makes a cropped render's silhouette gradient equal the full frame's on the window
    (tests/test_projective.py); without a crop the two are the same code."""
    import drjit as dr
    import mitsuba as mi

    film = sensor.film()
    aovs = integrator.aov_names()
    detail = integrator.proj_detail
    with dr.suspend_grad():
        centre = sensor.world_transform() @ mi.Point3f(0)
        ss = detail.sample_primarily_visible_silhouette(scene, centre, sampler.next_2d(), True)
        active = ss.is_valid() & (ss.pdf > 0)
        J = detail.sensor_jacobian(sensor, ss)
        dL, wavelengths = detail.eval_primary_silhouette_radiance_difference(scene, sampler, ss, sensor, active=active)
        active &= dr.any(dL != 0)
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.p, si.prim_index, si.uv = ss.p, ss.prim_index, ss.uv
    motion = dr.dot(ss.shape.differential_motion(dr.detach(si), active), ss.n)
    derivative = dL * motion * dr.rcp(ss.pdf) * J
    film.prepare(aovs)
    with dr.suspend_grad():
        it = dr.zeros(mi.Interaction3f)
        it.p = ss.p
        ds, _ = sensor.sample_direction(it, mi.Point2f(0))
    offset = film.crop_offset()
    block = film.create_block(normalize=True)
    block.set_coalesce(block.coalesce() and spp >= 4)
    block.put(pos=ds.uv + mi.Point2f(float(offset[0]), float(offset[1])), wavelengths=wavelengths,
              value=derivative * dr.rcp(mi.ScalarFloat(spp)), weight=0, alpha=1, active=active)
    film.put_block(block)
    return film.develop()
