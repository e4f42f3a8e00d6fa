"""Denoising a path-traced render with Intel Open Image Denoise (OIDN, PyPI ``pyoidn``), with its auxiliary features.

Radiance is linear float32 ``(V, H, W, 3)`` (HDR, non-negative); features are albedo ``(V, H, W, 3)`` in [0, 1]
(reflectance, unitless) and shading normal ``(V, H, W, 3)`` in [-1, 1] (world space; 0 where the camera ray leaves
the scene), means over the pixel's samples (:func:`render_features`). Two kinds of feature:

* **first hit** (Mitsuba's ``aov`` integrator): the albedo and normal of the surface the camera ray hits first. On
  a see-through object this is the object's own smooth map, so the denoiser takes the ground texture seen through
  it for noise and wipes it (measured: docs/results/planner.md).
* **see-through** (:func:`see_through_features`): OIDN's documentation advises, for specular transmission, the
  albedo and normal of the next non-specular surface behind it. Our object is partly transmissive (the principled
  ``spec_trans`` map ``t``, weighted by ``1 - metallic``), so the feature is the blend the colour itself makes: at a
  hit on the object the ray continues refracted (index ``eta``; total internal reflection reflects), and the
  feature is ``(1 - t) * first-hit + t * sqrt(base_color) * behind`` (``sqrt(base_color)``: the principled BSDF's
  tint per interface), recursively; the refracted direction is drawn from the transmission lobe (its roughness),
  so the surface behind is as blurred in the feature as in the colour. Opaque hits (``t = 0``, every
  environment surface) end the ray: an opaque object's feature is the first-hit one, and a fully transmissive,
  white, index-1 object's is the object-free scene's (tests/test_denoise.py).

As OIDN's documentation recommends for features that are themselves Monte Carlo estimates, a variant may denoise
each feature first on its own by the ``RT`` filter ("prefiltering") and filter the colour with ``cleanAux`` set, so
that the features' residual noise is not mistaken for detail to keep. ``hdr`` is set: the input is linear
radiance, not sRGB.

The with-object and the object-free render of an evaluation must be denoised identically (same filter, same
quality, same feature kind, features rendered at the same spp and seed): :func:`denoise` is a pure function of its
inputs.

Licences: OIDN is Apache-2.0 (Intel); the ``pyoidn`` binding is MIT.

What it buys is measured, not assumed: ``bench/bench_planner.py --denoisers`` (error against a converged reference
at equal seconds, the denoiser's bias against the noise at the stage's spp, on the whole frame and on the object's
own pixels, with the detail it keeps there); the figures are in ``docs/results/planner.md``.
"""

from __future__ import annotations

import threading
from typing import NamedTuple, Sequence

import numpy as np

#: ``aov`` integrator setting of the feature pass: first-hit albedo and shading normal.
FEATURES_AOV = {"type": "aov", "aovs": "albedo:albedo,normal:sh_normal"}


class Variant(NamedTuple):
    """A denoiser setting: whether it uses the albedo and normal features, prefilters them (``cleanAux``), OIDN's
    quality, and whether the features are the see-through kind (:func:`see_through_features`)."""

    features: bool
    prefilter: bool
    quality: str
    see_through: bool = False
    sharp: bool = False  # see-through: refract about the shading normal (no lobe sampling)


#: The denoiser settings measured (``bench/bench_planner.py --denoisers``): name -> :class:`Variant`.
#: ``oidn``: albedo and normal, prefiltered, ``cleanAux``, high quality (OIDN's recommendation; with clean features
#: its high-quality model is the large one: 0.5 CPU s for 4 views of 96 px, measured); ``oidn-balanced``: the same at
#: balanced quality (0.2 s); ``oidn-raw``: the first-hit features as rendered, without prefiltering (0.07 s);
#: ``oidn-through``: as ``oidn-raw`` with the see-through features; ``oidn-through-sharp``: the same with the
#: transmission's roughness left out (the feature shows what is behind sharply); ``oidn-color``: the colour alone.
VARIANTS = {"oidn": Variant(True, True, "high"), "oidn-balanced": Variant(True, True, "balanced"),
            "oidn-raw": Variant(True, False, "high"), "oidn-through": Variant(True, False, "high", True),
            "oidn-through-sharp": Variant(True, False, "high", True, True),
            "oidn-color": Variant(False, False, "high")}

#: Transmissive hits followed per camera ray by :func:`see_through_features` (a closed object is entered and left:
#: two per crossing); the hit after the last is taken as opaque.
MAX_TRANSMISSIONS = 6

_LOCK = threading.Lock()
_DEVICE = None
_FILTERS: dict = {}  # (inputs, shape, hdr, cleanAux, quality) -> a committed filter, reused


def _device():
    """One committed OIDN CPU device per process (creating one loads the network weights' runtime)."""
    global _DEVICE
    if _DEVICE is None:
        import pyoidn

        dev = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
        dev.commit()
        err = dev.get_error()
        if err:
            raise RuntimeError(f"Open Image Denoise: {err}")
        _DEVICE = dev
    return _DEVICE


def render_features(elements: dict, obj, cams: Sequence, spp: int, seed: int = 0,
                    see_through: bool = False, sharp: bool = False, scene=None,
                    without: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Albedo and shading normal of every view, ``((V, H, W, 3), (V, H, W, 3))`` float32: means over ``spp`` samples
    per pixel (the same box pixel filter as the colour), albedo clipped to [0, 1]. First-hit features (Mitsuba's
    ``aov`` integrator, ``seed``) or, with ``see_through``, :func:`see_through_features` (``sharp``: without the
    transmission lobe's roughness; ``scene``, ``without``: see there, the first-hit pass ignores them)."""
    from optimizer.rendering.render import render_shaded

    if see_through:
        return see_through_features(elements, obj, cams, spp, seed, lobe=not sharp, scene=scene, without=without)
    img = render_shaded(elements, obj, cams, FEATURES_AOV, int(spp), int(seed))
    if img.shape[-1] != 6:
        raise RuntimeError(f"the feature pass gave {img.shape[-1]} channels, expected 6 (albedo, normal)")
    albedo = np.clip(img[..., :3], 0.0, 1.0).astype(np.float32)
    normal = np.clip(img[..., 3:6], -1.0, 1.0).astype(np.float32)
    return albedo, normal


def see_through_features(elements: dict, obj, cams: Sequence, spp: int = 16, seed: int = 0,
                         lobe: bool = True, jitter: bool = True, scene=None,
                         without: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The see-through albedo and normal of every view (module docstring), ``((V, H, W, 3), (V, H, W, 3))``
    float32, from ``round(sqrt(spp))^2`` stratified rays per pixel, jittered within their strata by ``seed`` (as the
    ``aov`` pass samples its pixels; ``jitter=False``: at the strata's centres, the same features for every seed --
    then the denoised object-free render varies less from seed to seed than the object's pixels, whose colour
    noise the features let through: measured 1.6-3.0x noisier than the background, bench/bench_noise.py).

    At each hit the albedo is the BSDF's diffuse reflectance (what the ``aov`` integrator's albedo reads) and the
    normal the shading normal; at a hit on ``obj`` with a principled BSDF, its transmission weight
    ``t = spec_trans * (1 - metallic)`` passes that share of the feature to what the ray hits next, tinted by
    ``sqrt(base_color)`` (the normal untinted), for up to :data:`MAX_TRANSMISSIONS` hits. The ray goes on refracted
    (index ``eta``) about a microfacet normal drawn from the GGX visible normals of the transmission lobe (``alpha =
    roughness^2``, the principled BSDF's; random stream ``seed``), so that what is behind is blurred as the colour
    blurs it; ``lobe=False`` refracts about the shading normal (sharp: the feature then shows texture the colour
    has not got, and the denoiser adds it: measured over-sharpening on rough objects, docs/results/planner.md).
    Total internal reflection reflects. Fresnel reflection off the transmissive surface is left out (the sky or
    sun it mirrors has no albedo). All views are traced in one symbolic loop (one kernel launch, like the ``aov``
    pass). ``scene``: ``elements`` with ``obj`` already built (a build costs 20-50 ms).

    ``without``: the features of the same scene, cameras, spp and seed without ``obj`` (the background's). Then only
    the pixels whose rays can meet ``obj``'s bounding box (the rectangle of its projected corners) are traced and
    every other pixel is taken from ``without``: a ray that misses the box hits what it hits without the object,
    with the same random numbers (each ray keeps its jitter and its stream), so the result is the full pass's
    (``tests/test_denoise.py``)."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.rendering import scene as scn
    from optimizer.rendering.render import camera_rays, stack_rays
    from optimizer.rendering.region import box_pixels

    ss = max(1, int(round(float(spp) ** 0.5)))
    sc = scene if scene is not None else scn.build_scene(elements, obj)
    bsdf_obj = obj.bsdf() if obj is not None else None
    principled = bsdf_obj is not None and all(bsdf_obj.has_attribute(k) for k in ("spec_trans", "metallic",
                                                                                  "base_color"))
    params = mi.traverse(bsdf_obj) if principled else {}
    # opaque: a value baked into the kernel as a literal would compile a new kernel per seed or index (measured 0.2 s)
    eta = dr.opaque(mi.Float, float(params["eta"][0]) if "eta" in params else 1.5)
    gen = np.random.default_rng(int(seed))
    # the pixels traced: all, or (with ``without``) those whose rays can meet the object's box
    sel = [None] * len(cams) if without is None or obj is None else [
        np.arange(c.width * c.height) if p is None else p for c, p in zip(cams, box_pixels(obj, cams))]
    rays = [camera_rays(cam, ss, gen if jitter else None, p) for cam, p in zip(cams, sel)]  # one wavefront
    sizes = [(cam.width * cam.height if p is None else p.size) * ss * ss for cam, p in zip(cams, sel)]
    lanes = None  # the rays traced, as lanes of the full pass (None: all)
    if sel[0] is not None:
        offsets = np.cumsum([0] + [cam.width * cam.height * ss * ss for cam in cams])
        lanes = np.concatenate([off + (p[:, None] * (ss * ss) + np.arange(ss * ss)).ravel()
                                for off, p in zip(offsets, sel)]).astype(np.int64)
    ray = stack_rays(rays)
    obj_ptr = mi.ShapePtr(obj) if principled else None

    def body(ray, active, weight, share, a_acc, n_acc, k, rng):
        si = sc.ray_intersect(ray, active)
        hit = active & si.is_valid()
        albedo = dr.clip(si.bsdf(ray).eval_diffuse_reflectance(si, hit), 0.0, 1.0)
        t, tint, alpha = mi.Float(0.0), mi.Color3f(1.0), mi.Float(0.0)
        if principled:
            on_obj = hit & (si.shape == obj_ptr) & (k < MAX_TRANSMISSIONS)
            t = dr.select(on_obj, dr.clip(bsdf_obj.eval_attribute_1("spec_trans", si, on_obj), 0.0, 1.0)
                          * (1.0 - dr.clip(bsdf_obj.eval_attribute_1("metallic", si, on_obj), 0.0, 1.0)), 0.0)
            tint = dr.sqrt(dr.clip(bsdf_obj.eval_attribute("base_color", si, on_obj), 0.0, 1.0))
            alpha = dr.maximum(dr.square(bsdf_obj.eval_attribute_1("roughness", si, on_obj)), 1e-3)
        a_acc = a_acc + dr.select(hit, weight * (1.0 - t) * albedo, 0.0)
        n_acc = n_acc + dr.select(hit, share * (1.0 - t) * si.sh_frame.n, 0.0)
        # the next direction: refraction about a microfacet normal drawn from the lobe's visible normals (GGX,
        # alpha = roughness^2, as the principled BSDF's), so that what is behind is blurred as in the colour
        side = dr.sign(mi.Frame3f.cos_theta(si.wi))
        u = mi.Point2f(rng.next_float32(), rng.next_float32())
        m, _ = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, True).sample(si.wi * side, u)
        m = m if lobe else mi.Vector3f(0.0, 0.0, 1.0)  # upper hemisphere: dot(wi, m) keeps the side (as in Mitsuba)
        r, cos_t, _, eta_ti = mi.fresnel(dr.dot(si.wi, m), eta)
        wo = dr.select(r >= 1.0, mi.reflect(si.wi, m), mi.refract(si.wi, m, cos_t, eta_ti))
        return (si.spawn_ray(si.to_world(wo)), hit & (t > 0), weight * t * tint, share * t, a_acc, n_acc, k + 1,
                rng)

    n_rays = int(sum(sizes))
    if n_rays == 0:  # no ray meets the object: the object-free features
        return without[0].copy(), without[1].copy()
    init = (0x853C49E6748FEA9B + int(seed)) % (1 << 64)
    if lanes is None:
        rng = mi.PCG32(n_rays, initstate=dr.opaque(mi.UInt64, init))
    else:  # lane i's stream of the full pass: PCG32(n) seeds lane i with (initstate + i, initseq + i)
        rng = mi.PCG32(n_rays)
        li = mi.UInt64(lanes.astype(np.uint64))
        rng.seed(dr.opaque(mi.UInt64, init) + li, dr.opaque(mi.UInt64, 0xDA3E39CB94B95BDB) + li)
    state = (ray, dr.full(mi.Bool, True, n_rays),
             dr.full(mi.Color3f, 1.0, n_rays),  # the tinted share still to be given (albedo)
             dr.full(mi.Float, 1.0, n_rays),  # the untinted share (normal)
             dr.zeros(mi.Color3f, n_rays), dr.zeros(mi.Normal3f, n_rays), dr.zeros(mi.UInt32, n_rays), rng)
    state = dr.while_loop(state, lambda ray, active, *rest: active, body, labels=(
        "ray", "active", "weight", "share", "albedo", "normal", "k", "rng"), label="see_through_features")
    a_acc, n_acc = state[4], state[5]
    out = []
    for acc, fill in zip((a_acc, n_acc), without if lanes is not None else (None, None)):
        flat = np.asarray(acc, dtype=np.float32).reshape(3, -1).T  # Dr.Jit gives (3, N): channel-major
        views, start = [], 0
        for v, (cam, n) in enumerate(zip(cams, sizes)):
            means = flat[start:start + n].reshape(-1, ss * ss, 3).mean(1)
            if sel[v] is None:
                views.append(means.reshape(cam.height, cam.width, 3))
            else:  # the pixels not traced: the object-free pass's
                img = np.array(fill[v], np.float32).reshape(-1, 3)
                img[sel[v]] = means
                views.append(img.reshape(cam.height, cam.width, 3))
            start += n
        out.append(np.stack(views))
    return np.clip(out[0], 0.0, 1.0).astype(np.float32), np.clip(out[1], -1.0, 1.0).astype(np.float32)


def _run(images: dict[str, np.ndarray], hdr: bool, clean_aux: bool, quality: str) -> np.ndarray:
    """One OIDN ``RT`` filter pass over one ``(H, W, 3)`` image set (``color`` with optional ``albedo`` /
    ``normal``, or a single feature: its prefilter). Filters are kept per configuration and size: a new filter's
    first commit builds its network (measured: ~0.1 s per filter, 7x the pass itself at 96 px)."""
    import pyoidn

    qualities = {"high": pyoidn.OIDN_QUALITY_HIGH, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
                 "fast": pyoidn.OIDN_QUALITY_FAST}
    if quality not in qualities:
        raise ValueError(f"unknown denoiser quality {quality!r}; choose one of {sorted(qualities)}")
    names = {"color": pyoidn.OIDN_IMAGE_COLOR, "albedo": pyoidn.OIDN_IMAGE_ALBEDO,
             "normal": pyoidn.OIDN_IMAGE_NORMAL}
    first = next(iter(images.values()))
    out = np.zeros_like(first)
    key = (tuple(images), first.shape, bool(hdr), bool(clean_aux), quality)
    with _LOCK:
        dev = _device()
        filt = _FILTERS.get(key)
        if filt is None:
            filt = _FILTERS[key] = pyoidn.Filter(dev, pyoidn.OIDN_FILTER_TYPE_RT)
            if "color" in images:
                filt.set_bool("hdr", bool(hdr))
                filt.set_bool("cleanAux", bool(clean_aux))
            filt.set_quality(qualities[quality])
        for k, v in images.items():
            filt.set_image(names[k], v, pyoidn.OIDN_FORMAT_FLOAT3)
        filt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, out, pyoidn.OIDN_FORMAT_FLOAT3)
        filt.commit()
        filt.execute()
        err = dev.get_error()
        if err:
            raise RuntimeError(f"Open Image Denoise: {err}")
    return out


def denoise(color: np.ndarray, albedo: np.ndarray | None = None, normal: np.ndarray | None = None,
            prefilter: bool = True, quality: str = "high") -> np.ndarray:
    """Denoised linear radiance, the shape of ``color`` (``(H, W, 3)`` or ``(V, H, W, 3)``, non-negative).

    ``albedo`` / ``normal``: the features of the same pixels (:func:`render_features`); ``normal`` needs ``albedo``
    (OIDN's rule). ``prefilter``: denoise each feature first and filter the colour with ``cleanAux`` (OIDN's
    recommendation for noisy features); off, the features are taken as they are (``cleanAux`` off).

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> flat = np.full((32, 32, 3), 0.5, np.float32)
    >>> noisy = (flat * rng.exponential(1.0, flat.shape)).astype(np.float32)
    >>> bool(np.abs(denoise(noisy) - flat).mean() < np.abs(noisy - flat).mean() / 4)
    True
    """
    c = np.asarray(color, dtype=np.float32)
    if c.ndim not in (3, 4) or c.shape[-1] != 3:
        raise ValueError(f"color must be (H, W, 3) or (V, H, W, 3) linear RGB, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("color has non-finite values; sanitise the render before denoising")
    if normal is not None and albedo is None:
        raise ValueError("a normal feature needs the albedo feature too (Open Image Denoise's rule)")
    feats = {k: np.asarray(v, dtype=np.float32) for k, v in (("albedo", albedo), ("normal", normal)) if v is not None}
    for k, v in feats.items():
        if v.shape != c.shape:
            raise ValueError(f"{k} has shape {v.shape}, the colour {c.shape}")
    if c.ndim == 4:
        return np.stack([denoise(c[i], *(feats[k][i] if k in feats else None for k in ("albedo", "normal")),
                                 prefilter=prefilter, quality=quality) for i in range(c.shape[0])])
    c = np.ascontiguousarray(np.clip(c, 0.0, None))
    if prefilter:
        feats = {k: _run({k: np.ascontiguousarray(v)}, False, False, quality) for k, v in feats.items()}
    images = {"color": c, **{k: np.ascontiguousarray(v) for k, v in feats.items()}}
    return _run(images, hdr=True, clean_aux=bool(prefilter and feats), quality=quality)


def denoise_variant(color: np.ndarray, albedo: np.ndarray | None, normal: np.ndarray | None,
                    variant: str = "oidn") -> np.ndarray:
    """:func:`denoise` with the settings of ``variant`` (:data:`VARIANTS`)."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown denoiser {variant!r}; choose one of {', '.join(VARIANTS)}")
    feats, prefilter, quality = VARIANTS[variant][:3]
    if feats and (albedo is None or normal is None):
        raise ValueError(f"denoiser {variant!r} needs the albedo and normal features (render_features)")
    return denoise(color, albedo if feats else None, normal if feats else None, prefilter=prefilter, quality=quality)


def variant_features(variant: str, elements: dict, obj, cams: Sequence, spp: int, seed: int = 0, scene=None,
                     without: tuple[np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The features ``variant`` denoises with (:func:`render_features` of its kind; ``scene``, ``without``: see
    :func:`see_through_features`), or ``(None, None)`` for a colour-only variant."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown denoiser {variant!r}; choose one of {', '.join(VARIANTS)}")
    v = VARIANTS[variant]
    if not v.features:
        return None, None
    return render_features(elements, obj, cams, spp, seed, see_through=v.see_through, sharp=v.sharp, scene=scene,
                           without=without)
