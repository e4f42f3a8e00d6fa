"""A perceptual term next to Stage 1's photometric loss (``--perceptual W``, issue 29).

The gated loss (Eq. 9) and the squared error score pixels one at a time: a body that matches the background's mean
colour but not its texture (too smooth, or speckled) costs them little, and the eye sees it at once. LPIPS (Zhang et
al. 2018) compares deep features and does see it. With ``Stage1Settings.perceptual = W > 0`` each Stage 1 iteration
adds ``W * mean over views of LPIPS(render, background)`` to the loss:

* the render and its background target are compared as the evaluation compares them: linear radiance, clipped to
  ``[0, 1]``, sRGB-encoded; on the training window (the loss domain's bounding box, or the frame), padded with
  the background to the network's smallest input (32 px) where the window is smaller;
* the network runs outside Dr.Jit: the view's render is read back once, LPIPS and its gradient with respect to the
  linear render ``G = dLPIPS / dI`` are computed by the network's own autodiff, and Dr.Jit back-propagates the
  surrogate ``W * sum(I * G)``, whose gradient with respect to every scene parameter is exactly
  ``W * dLPIPS / dparam`` (``G`` is a constant of the backward pass);
* the value is logged as ``loss_perceptual`` (``W`` times the mean LPIPS over the step's views).

Where the network comes from (CONTRIBUTING.md's layering): the LPIPS networks and their weights live in
:mod:`evaluation.metrics.lpips`, which the optimiser must not import. The top layer passes the network in:
``import camo`` registers :func:`evaluation.metrics.lpips`-backed gradients with :func:`provide`; a program that
drives :func:`optimizer.optimise.run.run` without the ``camo`` package calls :func:`provide` itself (any function
with :data:`PerceptualFn`'s contract will do).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from camo_base.errors import SettingError

#: ``fn(x, y) -> (values, grad)``: ``x``, ``y`` float32 ``(N, H, W, 3)`` linear radiance (``y`` the targets);
#: ``values`` ``(N,)`` the distance of each pair, ``grad`` ``(N, H, W, 3)`` its derivative with respect to ``x``.
PerceptualFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

#: The networks ``perceptual_net`` may name (LPIPS v0.1 trunks).
NETS = ("alex", "vgg")

#: Smallest window side the networks take (AlexNet reaches relu5 at 31 px; VGG16 at 32 px).
MIN_SIDE = 32

_factory: Callable[[str], PerceptualFn] | None = None


def provide(factory: Callable[[str], PerceptualFn]) -> None:
    """Register ``factory(net) -> PerceptualFn`` (called by ``import camo``; the last registration wins)."""
    global _factory
    _factory = factory


def network(net: str) -> PerceptualFn:
    """The registered perceptual distance ``net`` (one of :data:`NETS`); a clear error when none is registered."""
    if net not in NETS:
        raise SettingError(f"{{0}} must be one of {', '.join(NETS)}, got {net!r}", "stage1.perceptual_net")
    if _factory is None:
        raise SettingError("{0} > 0 needs the LPIPS network: import camo (it registers evaluation.metrics.lpips) "
                           "or call optimizer.optimise.perceptual.provide(...)", "stage1.perceptual")
    return _factory(net)


def pad_to_min(x: np.ndarray, y: np.ndarray, side: int = MIN_SIDE) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """``x``, ``y`` ``(N, H, W, 3)`` padded at the bottom and right to at least ``side`` px with ``y``'s edge pixels
    (both images: the padding is identical, so it adds no distance); returns them and the original ``(H, W)``.

    >>> a, b, hw = pad_to_min(np.zeros((1, 20, 40, 3)), np.ones((1, 20, 40, 3)))
    >>> a.shape, hw, float(a[0, 25, 0, 0]), float(b[0, 25, 0, 0])
    ((1, 32, 40, 3), (20, 40), 1.0, 1.0)
    """
    h, w = x.shape[1:3]
    ph, pw = max(side - h, 0), max(side - w, 0)
    if not (ph or pw):
        return x, y, (h, w)
    yp = np.pad(y, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")
    xp = yp.copy()
    xp[:, :h, :w] = x
    return xp, yp, (h, w)


def perceptual_grad(fn: PerceptualFn, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``fn`` on windows of any size (padded by :func:`pad_to_min`); returns ``(values (N,), grad like x)``."""
    xp, yp, (h, w) = pad_to_min(np.asarray(x, np.float32), np.asarray(y, np.float32))
    values, grad = fn(xp, yp)
    return np.asarray(values, np.float64), np.ascontiguousarray(np.asarray(grad, np.float32)[:, :h, :w])
