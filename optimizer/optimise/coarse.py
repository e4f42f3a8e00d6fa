"""A coarse level under the albedo and transmittance maps (``--coarse-grid K``, issue 29): the body's colour moved as a
whole, at its own step size, instead of texel by texel.

Why. The glassy tint (:mod:`evaluation.metrics.tint`) is the body's mean colour against the ground's in the same
pixels, a low-frequency error. With the maps as the paper parameterises them (one value per texel, per-texel Adam) a
coherent colour error moves the body only as fast as each texel's own gradient, mostly Monte Carlo noise and texture
the multi-view body cannot hold, lets it: Adam divides each texel's step by that texel's running gradient magnitude.
The mean-colour term (:mod:`optimizer.optimise.tint`) weighted that error up, but its whole-body pull then set every
texel's normalised step at once (parts too dark and parts too bright pushed the same way), and 4 training views' mean
colours, matched texel by texel, did not carry over to novel views (docs/results/giveaways.md). A parameter with few
degrees of freedom cannot do either: its gradient is the sum of the texels' gradients under it, in which the per-texel
noise averages out and the shared colour error adds up, and it cannot fit one view's mean colour with texels that are
right for that view only.

The parameterisation. For each map ``X`` of :data:`COARSE_MAPS` with ``C`` channels, an offset grid ``c`` of ``K x K x
C`` cells (``K = 1``: one offset per channel for the whole body) is added to the fine map before rendering::

    X_rendered = clip(X_fine + U c, low, 1)

``U`` is bilinear interpolation between the cells' centres over the map's texel grid (edges clamped; rows sum to 1),
so a constant ``c`` is a constant offset. ``c`` is a parameter of Stage 1's Adam of its own (``<map>_coarse``, rate
``--coarse-lr``, kept in [-1, 1]); its gradient is ``U^T`` of the fine map's gradient where the clip is inactive, by
the gather's adjoint. The fine maps keep their own parameters, rate, gradient blur and projection. The result of the
stage is folded (:func:`fold`): the maps a run saves, exports and hands to Stage 2 are ``clip(X_fine + U c)``, so
nothing downstream knows the level existed. Stage 1 only; the ``fast`` preset's default is ``K = 1`` (no worse than
no level on crop PSNR and LPIPS-proxy on the six built-in scenes, docs/results/giveaways.md; ``--coarse-grid 0``
turns it off), the ``paper`` preset has none.

Cost: four gathers of the coarse grid per map and step (``R^2 C`` each; 0.2 M at 128 texels), next to a render.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: The maps that get a coarse level: the body's colour (albedo) and how much of the ground shows through it
#: (transmittance). Metallic and roughness are left alone: a whole-body offset of either turns sky glints on or off.
COARSE_MAPS = ("albedo", "transmittance")

#: The coarse offsets are kept in [-OFFSET_BOUND, OFFSET_BOUND] (a map value lives in [0, 1]).
OFFSET_BOUND = 1.0


def coarse_key(name: str) -> str:
    """The optimiser's name of map ``name``'s coarse level (``"albedo"`` -> ``"albedo_coarse"``)."""
    return f"{name}_coarse"


def interpolation_taps(fine: int, coarse: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of ``coarse`` cells onto ``fine`` texels along one axis, both spanning [0, 1] with samples
    at their centres and edges clamped: per texel the two cells ``(fine, 2)`` int64 and their weights ``(fine, 2)``
    float64 (summing to 1).

    >>> idx, w = interpolation_taps(4, 2)
    >>> idx.tolist(), w.round(3).tolist()
    ([[0, 1], [0, 1], [0, 1], [1, 1]], [[1.0, 0.0], [0.75, 0.25], [0.25, 0.75], [1.0, 0.0]])
    """
    if fine < 1 or coarse < 1:
        raise ValueError(f"grid sizes must be >= 1, got fine {fine}, coarse {coarse}")
    pos = np.clip((np.arange(fine) + 0.5) / fine * coarse - 0.5, 0.0, coarse - 1)  # in cell-centre units
    lo = np.minimum(np.floor(pos).astype(np.int64), coarse - 1)
    hi = np.minimum(lo + 1, coarse - 1)
    t = pos - lo
    return np.stack([lo, hi], 1), np.stack([1.0 - t, t], 1)


def interpolation_matrix(fine: int, coarse: int) -> np.ndarray:
    """``U`` along one axis as a dense ``(fine, coarse)`` float64 matrix (:func:`interpolation_taps`)."""
    idx, w = interpolation_taps(fine, coarse)
    u = np.zeros((fine, coarse))
    np.add.at(u, (np.repeat(np.arange(fine), 2), idx.ravel()), w.ravel())
    return u


def upsample_np(c: np.ndarray, resolution: int) -> np.ndarray:
    """``U c``: the coarse grid ``(K, K, C)`` interpolated onto ``(resolution, resolution, C)`` float64.

    >>> upsample_np(np.full((1, 1, 3), 0.2), 4)[2, 1].tolist()   # one cell: a constant offset
    [0.2, 0.2, 0.2]
    """
    c = np.asarray(c, np.float64)
    u = interpolation_matrix(resolution, c.shape[0])
    return np.einsum("ik,klc,jl->ijc", u, c, u)


def fold(values: dict[str, np.ndarray], coarse: dict[str, np.ndarray], lows: dict[str, float]) -> dict[str, np.ndarray]:
    """The maps as rendered: ``clip(X_fine + U c, low, 1)`` for every map in ``coarse`` (``{map name: (K, K, C)}``);
    the other values as they are (a new dict; float32 maps)."""
    out = dict(values)
    for name, c in coarse.items():
        fine = np.asarray(values[name], np.float64)
        out[name] = np.clip(fine + upsample_np(c, fine.shape[0]), lows[name], 1.0).astype(np.float32)
    return out


class CoarseLevel:
    """The coarse levels of a stage's maps (module doc): ``grid`` K cells a side over maps of ``resolution`` texels
    a side; ``channels``: ``{map name: C}``. :meth:`add` is the Dr.Jit side (fine + ``U c`` with its AD graph),
    :meth:`initial` the zero offsets the optimiser starts from."""

    def __init__(self, resolution: int, grid: int, channels: dict[str, int]):
        if grid < 1 or grid > resolution:
            raise ValueError(f"the coarse grid must have 1 to {resolution} cells a side, got {grid}")
        self.resolution, self.grid, self.channels = int(resolution), int(grid), dict(channels)
        idx, w = interpolation_taps(self.resolution, self.grid)
        self._taps: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        for C in set(self.channels.values()):
            taps = []
            for a in range(2):
                for b in range(2):
                    # texel (i, j), channel ch reads cell (idx[i, a], idx[j, b]) with weight w[i, a] w[j, b]
                    cell = (idx[:, a][:, None] * self.grid + idx[:, b][None, :])[..., None] * C + np.arange(C)
                    weight = np.broadcast_to((w[:, a][:, None] * w[:, b][None, :])[..., None],
                                             (self.resolution, self.resolution, C))
                    taps.append((cell.ravel().astype(np.uint32), weight.ravel().astype(np.float32)))
            self._taps[C] = taps
        self._dr_taps: dict[int, list[Any]] | None = None

    def initial(self, name: str) -> np.ndarray:
        """Zero offsets ``(K, K, C)`` float32 for map ``name``."""
        return np.zeros((self.grid, self.grid, self.channels[name]), np.float32)

    def add(self, fine, coarse, low: float):
        """``clip(fine + U coarse, low, 1)`` as a Dr.Jit ``TensorXf`` ``(R, R, C)`` (gradients flow to both)."""
        import drjit as dr
        import mitsuba as mi

        if self._dr_taps is None:
            self._dr_taps = {C: [(mi.UInt32(i), mi.Float(w)) for i, w in taps] for C, taps in self._taps.items()}
        C = fine.shape[2]
        up = None
        for i, w in self._dr_taps[C]:
            term = dr.gather(mi.Float, coarse.array, i) * w
            up = term if up is None else up + term
        return mi.TensorXf(dr.clip(fine.array + up, low, 1.0), fine.shape)
