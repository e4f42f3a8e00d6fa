"""Denoising a path-traced render with Intel Open Image Denoise (OIDN, PyPI ``pyoidn``), with its auxiliary features.

Radiance is linear float32 ``(V, H, W, 3)`` (HDR, non-negative); features are first-hit albedo ``(V, H, W, 3)`` in
[0, 1] and shading normal ``(V, H, W, 3)`` in [-1, 1] (world space; 0 where the camera ray leaves the scene), from
Mitsuba's ``aov`` integrator (:func:`render_features`). As OIDN's documentation recommends for features that are
themselves Monte Carlo estimates (anti-aliased edges: the features are averages over the pixel's samples), each
feature image is first denoised on its own by the ``RT`` filter ("prefiltering") and the colour is then filtered
with ``cleanAux`` set, so that the features' residual noise is not mistaken for detail to keep. ``hdr`` is set: the
input is linear radiance, not sRGB.

The with-object and the object-free render of an evaluation must be denoised identically (same filter, same
quality, features rendered at the same spp and seed): :func:`denoise` is a pure function of its inputs.

Licences: OIDN is Apache-2.0 (Intel); the ``pyoidn`` binding is MIT.

What it buys is measured, not assumed: ``bench/bench_planner.py --denoise`` (error against a converged reference
at equal seconds, the denoiser's bias against the noise at the stage's spp, the noise around the object against the
background's); the figures are in ``docs/results/planner.md``.
"""

from __future__ import annotations

import threading
from typing import Sequence

import numpy as np

#: ``aov`` integrator setting of the feature pass: first-hit albedo and shading normal.
FEATURES_AOV = {"type": "aov", "aovs": "albedo:albedo,normal:sh_normal"}

#: The denoiser settings measured (``bench/bench_planner.py --denoisers``): name -> (features, prefilter, quality).
#: ``oidn``: albedo and normal, prefiltered, ``cleanAux``, high quality (OIDN's recommendation; with clean features
#: its high-quality model is the large one: 0.5 CPU s for 4 views of 96 px, measured); ``oidn-balanced``: the same at
#: balanced quality (0.2 s); ``oidn-raw``: the features as rendered, without prefiltering (0.07 s); ``oidn-color``:
#: the colour alone.
VARIANTS = {"oidn": (True, True, "high"), "oidn-balanced": (True, True, "balanced"),
            "oidn-raw": (True, False, "high"), "oidn-color": (False, False, "high")}

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


def render_features(elements: dict, obj, cams: Sequence, spp: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """First-hit albedo and shading normal of every view, ``((V, H, W, 3), (V, H, W, 3))`` float32: means over
    ``spp`` samples per pixel (the same pixel filter as the colour), albedo clipped to [0, 1]."""
    from optimizer.rendering.render import render_shaded

    img = render_shaded(elements, obj, cams, FEATURES_AOV, int(spp), int(seed))
    if img.shape[-1] != 6:
        raise RuntimeError(f"the feature pass gave {img.shape[-1]} channels, expected 6 (albedo, normal)")
    albedo = np.clip(img[..., :3], 0.0, 1.0).astype(np.float32)
    normal = np.clip(img[..., 3:6], -1.0, 1.0).astype(np.float32)
    return albedo, normal


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
    feats, prefilter, quality = VARIANTS[variant]
    if feats and (albedo is None or normal is None):
        raise ValueError(f"denoiser {variant!r} needs the albedo and normal features (render_features)")
    return denoise(color, albedo if feats else None, normal if feats else None, prefilter=prefilter, quality=quality)
