"""A path tracer over a chosen set of pixels, with per-pixel random streams, and a pilot mode that says where
each pixel's light came from.

Why not Mitsuba's ``path`` with a cropped film: Mitsuba seeds sample ``i`` of a render from ``(seed, i)``, and ``i``
counts the samples of the *rendered window*, so a window's pixel gets other random numbers than the same pixel of a
full-frame render. A render with and without the object must share them (common random numbers: paths that miss
the object give the same radiance in both, so a metric sees the object, not two noise patterns), and a window
render of the object must be exact against the full-frame background. Here sample ``s`` of pixel ``p`` (row-major
in the full frame; several views side by side in one ``batch`` film) draws from a PCG32 stream keyed by
``(seed, s, p)`` (:func:`pixel_rng`) whatever else is rendered, so any subset of pixels reproduces the full frame's samples, and the per-pixel mean is a
fixed-order block sum (the result does not depend on the thread count).

The estimator is Mitsuba's ``path`` / ``prb`` estimator: next-event estimation and BSDF sampling combined by
multiple importance sampling (power heuristic), Russian roulette from vertex ``rr_depth`` with survival probability
``min(max(throughput) * eta^2, 0.95)``; ``max_depth`` counts vertices like Mitsuba (2 = direct light only).
``tests/test_tracer.py`` checks it against Mitsuba's ``path`` (the same mean, the same variance).

With ``record=True`` (the planner's pilot) it also returns per pixel, as luminance (Rec. 709, linear), averaged
over the samples (see :data:`RECORD`):

``m{M}``      the contribution that needs ``max_depth >= M`` (an emitter hit at vertex ``k`` needs ``k + 1``, the
              emitter sample taken at vertex ``k`` needs ``k + 2``): a render at ``max_depth = M`` is exactly
              ``m1 + ... + mM`` of the same samples;
``q{M}``      the square of that partial sum per sample (mean minus squared mean: the per-sample variance of a
              render at ``max_depth = M``);
``n{k}``      1 for each sample still traced when vertex ``k`` is searched (a render at ``max_depth = M`` casts
              ``n0 + ... + n{M-1}`` rays of each kind per sample: the cost model);
``via``       light that reached a surface of the environment by way of the object (colour bleeding, light the
              object reflects onto the ground): the path met the environment, then the object;
``via_t``     its part that went *through* the object (transmission): the caustic chains that lighten a
              transmissive object's shadow, and ``via_t2`` its square per sample (the noise they bring);
``seen_t``    light seen through the object (a transmission at the object before any environment vertex), and
              ``seen_t2`` its square per sample;
``e{i}``      the light of emitter ``i`` (``scene.emitters()`` order; further ones are added to the last).

The object is the shape with id :data:`optimizer.rendering.scene.OBJECT_ID`. The loop is unrolled in Python, one
wavefront kernel per vertex (each compiles once and is cached).
"""

from __future__ import annotations

import numpy as np

MAX_EMITTERS = 4
LUMA = (0.2126, 0.7152, 0.0722)


def record_names(max_depth: int, emitters: int) -> list[str]:
    """Names of the ``record=True`` outputs, in order (module doc)."""
    m = [f"m{i}" for i in range(1, max_depth + 1)]
    q = [f"q{i}" for i in range(1, max_depth + 1)]
    n = [f"n{i}" for i in range(max_depth)]
    e = [f"e{i}" for i in range(min(max(emitters, 1), MAX_EMITTERS))]
    return m + q + n + ["via", "via_t", "via_t2", "seen_t", "seen_t2"] + e


def pixel_rng(pixel, sample, key: int):
    """One PCG32 stream per entry of ``pixel`` / ``sample`` (``mi.UInt32``): sample ``s`` of pixel ``p`` is seeded by
    ``TEA(key + s * 0x9E3779B9, p)`` (Mitsuba's ``independent`` sampler seeds lane ``i`` by ``TEA(seed, i)``). Sample
    ``s`` of a pixel is the same whatever the spp, so a render at ``2 spp`` holds the one at ``spp``."""
    import drjit as dr
    import mitsuba as mi

    k = dr.opaque(mi.UInt32, int(key) & 0xFFFFFFFF) + sample * mi.UInt32(0x9E3779B9)
    v0, v1 = mi.sample_tea_32(k, pixel)
    rng = mi.PCG32(dr.width(pixel))
    rng.seed(mi.UInt64(v0), mi.UInt64(v1))
    return rng


#: The samplers :func:`render_views` offers: ``independent`` (every dimension of every sample from the pixel's PCG32
#: streams) and ``sobol`` (:func:`sobol_samples`: the camera ray's position in the pixel and the first vertex's
#: emitter and BSDF samples stratified across a pixel's samples; every later dimension independent).
SAMPLERS = ("independent", "sobol")
_SOBOL_SALT = 0x5A3C9E17


def _brev(x):
    import drjit as dr

    return dr.brev(x)


def owen_scramble(x, seed):
    """Nested uniform (Owen) scrambling of the 32-bit fractions ``x`` (``mi.UInt32``) keyed by ``seed`` (one per
    entry): Burley's hash-based Laine-Karras permutation on the reversed bits ("Practical Hash-based Owen
    Scrambling", JCGT 2020). Every output is uniform on [0, 2^32) over the seeds, and a (0, m, 2)-net stays one."""
    import mitsuba as mi

    x = _brev(x)
    x = x + seed
    x ^= x * mi.UInt32(0x6C50B47C)
    x ^= x * mi.UInt32(0xB82F1E52)
    x ^= x * mi.UInt32(0xC7AFE638)
    x ^= x * mi.UInt32(0x8D22F6E6)
    return _brev(x)


def sobol01(index):
    """The first two dimensions of the Sobol sequence as 32-bit fractions (``mi.UInt32`` each) of ``index``
    (``mi.UInt32``): van der Corput and the Pascal-matrix dimension, a (0, 2)-sequence in base 2 (every aligned block
    of 2^m consecutive indices is a (0, m, 2)-net: one point in each of any 2^m equal elementary rectangles)."""
    import drjit as dr
    import mitsuba as mi

    x = _brev(index)
    y = dr.zeros(mi.UInt32, dr.width(index))
    v = 1 << 31
    for b in range(32):
        y = dr.select(((index >> b) & 1) != 0, y ^ mi.UInt32(v), y)
        v ^= v >> 1
    return x, y


def sobol_samples(pixel, sample, key: int, pairs: int):
    """``pairs`` stratified 2D samples (``mi.Point2f`` each) for sample ``sample`` of pixel ``pixel``: pair ``j`` is
    the Owen-scrambled Sobol (0, 2)-sequence at index ``sample`` (pair 0) or at the index shuffled by an Owen
    scramble of its bits in reverse order (pairs 1 on: Burley's shuffle, which maps every aligned run of 2^m indices
    onto an aligned run of 2^m), the scrambles keyed by ``(key, pixel, j)`` (TEA), so that

    * each sample is uniform on the unit square (unbiased, as the independent sampler),
    * any ``2^m`` consecutive samples of a pixel from a multiple of ``2^m`` (its first ``spp``, or the ``spp`` after
      them) are a (0, m, 2)-net in every pair (one sample per elementary rectangle of area 2^-m): the pixel's
      samples cover the pair's square evenly, at any spp, and sample ``s`` is the same whatever the spp,
    * the pairs are decorrelated from each other (a pixel's samples meet the pairs' strata in a random order; without
      the shuffle pair 1's coordinates would be a fixed function of pair 0's within a pixel), as padded sampling
      does.

    Measured reason it is hand-written: Mitsuba's ``ldsampler`` / ``multijitter`` number their samples per rendered
    lane, not per (pixel, sample), so a region render would not reproduce the full frame's samples
    (module docstring)."""
    import drjit as dr
    import mitsuba as mi

    out = []
    base = (int(key) ^ _SOBOL_SALT) & 0xFFFFFFFF
    for j in range(int(pairs)):
        # opaque: the seed is a kernel input, not a literal (a literal compiles the kernel anew for every seed)
        s0, s1 = mi.sample_tea_32(dr.opaque(mi.UInt32, (base + 2 * j) & 0xFFFFFFFF), pixel)
        s2, _ = mi.sample_tea_32(dr.opaque(mi.UInt32, (base + 2 * j + 1) & 0xFFFFFFFF), pixel)
        idx = owen_scramble(sample, s2) if j else sample  # a shuffle: pair j's k-th sample is not pair 0's
        x, y = sobol01(idx)
        x, y = owen_scramble(x, s0), owen_scramble(y, s1)
        out.append(mi.Point2f(mi.Float(x >> 8) * (1.0 / (1 << 24)), mi.Float(y >> 8) * (1.0 / (1 << 24))))
    return out


def trace(scene, ray, rng, max_depth: int, rr_depth: int, record: bool = False, first=None):
    """Radiance along ``ray`` (``mi.Spectrum``) and, with ``record``, the list of per-sample records of
    :func:`record_names` (luminance; else None). ``rng``: an ``mi.PCG32`` with one stream per ray (advanced).
    ``first``: ``(emitter, bsdf)`` 2D samples (``mi.Point2f``) the first vertex uses instead of the streams' (the
    ``sobol`` sampler, :func:`sobol_samples`); the streams advance alike, so later vertices draw the same numbers.
    One symbolic loop over the path's vertices (one kernel)."""
    import drjit as dr
    import mitsuba as mi
    from mitsuba.ad.integrators.common import mis_weight

    from optimizer.rendering.scene import OBJECT_ID

    K = int(max_depth)
    if K < 1:
        raise ValueError("max_depth must be >= 1")
    ctx = mi.BSDFContext()
    obj = next((s for s in scene.shapes() if s.id() == OBJECT_ID), None) if record else None
    obj_ptr = mi.ShapePtr(obj) if obj is not None else None
    emitters = list(scene.emitters())
    n_e = min(max(len(emitters), 1), MAX_EMITTERS)
    em_ptrs = [mi.EmitterPtr(e) for e in emitters]
    n = dr.width(ray.o)

    def lum(s):
        return LUMA[0] * s[0] + LUMA[1] * s[1] + LUMA[2] * s[2]

    def emitter_index(ptr):
        idx = mi.UInt32(n_e - 1)
        for i in reversed(range(min(len(em_ptrs), n_e - 1))):
            idx = dr.select(ptr == em_ptrs[i], mi.UInt32(i), idx)
        return idx

    def zeros(count):
        return tuple(dr.zeros(mi.Float, n) for _ in range(count))

    prev = dr.zeros(mi.Interaction3f, n)
    pi = scene.ray_intersect_preliminary(ray, coherent=True, active=dr.full(mi.Bool, True, n))
    state = (mi.UInt32(0), dr.full(mi.Bool, True, n), mi.Ray3f(ray), pi, dr.full(mi.Spectrum, 1.0, n),
             dr.full(mi.Float, 1.0, n), prev, dr.full(mi.Float, 1.0, n), dr.full(mi.Bool, True, n),
             dr.zeros(mi.Spectrum, n), rng)
    if record:
        flags = tuple(dr.full(mi.Bool, False, n) for _ in range(4))  # env_seen, via, via_t, seen_t
        state += (flags, zeros(K + 2), zeros(K), zeros(3), zeros(n_e))

    def cond(depth, active, *rest):
        return active

    def body(depth, active, ray, pi, β, η, prev, prev_pdf, prev_delta, L, rng, *rec):
        si = pi.compute_surface_interaction(ray, ray_flags=mi.RayFlags.All, active=active)
        # emitter hit at vertex ``depth`` (needs max_depth >= depth + 1); Mitsuba's MIS against emitter sampling
        ds = mi.DirectionSample3f(scene, si=si, ref=prev)
        em_pdf = scene.pdf_emitter_direction(prev, ds, active & ~prev_delta & (depth > 0))
        mis = dr.select(depth > 0, mis_weight(prev_pdf, em_pdf), 1.0)
        Le = dr.select(active, β * mis * ds.emitter.eval(si, active), 0.0)
        active_next = active & si.is_valid() & (depth + 1 < K)
        bsdf = si.bsdf(ray)
        # emitter sample at vertex ``depth`` (needs max_depth >= depth + 2)
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        u = mi.Point2f(rng.next_float32(), rng.next_float32())
        if first is not None:
            u = dr.select(depth == 0, first[0], u)
        ds_em, em_w = scene.sample_emitter_direction(si, u, True, active_em)
        active_em &= ds_em.pdf != 0.0
        wo = si.to_local(ds_em.d)
        val, pdf = bsdf.eval_pdf(ctx, si, wo, active_em)
        mis_em = dr.select(ds_em.delta, 1.0, mis_weight(ds_em.pdf, pdf))
        Lr = dr.select(active_em, β * mis_em * val * em_w, 0.0)
        L = L + Le + Lr
        # BSDF sample: the next vertex
        u1 = rng.next_float32()
        u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        if first is not None:
            u2 = dr.select(depth == 0, first[1], u2)
        bs, bw = bsdf.sample(ctx, si, u1, u2, active_next)
        if record:
            (env_seen, via, via_t, seen_t), A, alive, cats, E = rec
            alive = tuple(a + dr.select(active & (depth == k), 1.0, 0.0) for k, a in enumerate(alive))
            on_obj = si.is_valid() & (si.shape == obj_ptr) if obj_ptr is not None else mi.Bool(False)
            y_le, y_lr = lum(Le), lum(Lr)
            A = tuple(a + dr.select(depth + 1 == m, y_le, 0.0) + dr.select(depth + 2 == m, y_lr, 0.0)
                      for m, a in enumerate(A))
            via_here = via | (active_next & on_obj & env_seen)
            through = on_obj & (wo.z * si.wi.z < 0.0)
            c_via, c_via_t, c_seen_t = cats
            c_via = c_via + dr.select(via, y_le, 0.0) + dr.select(via_here, y_lr, 0.0)
            c_via_t = c_via_t + dr.select(via_t, y_le, 0.0) + dr.select(via_t | (through & env_seen), y_lr, 0.0)
            c_seen_t = c_seen_t + dr.select(seen_t, y_le, 0.0) + dr.select(seen_t | (through & ~env_seen), y_lr, 0.0)
            ei_le, ei_lr = emitter_index(ds.emitter), emitter_index(ds_em.emitter)
            E = tuple(e + dr.select(ei_le == i, y_le, 0.0) + dr.select(ei_lr == i, y_lr, 0.0) for i, e in enumerate(E))
            is_t = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Transmission)
            via_t = via_t | (active_next & on_obj & env_seen & is_t)
            seen_t = seen_t | (active_next & on_obj & ~env_seen & is_t)
            via = via_here
            env_seen = env_seen | (active_next & ~on_obj)
            rec = ((env_seen, via, via_t, seen_t), A, alive, (c_via, c_via_t, c_seen_t), E)
        prev = dr.zeros(mi.Interaction3f)
        prev.p, prev.n, prev.t, prev.time, prev.wavelengths = si.p, si.n, si.t, si.time, si.wavelengths
        ray = si.spawn_ray(si.to_world(bs.wo))
        η = η * bs.eta
        β = β * bw
        prev_pdf = bs.pdf
        prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        β_max = dr.max(mi.unpolarized_spectrum(β))
        active_next &= β_max != 0.0
        rr_prob = dr.minimum(β_max * η**2, 0.95)
        rr_continue = rng.next_float32() < rr_prob  # drawn at every vertex, as Mitsuba's prb does
        rr_active = depth >= rr_depth
        β = dr.select(rr_active, β * dr.rcp(rr_prob), β)
        active_next &= ~rr_active | rr_continue
        pi = scene.ray_intersect_preliminary(ray, coherent=False, active=active_next)
        return (depth + 1, active_next, ray, pi, β, η, prev, prev_pdf, prev_delta, L, rng, *rec)

    out = dr.while_loop(state, cond, body, max_iterations=K, label="camo tracer")
    L = out[9]
    if not record:
        return L, None
    _, A, alive, (c_via, c_via_t, c_seen_t), E = out[11:]
    partial = dr.zeros(mi.Float, n)
    squares = []
    for m in range(1, K + 1):
        partial = partial + A[m]
        squares.append(partial * partial)
    return L, list(A[1:K + 1]) + squares + list(alive) + [c_via, c_via_t, c_via_t * c_via_t, c_seen_t,
                                                          c_seen_t * c_seen_t] + list(E)


def pixel_rays(sensor, width: int, height: int, pixels, spp: int, key: int, first_sample: int = 0,
               sampler: str = "independent"):
    """Camera rays for ``spp`` samples of each pixel in ``pixels`` (flat row-major indices of the full
    ``width x height`` film), sample-major within a pixel, samples ``first_sample`` to ``first_sample + spp - 1``,
    and their random streams (:func:`pixel_rng`). ``first_sample`` may be an array, one per entry of ``pixels``
    (a pixel may then appear several times, each entry another run of its samples). Returns ``(ray, weight, rng,
    first)``: ``first`` the first vertex's stratified ``(emitter, bsdf)`` samples with ``sampler = "sobol"``
    (:func:`sobol_samples`; the position in the pixel is its first pair), else None."""
    import drjit as dr
    import mitsuba as mi

    pix = mi.UInt32(np.ascontiguousarray(pixels, dtype=np.uint32))
    n = dr.width(pix) * spp
    lane = dr.arange(mi.UInt32, n)
    p = dr.gather(mi.UInt32, pix, lane // spp)
    if np.ndim(first_sample):
        first = dr.gather(mi.UInt32, mi.UInt32(np.ascontiguousarray(first_sample, dtype=np.uint32)), lane // spp)
    else:
        first = dr.opaque(mi.UInt32, int(first_sample))
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
    s = lane % spp + first
    rng = pixel_rng(p, s, key)
    x = mi.Float(p % width)
    y = mi.Float(p // width)
    ux = rng.next_float32()
    uy = rng.next_float32()
    strat = None
    if sampler == "sobol":
        cam, em, bs = sobol_samples(p, s, key, 3)
        ux, uy = cam.x, cam.y
        strat = (em, bs)
    pos = mi.Point2f((x + ux) / width, (y + uy) / height)
    ray, weight = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    return ray, weight, rng, strat


def render_pixels(scene, sensor, width: int, height: int, pixels, spp: int, seed: int, max_depth: int,
                  rr_depth: int = 5, record: bool = False, chunk: int = 1 << 22, first_sample: int = 0,
                  moments: bool = False, groups: int = 1, sampler: str = "independent"):
    """``(rgb, records, lum2, group_rgb)``: the mean radiance ``(N, 3)`` float32 of the pixels ``pixels`` (flat
    indices into ``width x height``); with ``record``, the mean records ``(N, R)`` float32 of :func:`record_names`
    (else None); with ``moments``, the mean squared luminance per sample ``(N,)`` (its per-sample variance is
    ``lum2 - Y^2``; else None); with ``groups`` > 1 (dividing ``spp``), the means of the ``groups`` consecutive
    groups of samples ``(N, groups, 3)`` (their mean is ``rgb``; else None). Samples ``first_sample`` to
    ``first_sample + spp - 1`` of each pixel are traced (a later call with ``first_sample = spp`` adds new ones;
    an array: one first sample per entry of ``pixels``, which may repeat a pixel).
    Pixels are rendered in chunks of at most ``chunk`` samples (each pixel's samples stay in one chunk; the result
    does not depend on the chunking). ``seed`` keys the random streams (:func:`pixel_rng`); ``sampler``: one of
    :data:`SAMPLERS` (``sobol``: stratified across each pixel's samples, :func:`sobol_samples`)."""
    import drjit as dr

    pixels = np.asarray(pixels, dtype=np.int64).ravel()
    if np.ndim(first_sample):
        first_sample = np.asarray(first_sample, dtype=np.int64).ravel()
        if first_sample.shape != pixels.shape:
            raise ValueError(f"first_sample has {first_sample.size} entries, pixels {pixels.size}")
    groups = int(groups)
    if groups < 1 or spp % groups:
        raise ValueError(f"groups must divide spp ({spp}), got {groups}")
    if pixels.size == 0:
        return (np.zeros((0, 3), np.float32), np.zeros((0, 0), np.float32) if record else None,
                np.zeros(0, np.float32) if moments else None, np.zeros((0, groups, 3), np.float32) if groups > 1 else None)
    per = max(1, chunk // max(int(spp), 1))
    key = int(seed) & 0xFFFFFFFF
    rgb_parts, rec_parts, m2_parts, grp_parts = [], [], [], []
    with dr.suspend_grad():
        for start in range(0, pixels.size, per):
            part = pixels[start:start + per]
            first = first_sample[start:start + per] if np.ndim(first_sample) else first_sample
            ray, weight, rng, strat = pixel_rays(sensor, width, height, part, int(spp), key, first, sampler)
            L, rec = trace(scene, ray, rng, max_depth, rr_depth, record, strat)
            L = L * weight
            dr.eval(L, rec)  # one launch of the path loop for every output (a block sum would evaluate each alone)
            if groups > 1:
                g = [dr.block_sum(L[c], spp // groups) for c in range(3)]
                dr.eval(*g)
                grp = np.stack([np.asarray(x) for x in g], -1).reshape(-1, groups, 3) / (spp // groups)
                grp_parts.append(grp.astype(np.float32))
            sums = [dr.block_sum(L[c], spp) for c in range(3)]
            if moments:
                y = LUMA[0] * L[0] + LUMA[1] * L[1] + LUMA[2] * L[2]
                sums.append(dr.block_sum(y * y, spp))
            if record:
                sums += [dr.block_sum(r, spp) for r in rec]
            dr.eval(*sums)
            rgb = np.stack([np.asarray(x) for x in sums[:3]], -1) / spp
            rgb_parts.append(rgb.astype(np.float32))
            k = 3
            if moments:
                m2_parts.append(np.asarray(sums[3]).astype(np.float32) / spp)
                k = 4
            if record:
                rec_parts.append(np.stack([np.asarray(x) for x in sums[k:]], -1).astype(np.float32) / spp)
    return (np.concatenate(rgb_parts), np.concatenate(rec_parts) if record else None,
            np.concatenate(m2_parts) if moments else None, np.concatenate(grp_parts) if groups > 1 else None)


def render_views(scene, views: int, width: int, height: int, spp: int, seed: int, max_depth: int,
                 rr_depth: int = 5, masks: np.ndarray | None = None, fill: np.ndarray | None = None,
                 record: bool = False, moments: bool = False, first_sample: int = 0, groups: int = 1,
                 counts: np.ndarray | None = None, sampler: str = "independent"):
    """Every view of ``scene``'s first sensor, a ``batch`` sensor of ``views`` views of ``width x height``
    (:func:`optimizer.rendering.scene.batch`; its film is ``views * width`` wide, and pixel ``p`` of that film is
    the key of its random streams): ``(V, H, W, 3)`` float32 linear radiance. Only the pixels where ``masks
    (V, H, W)`` is set are rendered (None: all), the others copied from ``fill (V, H, W, 3)`` (zeros when None).
    With ``record``, ``moments`` and/or ``groups`` > 1, a tuple: the image, then the mean records ``(V, H, W, R)`` of
    :func:`record_names`, the mean squared luminance ``(V, H, W)`` and/or the group means ``(G, V, H, W, 3)`` (zeros
    outside ``masks``). ``first_sample``, ``groups``: see :func:`render_pixels`.

    ``counts (V, H, W)`` int (instead of ``masks``): pixel ``p`` gets ``counts[p] * spp`` samples, ``first_sample``
    to ``first_sample + counts[p] * spp - 1`` of its stream, all pixels in one launch (pixels with count 0: ``fill``);
    the image only. The mean is taken over runs of ``spp`` samples, then over the runs: the same estimator as
    ``counts[p] * spp`` samples from ``first_sample`` (equal up to float rounding, ``tests/test_noise.py``)."""
    V, H, W = int(views), int(height), int(width)
    if counts is not None:
        if masks is not None or record or moments or groups > 1:
            raise ValueError("counts renders the image only, without masks")
        return _render_counts(scene, V, W, H, spp, seed, max_depth, rr_depth, counts, fill, first_sample, sampler)
    wide = np.zeros((H, V * W), bool)
    if masks is None:
        wide[:] = True
    else:
        m = np.asarray(masks, bool)
        if m.shape != (V, H, W):
            raise ValueError(f"masks must be {(V, H, W)}, got {m.shape}")
        wide = m.transpose(1, 0, 2).reshape(H, V * W)
    idx = np.flatnonzero(wide.ravel())
    rgb, rec, m2, grp = render_pixels(scene, scene.sensors()[0], V * W, H, idx, spp, seed, max_depth, rr_depth,
                                      record, first_sample=first_sample, moments=moments, groups=groups,
                                      sampler=sampler)
    out = np.zeros((H * V * W, 3), np.float32)
    if fill is not None:
        out[:] = np.asarray(fill, np.float32).transpose(1, 0, 2, 3).reshape(H * V * W, 3)
    out[idx] = rgb
    img = out.reshape(H, V, W, 3).transpose(1, 0, 2, 3).copy()
    if not record and not moments and groups <= 1:
        return img
    res = [img]
    if record:
        recs = np.zeros((H * V * W, rec.shape[1] if rec.size else 0), np.float32)
        recs[idx] = rec
        res.append(recs.reshape(H, V, W, -1).transpose(1, 0, 2, 3).copy())
    if moments:
        mm = np.zeros(H * V * W, np.float32)
        mm[idx] = m2
        res.append(mm.reshape(H, V, W).transpose(1, 0, 2).copy())
    if groups > 1:
        gg = np.zeros((H * V * W, groups, 3), np.float32)
        gg[idx] = grp
        res.append(gg.reshape(H, V, W, groups, 3).transpose(3, 1, 0, 2, 4).copy())
    return tuple(res)


def _render_counts(scene, V: int, W: int, H: int, spp: int, seed: int, max_depth: int, rr_depth: int,
                   counts: np.ndarray, fill: np.ndarray | None, first_sample: int,
                   sampler: str = "independent") -> np.ndarray:
    """:func:`render_views` with ``counts``: every run of ``spp`` samples is an entry of one launch."""
    c = np.asarray(counts)
    if c.shape != (V, H, W):
        raise ValueError(f"counts must be {(V, H, W)}, got {c.shape}")
    if (c < 0).any():
        raise ValueError("counts must be >= 0")
    wide = c.astype(np.int64).transpose(1, 0, 2).reshape(-1)
    idx = np.flatnonzero(wide)
    n = wide[idx]
    entries = np.repeat(idx, n)  # pixel of each run, a pixel's runs consecutive
    starts = np.concatenate([[0], np.cumsum(n)[:-1]])
    run = np.arange(entries.size) - np.repeat(starts, n)  # 0 .. n - 1 within a pixel
    rgb = render_pixels(scene, scene.sensors()[0], V * W, H, entries, spp, seed, max_depth, rr_depth,
                        first_sample=int(first_sample) + run * int(spp), sampler=sampler)[0]
    out = np.zeros((H * V * W, 3), np.float32)
    if fill is not None:
        out[:] = np.asarray(fill, np.float32).transpose(1, 0, 2, 3).reshape(H * V * W, 3)
    if idx.size:
        out[idx] = (np.add.reduceat(rgb.astype(np.float64), starts, axis=0) / n[:, None]).astype(np.float32)
    return out.reshape(H, V, W, 3).transpose(1, 0, 2, 3).copy()
