"""Samples where they buy the most error per second: per-pixel spp for a render with the object, with the shared
background render as a control variate.

The background render (the scene without the object, same seed, ``spp`` samples) is rendered once per scene and
camera set and shared by every input. With common random numbers (:mod:`optimizer.rendering.tracer`) sample ``k``
of a pixel with the object, ``X_k``, and without it, ``Y_k``, follow the same path until it meets the object, so
their difference ``D_k = X_k - Y_k`` is exactly 0 for every path the object does not touch. The **control-variate
estimator** of a pixel rendered with ``n <= spp`` samples,

    E = mean(X_1..X_n) + mean(Y_1..Y_spp) - mean(Y_1..Y_n)  =  mean(Y_1..Y_spp) + mean(D_1..D_n),

is unbiased for any ``n`` fixed in advance and has variance ``v_D / n + (v_X - v_D) / spp`` (``v`` per sample;
at ``n = spp`` it is the plain mean's ``v_X / spp``): where the object changes few paths (its shadow's penumbra, the
ground it darkens a little, everything far from it) ``v_D`` is small and a few samples give the error of ``spp``;
where every path meets it (its own pixels) ``v_D = v_X + v_Y`` and the plain mean ``mean(X_1..X_n)`` (variance
``v_X / n``) is used instead. Each pixel gets the estimator with the smaller variance and a count ``n`` from the
ladder ``base * FACTORS`` (``base = spp / BASE_SHARE``; above ``spp`` the plain mean), chosen by a Lagrangian
(:func:`lagrange`): the least CPU seconds (cost per sample of the object's pixels and of the others, timed once per
scene, :func:`measure_costs`) for which the summed variance over the frame is at most a uniform ``spp``'s. The
result: the error of full tracing at ``spp`` (the sum of ``v_X / spp``), seconds spent where the variance is.

Steps (:func:`optimizer.rendering.render.render_allocated`): a **base pass** of ``base`` samples per pixel (over the
region the object can change, :mod:`optimizer.rendering.region`, or every pixel) kept as ``OBJECT_GROUPS`` group
means; the per-pixel variances ``v_X``, ``v_D`` from those groups and the background's groups of the same samples
(the background keeps :func:`background_groups` group means), weighted by the sRGB curve's slope (the error is
measured in sRGB) and **pooled over each pixel's neighbours, the pixel itself left out**
(:func:`optimizer.rendering.noise.pooled`; the default ``sturdy`` estimate, :func:`sturdy_pooled`, takes the larger of
the 5 x 5 mean and the 15 x 15 mean over the pixels of the same kind, the object's or the others', so that a rare
bright path seen by few neighbours is not read as no variance): a pixel's count and estimator never depend on its own samples, so its
estimate stays unbiased (the global multiplier depends on every pixel: an O(1/N) coupling); then **extra passes**,
one launch per ladder step, each pixel's random stream continued.

**Noise** (issue 28, item 4): the allocation minimises the frame's error, not the object's noise against the
background's; it does not keep the object no noisier than the background. ``noise_floor`` adds a per-pixel floor
(each pixel's count at least the smallest whose estimated variance is within ``TOLERANCE`` of the background's
``v_Y / spp``), but its estimates (4 groups of ``spp / 16`` samples, pooled) miss the rare bright paths of rough
transmission under a sun: on ``tests/test_noise.py``'s glass sphere it left the object and its rim 1.74x noisier
than the background (1.93x at a uniform spp; :mod:`optimizer.rendering.noise` reaches 1.15x). So ``camo evaluate``
and the study stimuli keep noise matching (:mod:`optimizer.rendering.noise`) and do not use this module yet;
``bench/bench_planner.py --allocation`` measures it against full path tracing.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: The base pass takes ``spp / BASE_SHARE`` samples per pixel.
BASE_SHARE = 4
#: A pixel's count is ``base * f`` for ``f`` in this ladder (at most ``FACTORS[-1] / BASE_SHARE`` x ``spp``); each
#: step is one launch of the pixels at or above it.
FACTORS = (1, 2, 3, 4, 6, 8, 12, 16)
#: Group means kept by the base pass (their spread gives the per-pixel variances).
OBJECT_GROUPS = 4
#: Neighbourhood (pixels) over which the variances are pooled, the pixel itself left out.
WINDOW = 5
#: The wider neighbourhood (pixels) of the sturdy estimate (:func:`sturdy_pooled`): over the pixels of the same
#: kind only (the object's, the others), each pixel's variance at least their mean over it.
WIDE_WINDOW = 15
#: The per-pixel variance estimates :func:`allocate` may use: ``local`` (the mean over ``WINDOW``) and ``sturdy``
#: (the default: :func:`sturdy_pooled`).
ESTIMATORS = ("local", "sturdy")
#: The allocation variants ``bench/bench_planner.py --estimators`` measures: (estimator, object floor).
VARIANTS = {"local": ("local", False), "sturdy": ("sturdy", False), "sturdy-floor": ("sturdy", True)}
#: A pixel's noise variance may exceed the background's by this factor (the estimate is not finer than that).
TOLERANCE = 1.1


def check_spp(spp: int) -> None:
    """Refuse an ``spp`` the allocation cannot split into its base pass and groups (one line)."""
    q = BASE_SHARE * OBJECT_GROUPS
    if int(spp) != spp or spp < q or spp % q:
        raise ValueError(f"per-pixel sample allocation needs spp a multiple of {q} (a base pass of spp/{BASE_SHARE} "
                         f"samples in {OBJECT_GROUPS} groups), got {spp}")


def background_groups(spp: int) -> int:
    """How many group means the background at ``spp`` keeps: groups of ``spp / 16`` samples, the base pass's group
    size (the control variate needs the background's mean over a pixel's first ``n`` samples for every ``n`` on the
    ladder up to ``spp``)."""
    check_spp(spp)
    return BASE_SHARE * OBJECT_GROUPS


def ladder(spp: int) -> np.ndarray:
    """The sample counts a pixel may get, ascending."""
    check_spp(spp)
    return np.array([spp // BASE_SHARE * f for f in FACTORS], np.int64)


@dataclasses.dataclass
class Allocation:
    samples: np.ndarray  # (V, H, W) int: samples with the object per pixel (0: the background's pixel as it is)
    control: np.ndarray  # (V, H, W) bool: the pixel's estimate uses the background as a control variate
    spp: int  # the uniform spp whose error is matched
    costs: tuple[float, float]  # CPU seconds per sample: the object's pixels, the others
    floor_share: float  # share of the rendered pixels whose count the noise floor raised
    seconds: float  # allocation and extra passes

    @property
    def factor(self) -> np.ndarray:
        """``(V, H, W)`` float: samples with the object per pixel over ``spp`` (0: the background's pixel)."""
        return self.samples / float(self.spp)

    def to_dict(self) -> dict:
        r = self.samples > 0
        s = self.samples[r]
        return {"method": "allocation", "spp": self.spp,
                "samples_share": round(float(s.sum() / (self.samples.size * self.spp)), 4) if s.size else 0.0,
                "extra_samples_share": round(float((s.sum() - s.size * self.spp) / (self.samples.size * self.spp)), 4)
                if s.size else 0.0,
                "samples_p5_p50_p95": [int(x) for x in np.percentile(s, [5, 50, 95])] if s.size else [],
                "control_variate_share": round(float(self.control[r].mean()), 4) if s.size else 0.0,
                "floor_share": round(self.floor_share, 4),
                "cost_per_sample_object_other": [float(f"{c:.3g}") for c in self.costs],
                "seconds": round(self.seconds, 3)}


def srgb_slope(linear: np.ndarray) -> np.ndarray:
    """d srgb / d linear of :func:`camo_base.imaging.linear_to_srgb` at ``linear`` (the curve's continuation above
    1, as the error is measured), elementwise."""
    x = np.clip(np.asarray(linear, np.float64), 0, None)
    return np.where(x <= 0.0031308, 12.92, 1.055 / 2.4 * np.maximum(x, 1e-12) ** (1 / 2.4 - 1))


def variances(obj_groups: np.ndarray, bg_groups: np.ndarray, group_size: int, weight: np.ndarray):
    """Per-sample variances ``(v_X, v_D, v_Y)``, each ``(V, H, W)``, of the render with the object, of its
    difference with the background and of the background, from the means of ``G`` groups of the same
    ``group_size`` samples ``(G, V, H, W, 3)`` (linear; ``bg_groups`` the background's groups of the same samples),
    each channel's variance weighted by ``weight (V, H, W, 3)`` (the squared sRGB slope) and averaged."""
    x, y = np.asarray(obj_groups, np.float64), np.asarray(bg_groups, np.float64)
    if x.shape != y.shape or x.ndim != 5 or x.shape[0] < 2:
        raise ValueError(f"groups must be two (G >= 2, V, H, W, 3) arrays of one shape, got {x.shape}, {y.shape}")

    def v(a):
        return (a.var(0, ddof=1) * group_size * weight).mean(-1)

    return v(x), v(x - y), v(y)


def variance_table(v_x: np.ndarray, v_d: np.ndarray, spp: int, levels: np.ndarray, control: np.ndarray) -> np.ndarray:
    """``(N, L)``: each pixel's estimator variance at each ladder count -- ``v_D / n + (v_X - v_D) / spp`` with the
    control variate (``control``, counts up to ``spp``), ``v_X / n`` otherwise."""
    n = np.asarray(levels, np.float64)[None, :]
    plain = v_x[:, None] / n
    cv = v_d[:, None] / n + (v_x - v_d)[:, None] / spp
    return np.where(control[:, None] & (n <= spp), cv, plain)


def lagrange(var: np.ndarray, cost: np.ndarray, levels: np.ndarray, target: float,
             allowed: np.ndarray | None = None, iterations: int = 64) -> np.ndarray:
    """Index into ``levels`` per pixel: the counts that minimise the seconds ``sum cost_i n_i`` subject to the summed
    variance ``sum var[i, n_i] <= target`` (``var (N, L)``: each pixel's variance at each count; ``allowed (N, L)``
    bool: the counts a pixel may take, default all). Each pixel takes ``argmin_n cost_i n + mu var[i, n]`` over its
    allowed counts, with the least multiplier ``mu`` (bisection in log mu) that meets the target; when even the
    largest counts cannot, the largest.

    Two pixels, variances 9 and 1 per sample at unit cost, counts 1-16, the target of a uniform 4 samples
    (10 / 4): Neyman's 3:1 ratio, rounded -- 5 and 2 samples, 7 in all instead of 8 (the least any pair meets it
    with).

    >>> import numpy as np
    >>> lv = np.arange(1, 17)
    >>> lv[lagrange(np.array([9.0, 1.0])[:, None] / lv, np.ones(2), lv, 10.0 / 4)].tolist()
    [5, 2]
    """
    var = np.asarray(var, np.float64)
    cost = np.asarray(cost, np.float64)
    levels = np.asarray(levels, np.float64)
    if var.ndim != 2 or var.shape[1] != levels.size or cost.shape != (var.shape[0],):
        raise ValueError(f"var must be (N, {levels.size}) and cost (N,), got {var.shape}, {cost.shape}")
    if np.any(cost <= 0) or not np.all(np.isfinite(cost)):
        raise ValueError("cost per sample must be positive and finite")
    if not target > 0:
        raise ValueError(f"the target summed variance must be positive, got {target}")
    big = np.float64(np.finfo(np.float64).max / 4)
    ok = np.ones(var.shape, bool) if allowed is None else np.asarray(allowed, bool).copy()
    ok[~ok.any(1), -1] = True  # a pixel that no count satisfies: the largest
    seconds = np.where(ok, cost[:, None] * levels[None, :], big)

    def pick(mu: float) -> np.ndarray:
        return np.argmin(seconds + mu * np.where(ok, var, 0.0), axis=1)

    def summed(idx: np.ndarray) -> float:
        return float(var[np.arange(var.shape[0]), idx].sum())

    if summed(pick(0.0)) <= target:
        return pick(0.0)
    scale = float(cost.sum() * levels[-1] / target)
    lo, hi = np.log(scale) - 40.0, np.log(scale) + 40.0
    if summed(pick(float(np.exp(hi)))) > target:
        return pick(float(np.exp(hi)))
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if summed(pick(float(np.exp(mid)))) <= target:
            hi = mid
        else:
            lo = mid
    return pick(float(np.exp(hi)))


def pooled_over(values: np.ndarray, rendered: np.ndarray, window: int = WINDOW) -> np.ndarray:
    """The mean of ``values (V, H, W)`` over each pixel's rendered neighbours (``window x window``, the pixel left
    out; :func:`optimizer.rendering.noise.pooled`), 0 where none is rendered."""
    from optimizer.rendering.noise import pooled

    r = np.asarray(rendered, np.float64)
    w = pooled(r, window)
    return np.where(w > 0, pooled(np.asarray(values, np.float64) * r, window) / np.maximum(w, 1e-12), 0.0)


def sturdy_pooled(values: np.ndarray, rendered: np.ndarray, kind: np.ndarray, window: int = WINDOW,
                  wide: int = WIDE_WINDOW) -> np.ndarray:
    """Per-pixel variances ``(V, H, W)`` that do not underrate rare bright paths: the larger of the mean of
    ``values`` over the pixel's ``window`` neighbours (:func:`pooled_over`) and their mean over its ``wide``
    neighbours of the same ``kind`` (bool ``(V, H, W)``: the object's pixels against the others), the pixel itself
    left out of both.

    Why: a pixel's variance comes from the base pass's ``spp / 4`` samples in 4 groups; a path of rough
    transmission that carries the sun (probability ~1/400 per sample, 50x the pixel's mean) shows up in about one
    of the 24 neighbours' 384 samples, so the local mean is ~0 on many pixels that have that variance. The
    allocation gives such a pixel the base pass only (a quarter of ``spp``), and its error is 4x the uniform
    render's there: on such a field (``tests/test_allocation.py``) the allocation planned on the local mean reaches
    2.3x the error variance it aimed at. An underrated pixel costs error in ``1 / n``, an overrated one seconds in
    ``n``: the wide mean over the pixels of one kind (~200 neighbours, ~3,000 samples: the fireflies of a body are
    seen, the sky's smooth pixels do not lift the object's or the reverse) keeps the local estimate where it is
    higher (an edge, a caustic) and lifts it where it saw no rare path."""
    kind = np.asarray(kind, bool)
    rendered = np.asarray(rendered, bool)
    local = pooled_over(values, rendered, window)
    out = local
    for k in (kind, ~kind):
        out = np.where(k, np.maximum(out, pooled_over(values, rendered & k, wide)), out)
    return out


def allocate(obj_groups: np.ndarray, bg_groups: np.ndarray, group_size: int, reference: np.ndarray,
             cost: np.ndarray, rendered: np.ndarray, spp: int, noise_floor: bool = True,
             window: int = WINDOW, kind: np.ndarray | None = None, estimator: str = "sturdy",
             object_floor: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """``(samples (V, H, W) int, control (V, H, W) bool, floor_share)`` for the pixels ``rendered`` (0 samples
    elsewhere): the module doc's allocation. ``obj_groups`` / ``bg_groups``: ``(G, V, H, W, 3)`` group means of the
    base pass and of the background over the same samples; ``reference (V, H, W, 3)``: an image whose pooled value
    sets the sRGB slope (the base pass with the object); ``cost (V, H, W)``: seconds per sample; ``kind (V, H, W)``
    bool: the object's pixels (the sturdy estimate pools over pixels of one kind; default: the pixels whose cost is
    the largest); ``estimator``: one of :data:`ESTIMATORS`; ``object_floor``: the object's own pixels (``kind``)
    never below ``spp`` samples.

    Why the object floor: a body of rough transmission is where the base pass cannot see the variance (its rare
    bright paths) and where a sample costs most (1.6-4.6x the others'), so the Lagrangian starves it on an
    underrated estimate -- on the panorama (4 views, 96 px, 3 seeds) the object's pixels got a median 32 of 64
    samples and their squared error rose 35 % over a uniform 64 spp's, more than the other pixels saved. With the
    floor its error is the uniform render's and the saving comes from the pixels the control variate serves."""
    check_spp(spp)
    if estimator not in ESTIMATORS:
        raise ValueError(f"unknown variance estimator {estimator!r}: choose one of {', '.join(ESTIMATORS)}")
    rendered = np.asarray(rendered, bool)
    full_cost = np.asarray(cost, np.float64)
    kind = full_cost >= full_cost.max() if kind is None else np.asarray(kind, bool)  # the object's pixels
    slope = np.stack([pooled_over(np.asarray(reference)[..., c], np.ones(rendered.shape, bool), window)
                      for c in range(3)], -1)
    v_x, v_d, v_y = variances(obj_groups, bg_groups, group_size, srgb_slope(slope) ** 2)
    if estimator == "local":
        v_x, v_d, v_y = (pooled_over(v, rendered, window)[rendered] for v in (v_x, v_d, v_y))
    else:
        v_x, v_d, v_y = (sturdy_pooled(v, rendered, kind, window)[rendered] for v in (v_x, v_d, v_y))
    levels = ladder(spp)
    control = v_d < v_x
    table = variance_table(v_x, v_d, spp, levels, control)
    c = np.asarray(cost, np.float64)[rendered]
    target = float(np.sum(v_x)) / spp
    out_n = np.zeros(rendered.shape, np.int64)
    out_c = np.zeros(rendered.shape, bool)
    if v_x.size == 0 or target <= 0:
        out_n[rendered] = spp
        return out_n, out_c, 0.0
    allowed = table <= TOLERANCE * v_y[:, None] / spp + 1e-15 if noise_floor else None
    if object_floor:
        own = kind[rendered]
        at_least = ~own[:, None] | (levels[None, :] >= spp)
        allowed = at_least if allowed is None else allowed & at_least
    idx = lagrange(table, c, levels, target, allowed)
    floor_share = 0.0
    if noise_floor:
        free = lagrange(table, c, levels, target)
        floor_share = float(np.mean(idx > free))
    out_n[rendered] = levels[idx]
    out_c[rendered] = control
    return out_n, out_c, floor_share


def measure_costs(renderer, coverage: np.ndarray, rendered: np.ndarray, spp: int) -> tuple[float, float]:
    """CPU seconds per sample ``(object's pixels, the others)`` of ``renderer`` (a
    :class:`optimizer.rendering.render.PathRenderer` with the object): ``spp`` samples of the object's pixels
    (``coverage > 0``) within ``rendered`` and of as many other rendered pixels spread over them, the least of two
    launches each after one that compiles. Once per scene: their ratio is what the allocation uses."""
    import time

    obj = (np.asarray(coverage) > 0) & rendered
    rest = rendered & ~obj
    idx = np.flatnonzero(rest)
    if obj.sum() and idx.size > obj.sum():
        keep = idx[np.linspace(0, idx.size - 1, int(obj.sum())).astype(np.int64)]
        rest = np.zeros(rendered.size, bool)
        rest[keep] = True
        rest = rest.reshape(rendered.shape)
    out = []
    for m in (obj, rest):
        if not m.any():
            out.append(float("nan"))
            continue
        best = float("inf")
        for k in range(3):
            t = time.process_time()
            renderer(m, None, spp=spp, first_sample=1_000_000 + k * spp)
            if k:
                best = min(best, time.process_time() - t)
        out.append(max(best, 1e-9) / (float(m.sum()) * spp))
    c_obj, c_rest = out
    c_obj = c_obj if np.isfinite(c_obj) else c_rest
    c_rest = c_rest if np.isfinite(c_rest) else c_obj
    return (float(c_obj), float(c_rest)) if np.isfinite(c_obj) else (1.0, 1.0)


def extra_passes(renderer, image: np.ndarray, samples: np.ndarray, spp: int) -> np.ndarray:
    """``(V, H, W, 3)``: each pixel's mean over its ``samples (V, H, W)`` samples, from ``image`` (the base pass's
    means, ``spp / BASE_SHARE`` samples) and one launch per ladder step (samples ``n`` to ``n'`` of the pixels whose
    count is at least ``n'``)."""
    levels = ladder(spp)
    total = np.array(image, np.float64, copy=True) * levels[0]
    for lo, hi in zip(levels[:-1], levels[1:]):
        sel = samples >= hi
        if not sel.any():
            break
        more = renderer(sel, None, spp=int(hi - lo), first_sample=int(lo))
        total[sel] += np.asarray(more, np.float64)[sel] * float(hi - lo)
    return total / np.maximum(samples, 1)[..., None]


def combine(x_mean: np.ndarray, samples: np.ndarray, control: np.ndarray, bg_groups: np.ndarray,
            background: np.ndarray, spp: int) -> np.ndarray:
    """The estimate per pixel ``(V, H, W, 3)`` float32: ``x_mean`` (each pixel's mean over its ``samples``) plus,
    where ``control`` and ``samples < spp``, the background at ``spp`` minus the background over the same first
    ``samples`` samples (``bg_groups (G, V, H, W, 3)``: consecutive group means of ``spp / G`` samples); the
    ``background`` itself where ``samples == 0``."""
    g = np.asarray(bg_groups, np.float64)
    G = g.shape[0]
    size = spp // G
    cum = np.cumsum(g, 0)  # cum[k - 1] / k: the mean of the first k groups
    k = np.clip(samples // size, 1, G)
    first = np.take_along_axis(cum, (k - 1)[None, ..., None].repeat(3, -1), 0)[0] / k[..., None]
    bg = np.asarray(background, np.float64)
    use = (control & (samples < spp) & (samples > 0))[..., None]
    out = np.where(use, x_mean + bg - first, x_mean)
    return np.where((samples > 0)[..., None], out, bg).astype(np.float32)
