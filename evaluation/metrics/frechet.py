"""Frechet distance between Gaussians, and the per-image feature statistics that SIFID compares."""

from __future__ import annotations

import math
from typing import Union

import numpy as np
import torch

from camo_base.errors import CamoError

ArrayLike = Union[np.ndarray, torch.Tensor]


def _f64(a: ArrayLike) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().double().numpy()
    return np.asarray(a, dtype=np.float64)


def trace_sqrt_product(sigma1: ArrayLike, sigma2: ArrayLike) -> float:
    r""":math:`\operatorname{tr}\sqrt{\Sigma_1 \Sigma_2}` from the eigenvalues of :math:`\Sigma_1 \Sigma_2`.

    For symmetric positive semi-definite matrices the product is similar to the PSD matrix
    :math:`\Sigma_1^{1/2} \Sigma_2 \Sigma_1^{1/2}`, so its eigenvalues are real and >= 0; round-off can give tiny
    imaginary parts or negative values, so the real parts are clipped at 0 before the square root.
    """
    ev = np.linalg.eigvals(_f64(sigma1) @ _f64(sigma2))
    return float(np.sqrt(np.clip(ev.real, 0.0, None)).sum())


def frechet_distance(
    mu1: ArrayLike, sigma1: ArrayLike, mu2: ArrayLike, sigma2: ArrayLike, eps: float = 1e-6
) -> float:
    r"""Squared Frechet (2-Wasserstein) distance between :math:`N(\mu_1, \Sigma_1)` and :math:`N(\mu_2, \Sigma_2)`.

    .. math:: d^2 = \lVert \mu_1 - \mu_2 \rVert^2 + \operatorname{tr}\Sigma_1 + \operatorname{tr}\Sigma_2
              - 2 \operatorname{tr}\sqrt{\Sigma_1 \Sigma_2}

    as in FID/SIFID (Heusel et al. 2017; Shaham et al. 2019). The trace of the matrix square root is the sum of
    the square roots of the (real, clipped >= 0) eigenvalues of :math:`\Sigma_1 \Sigma_2`, in float64, so no
    ``scipy.linalg.sqrtm`` is needed. Rank-deficient covariances (fewer samples than dimensions, dead ReLU
    channels, flat images) need no special case here: their zero eigenvalues are simply clipped to 0 and the
    result stays finite and exact (e.g. ``diag(1, 0)`` vs ``diag(0, 1)`` gives 2). Identical covariances skip the
    term altogether (it is exactly 0): the result is then ``||mu1 - mu2||^2``. Only if the eigen-solver
    fails or returns non-finite values is a ridge ``eps * I`` added to both covariances inside the square-root
    term (pytorch-fid's and SinGAN's fallback). It is not added by default because it moves the result by about
    ``2 sqrt(eps * var)`` per direction that is flat in one image only (~2e-3 for unit variance), the size of the
    SIFID values in the paper's Table II. The covariance term is computed on covariances divided by their largest
    entry and scaled back (the distance is homogeneous), so covariances of any magnitude -- entries of 1e-200,
    whose product would underflow -- keep float64's relative precision. Round-off can make the sum slightly
    negative; the result is clamped at 0.

    Args:
        mu1, mu2: means ``(D,)``.
        sigma1, sigma2: covariances ``(D, D)``, symmetric PSD (checked: :func:`check_covariance`).
        eps: ridge used only when the eigen-solver fails (see above).

    Raises:
        CamoError: one line for mismatched shapes, NaN/inf, a covariance that is not symmetric or not PSD (to a
        relative 1e-6), entries above 1e150 (the product would overflow), or a non-finite result.

    Returns:
        Python float >= 0, in squared feature units; 0 for identical Gaussians.
    """
    m1, m2 = np.atleast_1d(_f64(mu1)), np.atleast_1d(_f64(mu2))
    s1, s2 = np.atleast_2d(_f64(sigma1)), np.atleast_2d(_f64(sigma2))
    d = m1.shape[0]
    if m1.shape != m2.shape or s1.shape != (d, d) or s2.shape != (d, d):
        raise CamoError(
            f"frechet_distance: shapes do not match: mu {m1.shape} / {m2.shape}, sigma {s1.shape} / {s2.shape}"
        )
    if not all(np.isfinite(a).all() for a in (m1, m2, s1, s2)):
        raise CamoError("frechet_distance: statistics contain NaN or infinite values")
    for name, s_ in (("sigma1", s1), ("sigma2", s2)):
        check_covariance(s_, name)
    diff = m1 - m2
    if np.array_equal(s1, s2):
        return float(diff @ diff)  # identical covariances: the covariance term is exactly 0
    # The distance is homogeneous: features scaled by c give c^2 d^2. Compute it on covariances scaled to a largest
    # entry of 1 and scale back, so that tiny covariances (entries <= ~1e-160, whose product underflows to 0 and
    # would drop the cross term) and large ones keep full float64 precision.
    scale = max(float(np.abs(s1).max()), float(np.abs(s2).max()))
    if scale > 0 and math.isfinite(scale):
        cov_term = scale * _covariance_term(s1 / scale, s2 / scale, eps, d)
    else:
        cov_term = _covariance_term(s1, s2, eps, d)
    value = float(diff @ diff) + cov_term
    if not np.isfinite(value):
        raise CamoError("frechet_distance: the result overflows float64; rescale the features")
    return max(value, 0.0)


def _covariance_term(s1: np.ndarray, s2: np.ndarray, eps: float, d: int) -> float:
    """``tr S1 + tr S2 - 2 tr sqrt(S1 S2)`` (with the ridge fallback of :func:`frechet_distance`)."""
    try:
        tr_covmean = trace_sqrt_product(s1, s2)
        ok = np.isfinite(tr_covmean)
    except np.linalg.LinAlgError:
        ok = False
    if not ok:
        ridge = eps * np.eye(d)
        try:
            tr_covmean = trace_sqrt_product(s1 + ridge, s2 + ridge)
        except np.linalg.LinAlgError as exc:
            raise CamoError(f"frechet_distance: the eigen-solver failed on sigma1 @ sigma2 ({exc})") from None
    return float(np.trace(s1) + np.trace(s2) - 2.0 * tr_covmean)


#: Largest covariance entry accepted: the product of two such matrices (D up to ~1e4 terms per entry) stays finite.
MAX_COVARIANCE = 1e150
#: Relative tolerance of the symmetry and positive semi-definiteness checks (float64 round-off of np.cov is
#: ~1e-16 relative; statistics from float32 features ~1e-7).
COVARIANCE_RTOL = 1e-6


def check_covariance(sigma: np.ndarray, name: str = "sigma") -> None:
    """CamoError (one line) unless ``sigma`` is a symmetric positive semi-definite matrix with entries below
    :data:`MAX_COVARIANCE` in magnitude; symmetry and PSD are checked to :data:`COVARIANCE_RTOL` times the
    largest entry (resp. eigenvalue)."""
    scale = float(np.abs(sigma).max()) if sigma.size else 0.0
    if scale > MAX_COVARIANCE:
        raise CamoError(f"frechet_distance: {name} has entries up to {scale:.3g}, beyond {MAX_COVARIANCE:g} (its "
                        "product with the other covariance would overflow float64); rescale the features")
    asym = float(np.abs(sigma - sigma.T).max()) if sigma.size else 0.0
    if asym > COVARIANCE_RTOL * scale:
        raise CamoError(f"frechet_distance: {name} is not symmetric (max |sigma - sigma^T| = {asym:.3g}, largest entry "
                        f"{scale:.3g}); pass a covariance matrix")
    if scale > 0:
        lo = float(np.linalg.eigvalsh(0.5 * (sigma + sigma.T)).min())
        if lo < -COVARIANCE_RTOL * scale:
            raise CamoError(f"frechet_distance: {name} is not positive semi-definite (smallest eigenvalue {lo:.3g}, "
                            f"largest entry {scale:.3g}); pass a covariance matrix")


def feature_statistics(features: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(C,)`` and unbiased covariance ``(C, C)`` (``np.cov(rowvar=False)``) over the positions of one
    feature map ``(C, H, W)``: every spatial location is one sample, as in SinGAN's SIFID. Float64."""
    if features.ndim != 3:
        raise CamoError(f"feature_statistics: expected (C, H, W), got {tuple(features.shape)}")
    c = features.shape[0]
    f = features.detach().to("cpu", torch.float64).permute(1, 2, 0).reshape(-1, c)  # (HW, C)
    if f.shape[0] < 2:
        raise CamoError("feature_statistics: the feature map has fewer than 2 positions; use a larger image")
    mu = f.mean(dim=0)
    fc = f - mu
    cov = fc.T @ fc / (f.shape[0] - 1)
    return mu.numpy(), cov.numpy()


def frechet_of_feature_maps(fx: torch.Tensor, fy: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Per-image Frechet distance of two batches of feature maps ``(N, C, H, W)`` (sizes may differ);
    returns ``(N,)`` float64."""
    out = [frechet_distance(*feature_statistics(a), *feature_statistics(b), eps=eps) for a, b in zip(fx, fy)]
    return torch.tensor(out, dtype=torch.float64)
