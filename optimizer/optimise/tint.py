"""A mean-colour term next to Stage 1's squared error (``--tint-match W``, issue 29): the body's mean colour in each
view weighted ``1 + W`` times against the rest of the error.

Why. The glassy tint (:mod:`evaluation.metrics.tint`: CIELAB ΔE between the mean colours inside the object's mask
with and without the object) is a low-frequency colour error. The squared error does contain it: on the object's
pixels the mean over pixels of ``(I - B)^2`` is the squared error of the mean colours plus the variance of the
per-pixel error about it. But at 4 spp the per-pixel part is mostly Monte Carlo noise and texture the multi-view body
cannot hold (``detail.py``), and Adam normalises each texel's step by its gradient's running magnitude, noise
included: a coherent colour error shared by every texel of the body moves them as slowly as any other error. This
term repeats the mean-colour part with weight ``W``, so its share of each texel's gradient, coherent across the body
and across steps, grows ``1 + W`` times.

The term. For view ``v`` with ``I`` the render as the loss compares it (linear radiance, soft-clamped when
``--loss-clamp``), ``B`` the background target in the same space and ``c`` the object's coverage inside the loss
domain (``(h, w)`` in [0, 1], the training window)::

    m_v  = sum_p c_p I_p / sum_p c_p            the body's mean colour (RGB)
    m*_v = sum_p c_p B_p / sum_p c_p            the ground's in the same pixels
    T    = W * mean_v  s_v |m_v - m*_v|^2 / 3

``s_v = sum_p c_p / |domain_v|`` is the mask's share of the loss domain's pixels, so ``T`` at ``W = 1`` is exactly the
mean-colour part of the squared error (the mean over the domain's pixels and the 3 channels) on a mask of uniform
coverage: ``W`` reads as the extra weight of the mask's mean colour. In the loss's own space (not CIELAB) so that the
term and the squared error agree at the match and do not pull against each other. Its gradient is
``dT / dI_p = 2 W s_v c_p (m_v - m*_v) / (3 V sum c)``; the render is read back once a step and the gradient enters
the backward pass through the surrogate ``sum(I * G)`` (one multiply-add per pixel), as the detail term does.

Local form (``--tint-scale S`` > 0). One mean per view pushes every texel of the body the same way, also where one
part is too bright and another too dark. With ``S`` > 0 the term compares the colour error low-passed by a Gaussian of
``S`` pixels instead, each pixel its own neighbourhood's cast::

    b_v  = G_S * (I - B)                         zero outside the window (``scipy.ndimage.gaussian_filter``,
                                                 mode "constant": a symmetric operator, so its transpose is itself)
    T    = W * mean_v  sum_p c_p |b_p|^2 / (3 |domain_v|)

with the gradient ``dT / dI = 2 W G_S * (c b) / (3 V |domain_v|)``. As ``S`` grows past the mask this tends to the
mean form; at ``S`` = 0 the mean form is used.

Noise. ``m_v`` of a 4-spp render averages the noise of every covered pixel (tens to hundreds), so its square's bias
(the variance of the mean) is small and does not depend on where the mean is: no correction is made.
"""

from __future__ import annotations

import numpy as np


def mask_weights(coverage: np.ndarray, domain: np.ndarray | None = None) -> np.ndarray:
    """The term's pixel weights ``(h, w)`` float64: the coverage in [0, 1] inside the loss domain (``domain > 0``; None:
    every pixel), not normalised."""
    c = np.clip(np.asarray(coverage, np.float64), 0.0, 1.0)
    return c if domain is None else c * (np.asarray(domain) > 0)


def mean_colour(img: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``sum c I / sum c`` ``(3,)`` float64 of ``img`` ``(h, w, 3)`` under ``weights`` ``(h, w)`` (NaN when their sum is
    0).

    >>> img = np.zeros((2, 2, 3)); img[0, 0] = (1.0, 0.5, 0.0)
    >>> mean_colour(img, np.array([[1.0, 1.0], [0.0, 0.0]])).tolist()
    [0.5, 0.25, 0.0]
    """
    w = np.asarray(weights, np.float64)
    total = w.sum()
    if total <= 0:
        return np.full(3, np.nan)
    return np.tensordot(w, np.asarray(img, np.float64), axes=([0, 1], [0, 1])) / total


def term_np(img: np.ndarray, target: np.ndarray, weights: np.ndarray, share: float, weight: float) -> float:
    """The term of one view (module doc), float64: ``W s |m - m*|^2 / 3``.

    >>> bg = np.full((4, 4, 3), 0.2); img = bg.copy(); img[1:3, 1:3] += (0.3, 0.0, 0.0)   # a red cast on the mask
    >>> c = np.zeros((4, 4)); c[1:3, 1:3] = 1.0
    >>> round(term_np(img, bg, c, share=0.25, weight=2.0), 6)   # 2 x 0.25 x 0.09 / 3
    0.015
    """
    m, m_star = mean_colour(img, weights), mean_colour(target, weights)
    if not np.all(np.isfinite(m - m_star)):
        return 0.0
    return float(weight) * float(share) * float(np.sum((m - m_star) ** 2)) / 3.0


def grad_np(img: np.ndarray, target: np.ndarray, weights: np.ndarray, share: float, weight: float) -> np.ndarray:
    """``dT / dI`` ``(h, w, 3)`` float64 of :func:`term_np` (module doc; zero without a mask)."""
    w = np.asarray(weights, np.float64)
    total = w.sum()
    if total <= 0:
        return np.zeros(np.shape(img), np.float64)
    d = mean_colour(img, w) - mean_colour(target, w)
    return (2.0 * float(weight) * float(share) / (3.0 * total)) * w[..., None] * d[None, None, :]


def _blur(x: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(np.asarray(x, np.float64), sigma=(sigma, sigma, 0.0), mode="constant", truncate=3.0)


def lowpass_term_np(img: np.ndarray, target: np.ndarray, weights: np.ndarray, share: float, weight: float,
                    sigma: float) -> float:
    """The local form's term of one view (module doc, ``S`` = ``sigma`` px > 0): ``W sum c |G_S (I - B)|^2 / (3
    |domain|)`` with ``|domain| = sum c / share``.

    >>> bg = np.zeros((9, 9, 3)); img = bg.copy(); img[:, :, 0] = 0.3                  # a uniform red cast
    >>> c = np.zeros((9, 9)); c[4, 4] = 1.0                                               # one covered pixel, mid-frame
    >>> round(lowpass_term_np(img, bg, c, 1.0, 1.0, 1.0), 4)   # the blur keeps a constant away from the edges: 0.09 / 3
    0.03
    """
    w = np.asarray(weights, np.float64)
    if w.sum() <= 0 or share <= 0:
        return 0.0
    b = _blur(np.asarray(img, np.float64) - np.asarray(target, np.float64), sigma)
    return float(weight) * float(np.sum(w[..., None] * b**2)) * float(share) / (3.0 * float(w.sum()))


def lowpass_grad_np(img: np.ndarray, target: np.ndarray, weights: np.ndarray, share: float, weight: float,
                    sigma: float) -> np.ndarray:
    """``dT / dI`` ``(h, w, 3)`` float64 of :func:`lowpass_term_np`."""
    w = np.asarray(weights, np.float64)
    if w.sum() <= 0 or share <= 0:
        return np.zeros(np.shape(img), np.float64)
    b = _blur(np.asarray(img, np.float64) - np.asarray(target, np.float64), sigma)
    return _blur(w[..., None] * b, sigma) * (2.0 * float(weight) * float(share) / (3.0 * float(w.sum())))


class TintTerm:
    """The term over a stage's views (module doc). ``targets``: per view the background target ``(h, w, 3)`` of its
    training window as the loss compares it; ``weights``: per view :func:`mask_weights` ``(h, w)``; ``share``: per
    view the mask's share of the loss domain's pixels (``sum weights / domain pixels``); ``weight`` W; ``sigma`` S
    (px; 0: the mean form, > 0: the local form).

    For the batch film (views side by side in one ``(H, V W, 3)`` render) pass ``film=(H, W, V)``: view ``v`` is the
    film's columns ``v W .. (v + 1) W``. :meth:`surrogate` returns the Dr.Jit scalar to add to the loss before
    ``dr.backward``; :attr:`last` holds the term's value and the mean ``|m - m*|`` (linear RGB) of the step."""

    def __init__(self, targets: list[np.ndarray], weights: list[np.ndarray], share: list[float], weight: float,
                 film: tuple[int, int, int] | None = None, sigma: float = 0.0):
        if not (len(targets) == len(weights) == len(share)):
            raise ValueError("one target, weight map and share per view")
        self.weight = float(weight)
        self.weights = [np.asarray(w, np.float64) for w in weights]
        self.targets = [np.asarray(t, np.float64) for t in targets]
        self.share = [float(s) for s in share]
        self.film = film
        self.sigma = float(sigma)
        self.last = {"value": 0.0, "error": None}

    def _view(self, arr: np.ndarray, v: int) -> np.ndarray:
        if self.film is None:
            return arr
        w = self.film[1]
        return arr[:, v * w:(v + 1) * w]

    def value_and_grads(self, arrays: list[np.ndarray], parts) -> tuple[float, dict[int, np.ndarray]]:
        """The mean over the step's views of the term and its gradient per image (``{image index: (h, w, 3)}``);
        ``arrays``: the step's renders as NumPy, ``parts``: per view ``(view, index of its image)``."""
        n = len(parts)
        value, errors, grads = 0.0, [], {}
        for v, k in parts:
            img = self._view(arrays[k], v)
            if self.weights[v].sum() <= 0:
                continue
            args = (img, self.targets[v], self.weights[v], self.share[v], self.weight)
            if self.sigma > 0:
                value += lowpass_term_np(*args, self.sigma) / n
                g = lowpass_grad_np(*args, self.sigma) / n
            else:
                value += term_np(*args) / n
                g = grad_np(*args) / n
            errors.append(float(np.linalg.norm(mean_colour(img, self.weights[v])
                                               - mean_colour(self.targets[v], self.weights[v]))))
            full = grads.setdefault(k, np.zeros(arrays[k].shape, np.float64))
            self._view(full, v)[...] += g
        self.last = {"value": value, "error": float(np.mean(errors)) if errors else None}
        return value, grads

    def surrogate(self, images, parts):
        """``images``: this step's renders (Dr.Jit ``TensorXf`` ``(h, w, 3)``, as the loss sees them); ``parts``: per
        view in the step ``(view, index of its image)``. Returns a Dr.Jit scalar whose gradient is the term's (its
        value is not: :attr:`last`), or None when no view has a mask."""
        import drjit as dr
        import mitsuba as mi

        arrays = [np.asarray(dr.detach(i), np.float64) for i in images]
        _, grads = self.value_and_grads(arrays, parts)
        if not grads:
            return None
        total = mi.Float(0.0)
        for k, g in grads.items():
            total = total + dr.sum(images[k].array * mi.Float(g.ravel().astype(np.float32)))
        return total
