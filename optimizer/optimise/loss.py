"""Stage-1 photometric losses: the luminance-gated chromaticity loss (Eq. 9) and plain MSE.

The paper ("Hiding in plain sight", Sec. III-C, Eq. 9) defines, for an object
rendering ``I_obj`` and a background rendering ``I_bg``::

    L = alpha * E[|Y(I_obj) - Y(I_bg)|] + E[g(dY) * |I~_obj - I~_bg|]
    dY = |Y(I_obj) - Y(I_bg)|,   Y = 0.2126 R + 0.7152 G + 0.0722 B  (Rec. 709)
    x~ = x / (Y(x) + eps),       g(x) = 1 / (1 + e^x)

The Dr.Jit functions (:func:`gated_loss`, :func:`mse_loss`, :func:`luminance`)
take ``mi.TensorXf`` images ``(H, W, 3)`` of **linear radiance** and return a
width-1 ``mi.Float``, so ``dr.backward(loss)`` reaches the scene parameters
through a Mitsuba render. :func:`gated_loss_np` / :func:`mse_loss_np` are
float64 NumPy references with exactly the same conventions (tests and
evaluation code use them). Eq. 10 (the mean over views) is the caller's job.

Choices the paper leaves open, and what this module does
-------------------------------------------------------
* **alpha = 1** (default). The paper gives no value. With radiance of order 1
  (a lit diffuse surface), |dY| and the per-channel chromaticity differences
  are both O(0.1..1), so 1 weighs brightness and tint alike.
* **eps = 1e-2, in radiance units** (absolute, not relative). For pixels with
  Y >> 1e-2 (anything visibly lit in a scene exposed to O(1) radiance)
  ``x~`` is the true chromaticity x/Y, independent of brightness. For pixels
  darker than that, where hue is mostly Monte Carlo noise, ``x~ -> x/eps -> 0``
  smoothly, so deep-shadow pixels neither impose a tint nor blow up: the
  chromaticity and its derivative stay bounded (|d x~ / d x| = O(1/eps)).
  Both eps and the gate act on absolute radiance (g(dY) is 0.5 at dY = 0, 0.27
  at dY = 1, < 1e-6 past dY ~ 14), so the loss is not exposure-invariant:
  render scenes at an exposure where lit surfaces are O(0.1..10), or scale
  both images by one constant before calling, rather than changing eps.
* **Gate.** g(0) = 0.5 exactly as written (the gate is not renormalised to 1
  at equal luminance). It is evaluated as ``t / (1 + t)`` with ``t = e^-|x|``
  (``1 / (1 + t)`` for negative x), which never overflows and goes to exactly
  0, with a zero derivative, for huge dY. By default gradients flow through
  the gate, as Eq. 9 is written; note this lets the optimiser lower the
  chromaticity term by *increasing* |dY| where ``g(1-g) * chroma > alpha``.
  ``detach_gate=True`` treats g(dY) as a constant weight in the backward
  pass (same value).
* **Channel averaging.** ``|I~_obj - I~_bg|`` is the L1 distance over the 3
  channels divided by 3: the second expectation is over pixels *and*
  channels. The luminance term is one value per pixel. MSE is likewise the
  mean over pixels and channels.
* **Domain.** ``weight`` is an optional non-negative ``(H, W)`` or
  ``(H, W, 1)`` pixel weight; every expectation is the weighted mean
  ``sum(w x) / sum(w)``. The caller passes the object mask dilated to include
  its shadow; no weight means the whole frame (w = 1). A weight that is
  negative, non-finite or of the wrong shape raises :class:`CamoError`.
* **Y is clamped at >= 0** before any use (|dY|, the gate and the
  chromaticity denominators): MC estimators and denoisers can produce slightly
  negative values, and Y + eps must stay >= eps. Channels themselves are used
  as given.
* **Non-finite pixels.** A pixel with a NaN or +-Inf in any channel of the
  object *or* the background image is excluded from the expectation (weight 0)
  and its values are replaced by 0 before any arithmetic, so neither the loss
  nor its gradient can become NaN; the gradient at such a pixel is 0. The
  count is returned by :func:`gated_loss_terms` (``nonfinite``, for
  ``log.jsonl``). If no pixel is left (empty mask, object off-screen in this
  view, or every pixel non-finite) the loss is 0 with a zero gradient.
* **Background is a constant target**: it is detached (no gradient).
* **Behaviour to know (measured in tests/test_loss.py, Fig. 7 in miniature).**
  When the luminance gap cannot be closed, the gate removes the chromaticity
  gradient completely, but the luminance term still pushes the albedo along
  ``-alpha * (0.2126, 0.7152, 0.0722)``: towards black, and, under plain
  gradient descent, away from green; under Adam (equal steps per channel)
  the hue angle is kept. Near Y ~ 0 the chromaticity gradient is
  O(radiance scale / eps), so strongly lit, nearly black pixels give large
  steps; with bright lighting (radiance ~1e3) the gate is open only within
  a few radiance units of the match.
* **Precision.** The Dr.Jit path computes in the variant's float32; the NumPy
  reference in float64. Finite inputs should stay below ~1e18 so squares fit
  float32 (renders are far below that).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np

from camo_base.errors import CamoError

REC709 = (0.2126, 0.7152, 0.0722)
DEFAULT_ALPHA = 1.0
DEFAULT_EPS = 1e-2
LOSS_NAMES = ("gated", "mse")

__all__ = [
    "REC709",
    "DEFAULT_ALPHA",
    "DEFAULT_EPS",
    "LOSS_NAMES",
    "LossTerms",
    "LossFn",
    "luminance",
    "gate",
    "gated_loss",
    "gated_loss_terms",
    "mse_loss",
    "make_loss",
    "luminance_np",
    "gate_np",
    "gated_loss_np",
    "gated_loss_terms_np",
    "mse_loss_np",
    "white_point",
    "soft_clamp",
    "soft_clamp_np",
]


# ---------------------------------------------------------------------------------------------
# Dr.Jit helpers (mitsuba is imported lazily: the CLI loads this module for every command)


def _mi():
    from optimizer import backend

    backend.init()
    import drjit as dr
    import mitsuba as mi

    return mi, dr


def _check_params(alpha: float, eps: float) -> tuple[float, float]:
    try:
        alpha, eps = float(alpha), float(eps)
    except (TypeError, ValueError):
        raise CamoError(f"loss alpha and eps must be numbers, got alpha={alpha!r}, eps={eps!r}") from None
    if not math.isfinite(alpha) or alpha < 0:
        raise CamoError(f"loss alpha must be a finite number >= 0, got {alpha}")
    if not math.isfinite(eps) or eps <= 0:
        raise CamoError(f"loss eps must be a finite number > 0, got {eps}")
    return alpha, eps


def _as_image(x: Any, name: str, detach: bool):
    """``x`` as an ``mi.TensorXf`` of shape (H, W, 3) (NumPy input is converted, as float32)."""
    mi, dr = _mi()
    if not dr.is_tensor_v(x):
        arr = np.asarray(x)
        if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise CamoError(f"{name} must be a float image (H, W, 3), got dtype {arr.dtype}")
        x = mi.TensorXf(np.ascontiguousarray(arr, dtype=np.float32))
    shape = tuple(x.shape)
    if len(shape) != 3 or shape[2] != 3 or shape[0] < 1 or shape[1] < 1:
        raise CamoError(f"{name} must have shape (H, W, 3), got {shape}")
    return dr.detach(x) if detach else x


def _weight_np(weight: Any, h: int, w: int) -> np.ndarray | None:
    """Validated float64 ``(H*W,)`` pixel weight, or None for the whole frame."""
    if weight is None:
        return None
    try:
        import drjit as dr

        if dr.is_tensor_v(weight) or dr.is_array_v(weight):
            weight = dr.detach(weight).numpy()
    except ImportError:  # pragma: no cover - drjit is a hard dependency
        pass
    arr = np.asarray(weight)
    if arr.dtype == object:
        raise CamoError("weight must be a numeric (H, W) array")
    arr = arr.astype(np.float64)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.shape != (h, w):
        raise CamoError(f"weight must have shape ({h}, {w}) or ({h}, {w}, 1), got {tuple(np.shape(weight))}")
    if not np.all(np.isfinite(arr)):
        raise CamoError("weight has NaN or infinite entries")
    if np.any(arr < 0):
        raise CamoError("weight must be non-negative")
    return arr.reshape(-1)


def _channels(img, n: int):
    mi, dr = _mi()
    base = dr.arange(mi.UInt32, n) * 3
    return [dr.gather(mi.Float, img.array, base + c) for c in range(3)]


def _prepare(obj, bg, weight, count_nonfinite: bool = False):
    """Shared set-up: sanitised channels, effective weight, 1/sum(w) and the non-finite count."""
    mi, dr = _mi()
    obj = _as_image(obj, "obj", detach=False)
    bg = _as_image(bg, "bg", detach=True)
    if tuple(obj.shape) != tuple(bg.shape):
        raise CamoError(f"obj and bg shapes differ: {tuple(obj.shape)} vs {tuple(bg.shape)}")
    h, w = int(obj.shape[0]), int(obj.shape[1])
    n = h * w
    o = _channels(obj, n)
    b = _channels(bg, n)
    valid = dr.isfinite(o[0])
    for ch in o[1:] + b:
        valid &= dr.isfinite(ch)
    # select() forwards the gradient only where `valid`: NaN/Inf pixels get exactly 0.
    o = [dr.select(valid, ch, 0.0) for ch in o]
    b = [dr.select(valid, ch, 0.0) for ch in b]
    wnp = _weight_np(weight, h, w)
    wt = mi.Float(1.0) if wnp is None else mi.Float(wnp.astype(np.float32))
    w_eff = dr.select(valid, wt, 0.0)
    wsum = dr.sum(w_eff)
    inv = dr.select(wsum > 0, dr.rcp(dr.maximum(wsum, 1e-30)), 0.0)
    nonfinite = dr.sum(dr.select(valid, 0.0, 1.0)) if count_nonfinite else None
    return o, b, w_eff, inv, nonfinite


def _lum(c):
    _, dr = _mi()
    return dr.maximum(REC709[0] * c[0] + REC709[1] * c[1] + REC709[2] * c[2], 0.0)


def luminance(img):
    """Rec. 709 luminance ``(H, W)`` of an ``(H, W, 3)`` linear image (``mi.TensorXf``, differentiable).

    This is the raw weighted sum (it may be negative for negative input); the
    loss clamps it at 0 before use.
    """
    mi, dr = _mi()
    img = _as_image(img, "img", detach=False)
    h, w = int(img.shape[0]), int(img.shape[1])
    c = _channels(img, h * w)
    y = REC709[0] * c[0] + REC709[1] * c[1] + REC709[2] * c[2]
    return mi.TensorXf(y, shape=(h, w))


def gate(x):
    """g(x) = 1 / (1 + e^x), overflow-free: ``t / (1 + t)`` with ``t = e^-|x|`` for x >= 0.

    Works on Dr.Jit arrays/tensors; g(0) == 0.5 exactly, g(x) -> 0 (derivative 0) for huge x.
    """
    _, dr = _mi()
    pos = x >= 0
    t = dr.exp(dr.select(pos, -x, x))  # e^-|x| in (0, 1], with the derivative of -x at x = 0
    return dr.select(pos, t / (1.0 + t), 1.0 / (1.0 + t))


@dataclasses.dataclass
class LossTerms:
    """The parts of Eq. 9 (width-1 ``mi.Float`` each; ``float(t.total[0])`` to read one).

    ``total = luminance + chroma``; ``luminance`` already includes alpha;
    ``chroma_ungated`` is E[|obj~ - bg~|] without g (diagnostics);
    ``nonfinite`` is the number of excluded non-finite pixels.
    """

    total: Any
    luminance: Any
    chroma: Any
    chroma_ungated: Any
    nonfinite: Any

    def as_floats(self) -> dict[str, float]:
        return {k: float(getattr(self, k)[0]) for k in ("total", "luminance", "chroma", "chroma_ungated", "nonfinite")}


def gated_loss_terms(
    obj, bg, weight=None, alpha: float = DEFAULT_ALPHA, eps: float = DEFAULT_EPS, detach_gate: bool = False
) -> LossTerms:
    """Eq. 9 split into its terms; see :func:`gated_loss` and the module docstring."""
    return _gated(obj, bg, weight, alpha, eps, detach_gate, extras=True)


def _gated(obj, bg, weight, alpha, eps, detach_gate, extras):
    alpha, eps = _check_params(alpha, eps)
    mi, dr = _mi()
    o, b, w_eff, inv, nonfinite = _prepare(obj, bg, weight, count_nonfinite=extras)
    yo, yb = _lum(o), _lum(b)
    dy = dr.abs(yo - yb)
    g = gate(dy)
    if detach_gate:
        g = dr.detach(g)
    ro, rb = 1.0 / (yo + eps), 1.0 / (yb + eps)
    chroma = (dr.abs(o[0] * ro - b[0] * rb) + dr.abs(o[1] * ro - b[1] * rb) + dr.abs(o[2] * ro - b[2] * rb)) * (
        1.0 / 3.0
    )
    lum_term = alpha * dr.sum(w_eff * dy) * inv
    chroma_term = dr.sum(w_eff * g * chroma) * inv
    ungated = dr.sum(w_eff * chroma) * inv if extras else None
    return LossTerms(lum_term + chroma_term, lum_term, chroma_term, ungated, nonfinite)


def gated_loss(obj, bg, weight=None, alpha: float = DEFAULT_ALPHA, eps: float = DEFAULT_EPS, detach_gate: bool = False):
    """Luminance-gated chromaticity loss, Eq. 9 (width-1 ``mi.Float``, differentiable w.r.t. ``obj``).

    ``obj``/``bg``: ``(H, W, 3)`` linear radiance (``mi.TensorXf``; NumPy is
    accepted and converted); ``bg`` is detached. ``weight``: optional
    non-negative ``(H, W)``/``(H, W, 1)`` pixel weight (weighted mean), None =
    whole frame. Non-finite pixels are excluded and zeroed; see the module docstring.
    """
    return _gated(obj, bg, weight, alpha, eps, detach_gate, extras=False).total


def mse_loss(obj, bg, weight=None):
    """Mean squared error over pixels and channels (the paper's Fig. 7 baseline), same domain rules."""
    _, dr = _mi()
    o, b, w_eff, inv, _ = _prepare(obj, bg, weight)
    sq = ((o[0] - b[0]) ** 2 + (o[1] - b[1]) ** 2 + (o[2] - b[2]) ** 2) * (1.0 / 3.0)
    return dr.sum(w_eff * sq) * inv


@dataclasses.dataclass(frozen=True)
class LossFn:
    """A named loss: ``fn(obj, bg, weight=None)`` (Dr.Jit) and ``fn.numpy(obj, bg, weight=None)`` (reference)."""

    name: str
    alpha: float = DEFAULT_ALPHA
    eps: float = DEFAULT_EPS

    def __call__(self, obj, bg, weight=None):
        if self.name == "gated":
            return gated_loss(obj, bg, weight, self.alpha, self.eps)
        return mse_loss(obj, bg, weight)

    def numpy(self, obj, bg, weight=None) -> float:
        if self.name == "gated":
            return gated_loss_np(obj, bg, weight, self.alpha, self.eps)
        return mse_loss_np(obj, bg, weight)


def make_loss(name: str, alpha: float = DEFAULT_ALPHA, eps: float = DEFAULT_EPS) -> Callable:
    """The loss called ``name`` (``"gated"`` or ``"mse"``); anything else raises :class:`CamoError`.

    ``alpha`` and ``eps`` are validated (alpha >= 0, eps > 0, finite) and ignored by ``"mse"``.
    """
    key = str(name).strip().lower() if isinstance(name, str) else None
    if key not in LOSS_NAMES:
        raise CamoError(f"unknown loss {name!r}; choose one of: {', '.join(LOSS_NAMES)}")
    alpha, eps = _check_params(alpha, eps)
    return LossFn(key, alpha, eps)


# ---------------------------------------------------------------------------------------------
# NumPy float64 references (same conventions)


def luminance_np(img: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance ``(...,)`` of ``(..., 3)`` linear RGB, float64 (not clamped)."""
    return np.asarray(img, dtype=np.float64) @ np.asarray(REC709, dtype=np.float64)


def gate_np(x):
    """g(x) = 1 / (1 + e^x) in float64, overflow-free."""
    x = np.asarray(x, dtype=np.float64)
    t = np.exp(-np.abs(x))
    return np.where(x >= 0, t / (1.0 + t), 1.0 / (1.0 + t))


def _prepare_np(obj, bg, weight):
    obj = np.asarray(obj, dtype=np.float64)
    bg = np.asarray(bg, dtype=np.float64)
    if obj.ndim != 3 or obj.shape[2] != 3 or obj.shape[0] < 1 or obj.shape[1] < 1:
        raise CamoError(f"obj must have shape (H, W, 3), got {obj.shape}")
    if obj.shape != bg.shape:
        raise CamoError(f"obj and bg shapes differ: {obj.shape} vs {bg.shape}")
    h, w = obj.shape[:2]
    o = obj.reshape(-1, 3)
    b = bg.reshape(-1, 3)
    valid = np.all(np.isfinite(o), axis=1) & np.all(np.isfinite(b), axis=1)
    o = np.where(valid[:, None], o, 0.0)
    b = np.where(valid[:, None], b, 0.0)
    wnp = _weight_np(weight, h, w)
    wt = np.ones(h * w) if wnp is None else wnp
    w_eff = np.where(valid, wt, 0.0)
    return o, b, w_eff, int(np.count_nonzero(~valid))


def _wmean(w: np.ndarray, x: np.ndarray) -> float:
    s = float(w.sum())
    return float((w * x).sum() / s) if s > 0 else 0.0


def gated_loss_terms_np(
    obj, bg, weight=None, alpha: float = DEFAULT_ALPHA, eps: float = DEFAULT_EPS
) -> dict[str, float]:
    """Float64 reference of :func:`gated_loss_terms` (dict of floats, same keys)."""
    alpha, eps = _check_params(alpha, eps)
    o, b, w_eff, nonfinite = _prepare_np(obj, bg, weight)
    yo = np.maximum(luminance_np(o), 0.0)
    yb = np.maximum(luminance_np(b), 0.0)
    dy = np.abs(yo - yb)
    chroma = np.abs(o / (yo + eps)[:, None] - b / (yb + eps)[:, None]).mean(axis=1)
    lum = alpha * _wmean(w_eff, dy)
    chr_ = _wmean(w_eff, gate_np(dy) * chroma)
    return {
        "total": lum + chr_,
        "luminance": lum,
        "chroma": chr_,
        "chroma_ungated": _wmean(w_eff, chroma),
        "nonfinite": float(nonfinite),
    }


def gated_loss_np(obj, bg, weight=None, alpha: float = DEFAULT_ALPHA, eps: float = DEFAULT_EPS) -> float:
    """Float64 NumPy reference of :func:`gated_loss` (Eq. 9) for ``(H, W, 3)`` arrays."""
    return gated_loss_terms_np(obj, bg, weight, alpha, eps)["total"]


def mse_loss_np(obj, bg, weight=None) -> float:
    """Float64 NumPy reference of :func:`mse_loss`."""
    o, b, w_eff, _ = _prepare_np(obj, bg, weight)
    return _wmean(w_eff, ((o - b) ** 2).mean(axis=1))


# ---------------------------------------------------------------------------------------------
# Glint-robust loss domain (beyond the paper; the ``fast`` preset's ``stage1.loss_clamp``, issue 32)

#: The background quantile the white point of :func:`white_point` is a multiple of.
WHITE_QUANTILE = 0.99


def white_point(background: np.ndarray, domain: np.ndarray | None, factor: float) -> float:
    """The white point of :func:`soft_clamp`: ``factor`` times the :data:`WHITE_QUANTILE` quantile of the linear
    background targets' channel values ``(V, H, W, 3)`` inside the loss ``domain`` ``(V, H, W)`` (the whole frames
    when None or empty), floored at 1e-3. Relative to the scene's own brightness, so the clamp means the same at any
    exposure.

    >>> white_point(np.full((1, 2, 2, 3), 0.5), None, 4.0)
    2.0
    """
    bg = np.asarray(background, np.float64)
    if not (math.isfinite(factor) and factor > 0):
        raise CamoError(f"white point factor must be a finite number > 0, got {factor}")
    vals = bg[np.asarray(domain) > 0] if domain is not None and np.any(np.asarray(domain) > 0) else bg.reshape(-1, 3)
    vals = vals[np.isfinite(vals)]
    q = float(np.quantile(vals, WHITE_QUANTILE)) if vals.size else 0.0
    return max(factor * q, 1e-3)


def soft_clamp(img, white: float):
    """``white * tanh(img / white)`` per channel (Dr.Jit, differentiable): the linear image below ``white`` (at
    ``x = white / 4`` the value is 2 % low and the slope 6 % below 1), saturating at ``white`` with a slope that
    falls as ``4 exp(-2 x / white)``, exactly 0 in float32 past ~9 white points.

    Why: with a near-mirror under the sun one 4-spp pixel that samples the sun carries ~1e3-1e5 times a lit pixel's
    radiance; its squared error is then the whole loss (meadow from a mirror start: 0.01 -> 87 at one iteration) and
    its gradient the whole step. Compared through this curve, no pixel adds more than ``white^2`` per channel, and a
    saturated glint adds no gradient. The bias this adds: the loss compares ``E[f(x)]`` (f concave above 0), not
    ``f(E[x])``: a pixel whose mean is below ``white`` but whose 4-spp estimates reach it (rare bright paths, glints)
    counts as darker than it is, by ``E[x - f(x)]`` (about ``E[x^3] / (3 white^2)`` for ``x`` well below ``white``),
    so the optimiser under-penalises sparse glints and sees bright pixels' errors shrunk by the slope ``1 -
    tanh^2``; the evaluation's sRGB metrics clip at display white 1, so radiance far above ``white`` is invisible to
    them as well."""
    import drjit as dr

    return white * dr.tanh(img / white)


def soft_clamp_np(img: np.ndarray, white: float) -> np.ndarray:
    """Float64 reference of :func:`soft_clamp`.

    >>> soft_clamp_np(np.array([0.0, 1.0, 1e6]), 4.0).round(4).tolist()
    [0.0, 0.9797, 4.0]
    """
    return white * np.tanh(np.asarray(img, np.float64) / white)
