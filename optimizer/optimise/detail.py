"""A detail term next to Stage 1's photometric loss (``--detail-match W``, issue 29): the body's pixel-scale texture
energy matched to the ground's.

Why. The squared error of one body seen in several views has its optimum at a body *smoother* than the ground: a
texel that covers ground pixel ``p1`` in one view and ``p2`` in another is best at their mean, and the mean of
``V`` unrelated patches of grain has ``1 / sqrt(V)`` of the grain's amplitude. Measured: the converged detail ratio
(:mod:`evaluation.metrics.detail_ratio`) of today's default is 0.59-0.63 on meadow and gravel at 4 views
(docs/results/giveaways.md), and neither LPIPS nor a lower IOR moved it. The eye sees a smooth body on grainy ground
at once. This term asks for the ground's texture energy (its statistics), not for its pixels.

The term. For view ``v``, with ``Y`` the luma of the render as the loss compares it (linear radiance, soft-clamped
when ``--loss-clamp``), ``Lap`` the 3x3 8-neighbour Laplacian (the detail ratio's kernel) and ``M`` the interior
of the object's coverage (pixels whose 3x3 neighbourhood is covered, fully, in the training window)::

    E_v  = mean_M Lap(Y_t) * Lap(Y_{t-1})        the render's texture energy
    E*_v = mean_M Lap(Y_bg)^2                    the background target's, same pixels
    T    = W * mean_v  s_v / (4 G max(E*_v, F)) * (E_v - E*_v)^2

``s_v`` is the interior's share of the loss domain's pixels, ``G`` = 72 the kernel's squared norm (one unit of white
noise has energy ``G``) and ``F`` a floor of ``G (1e-3)^2`` (a flat ground). Near the match ``T`` is
``W s_v (sqrt(E_v) - sqrt(E*_v))^2 / G``: the squared error the body's missing grain would cost on those pixels,
times ``W``. The squared error charges uncorrelated grain of amplitude ``a`` (a fraction of the ground's) ``a^2``
and the term ``W / 4 (a^2 - 1)^2``: their sum is least at ``a^2 = 1 - 2 / W`` (W = 8: a = 0.87). So the term buys
texture at a price in PSNR, by design; the issue's measure decides whether it is worth it.

Noise. A 4-spp render's own Monte Carlo noise has Laplacian energy far above the ground's grain, so
``mean Lap(Y_t)^2`` would say "detailed" of a flat body. ``E_v`` is instead the product of this step's render with
the previous step's (another sampler seed: independent noise, ``E[Lap(Y_t) Lap(Y_{t-1})] = Lap(mu_t) Lap(mu_{t-1})``):
unbiased up to one step's parameter change. Its gradient flows through ``Y_t`` only and is doubled (the derivative of
``Lap(mu)^2``); the first step, without a previous render, has no term. No extra render: the term reads the renders back once and adds one multiply-add per pixel to the backward pass.
"""

from __future__ import annotations

import numpy as np

from camo_base.imaging import REC709_LUMA

#: The 3x3 8-neighbour Laplacian's squared norm (8^2 + 8 x 1^2): the energy of unit white noise.
GAIN = 72.0
#: Floor of the target energy, in luma units (F = GAIN x FLOOR^2): a flat ground does not make the weight explode.
FLOOR = 1e-3
#: Coverage at or above which a pixel counts as the object's (the silhouette's partly covered pixels mix in ground).
FULL = 0.999

#: (dy, dx) of the 8 neighbours, in the order of the tap rows 1..8.
NEIGHBOURS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))


def interior_taps(covered: np.ndarray, column_offset: int = 0, width: int | None = None) -> np.ndarray:
    """Flat pixel indices ``(9, n)`` int64 of the pixels of ``covered`` ``(H, W)`` bool whose whole 3x3
    neighbourhood is covered and inside the image: row 0 the pixel, rows 1..8 its neighbours (:data:`NEIGHBOURS`).
    ``column_offset``, ``width``: the image is a film of views side by side, this view's columns start at
    ``column_offset`` and the film is ``width`` wide (default: the view alone).

    >>> interior_taps(np.ones((3, 4), bool))[:, 0].tolist()   # (1, 1) and its neighbours in a 4-wide image
    [5, 0, 1, 2, 4, 6, 8, 9, 10]
    """
    c = np.asarray(covered, bool)
    h, w = c.shape
    ok = np.zeros_like(c)
    if h >= 3 and w >= 3:
        inner = np.ones((h - 2, w - 2), bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                inner &= c[1 + dy: h - 1 + dy, 1 + dx: w - 1 + dx]
        ok[1:-1, 1:-1] = inner
    ys, xs = np.nonzero(ok)
    fw = w if width is None else int(width)
    rows = [(ys + dy) * fw + xs + dx + column_offset for dy, dx in ((0, 0), *NEIGHBOURS)]
    return np.stack(rows).astype(np.int64) if len(ys) else np.zeros((9, 0), np.int64)


def luma_np(img: np.ndarray) -> np.ndarray:
    """Rec. 709 luma of ``(..., 3)`` (float64)."""
    return np.asarray(img, np.float64) @ REC709_LUMA.astype(np.float64)


def laplacian_at(y: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """The 8-neighbour Laplacian (neighbours minus 8 x the pixel) of the flat image ``y`` at ``taps`` ``(9, n)``:
    ``(n,)`` float64."""
    y = np.asarray(y, np.float64).ravel()
    return y[taps[1:]].sum(0) - 8.0 * y[taps[0]]


def energy_np(img_a: np.ndarray, img_b: np.ndarray, taps: np.ndarray) -> float:
    """``mean Lap(Y_a) Lap(Y_b)`` over the taps (``img_*`` ``(H, W, 3)`` linear; NaN without taps); ``a = b`` gives
    the texture energy of one image.

    >>> img = np.zeros((5, 5, 3)); img[2, 2] = 1.0           # one white pixel: luma 1
    >>> round(energy_np(img, img, interior_taps(np.ones((5, 5), bool))), 4)   # (64 + 8 x 1) / 9 interior pixels
    8.0
    """
    if taps.shape[1] == 0:
        return float("nan")
    return float(np.mean(laplacian_at(luma_np(img_a), taps) * laplacian_at(luma_np(img_b), taps)))


def coefficient(target: float, share: float, weight: float) -> float:
    """``W s / (4 G max(E*, F))``: the factor of ``(E - E*)^2`` in the term (module doc)."""
    return float(weight) * float(share) / (4.0 * GAIN * max(float(target), GAIN * FLOOR**2))


def term_np(energy: float, target: float, share: float, weight: float) -> float:
    """The term's value for one view (module doc), float64.

    >>> term_np(4.0, 4.0, 0.5, 8.0), round(term_np(0.0, 72e-4, 1.0, 4.0), 8)   # matched; no grain, target 1e-2 rms
    (0.0, 0.0001)
    """
    return coefficient(target, share, weight) * (float(energy) - float(target)) ** 2


class DetailTerm:
    """The term over a stage's views (module doc). ``targets``: per view the tonemapped background target
    ``(h, w, 3)`` of its training window (or None for the batch film's views: ``film``); ``covered``: per view
    ``(h, w)`` bool, the object's fully covered pixels in that window; ``share``: per view the interior's share of
    the loss domain's pixels; ``weight`` W.

    For the batch film (views side by side in one ``(H, V W, 3)`` render) pass ``film=(H, W, V)``: taps then index
    the film. :meth:`surrogate` returns the Dr.Jit scalar to add to the loss before ``dr.backward`` and remembers
    this step's renders for the next (:meth:`state` / :meth:`load_state`: they travel in a checkpoint, so a resumed run
    continues as the run would have); :attr:`last` holds the term's value and the mean ``sqrt(E / E*)`` of the step
    (None without a previous render).
    """

    def __init__(self, targets: list[np.ndarray], covered: list[np.ndarray], share: list[float], weight: float,
                 film: tuple[int, int, int] | None = None):
        self.weight = float(weight)
        self.taps, self.target, self.coef = [], [], []
        for v, (tgt, cov) in enumerate(zip(targets, covered)):
            taps = interior_taps(cov) if film is None else \
                interior_taps(cov, column_offset=v * film[1], width=film[1] * film[2])
            local = interior_taps(cov)
            e = energy_np(tgt, tgt, local) if local.shape[1] else float("nan")
            self.taps.append(taps)
            self.target.append(e)
            self.coef.append(coefficient(e, share[v], weight) if np.isfinite(e) else 0.0)
        self.film = film
        self.previous: dict[int, np.ndarray] = {}  # image index -> the previous step's luma (flat, float64)
        self.last = {"value": 0.0, "ratio": None}

    def surrogate(self, images, parts):
        """``images``: this step's renders (Dr.Jit ``TensorXf`` ``(h, w, 3)``, soft-clamped as the loss sees them);
        ``parts``: per view in the step ``(view, index of its image)``. Returns a Dr.Jit scalar whose gradient is the
        term's (its value is not: :attr:`last`), or None on a step without a previous render."""
        import drjit as dr
        import mitsuba as mi

        arrays = [np.asarray(dr.detach(i), np.float64) for i in images]
        lumas = [luma_np(a).ravel() for a in arrays]
        grads: dict[int, np.ndarray] = {}  # image index -> d(term)/d(luma), flat
        value, ratios = 0.0, []
        n_views = len(parts)
        for v, k in parts:
            taps = self.taps[v]
            prev = self.previous.get(k)
            if prev is None or taps.shape[1] == 0 or self.coef[v] == 0.0:
                continue
            lap_prev = laplacian_at(prev, taps)
            e = float(np.mean(laplacian_at(lumas[k], taps) * lap_prev))
            value += self.coef[v] * (e - self.target[v]) ** 2 / n_views
            ratios.append(np.sqrt(max(e, 0.0) / max(self.target[v], GAIN * FLOOR**2)))
            # d/dY_t of coef (E - E*)^2 / V with dE/dY_t = 2 Lap^T(Lap Y_{t-1}) / n (the doubled cross product)
            c = (2.0 * self.coef[v] * (e - self.target[v]) * 2.0 / taps.shape[1] / n_views) * lap_prev
            g = grads.setdefault(k, np.zeros(lumas[k].size))
            np.add.at(g, taps[0], -8.0 * c)
            for row in range(1, 9):
                np.add.at(g, taps[row], c)
        for k, y in enumerate(lumas):
            self.previous[k] = y
        self.last = {"value": value, "ratio": float(np.mean(ratios)) if ratios else None}
        if not grads:
            return None
        # the surrogate sum(I * G): G a constant of the backward pass, so its gradient is the term's (one multiply-add
        # per pixel; gathering the Laplacian in Dr.Jit cost seconds a step)
        total = mi.Float(0.0)
        luma_w = REC709_LUMA.astype(np.float64)
        for k, g in grads.items():
            G = (g[:, None] * luma_w[None, :]).ravel().astype(np.float32)
            total = total + dr.sum(images[k].array * mi.Float(G))
        return total

    def state(self) -> dict[str, np.ndarray]:
        """The previous step's lumas, for a checkpoint (keys ``detail_prev/K``)."""
        return {f"detail_prev/{k}": np.asarray(y, np.float64) for k, y in self.previous.items()}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore :meth:`state` (missing keys: no previous render, as at a stage's first step)."""
        self.previous = {int(key.split("/", 1)[1]): np.asarray(v, np.float64).ravel()
                         for key, v in state.items() if key.startswith("detail_prev/")}
