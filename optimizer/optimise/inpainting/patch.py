"""Offline Stage-2 backend ``"patch"``: depth-aware multi-scale PatchMatch texture synthesis.

What it does (an exemplar-based stand-in for the depth-ControlNet SDXL
inpainter of the paper, Eq. 13 and Fig. 8, that runs without weights):

1. **Sources.** Patches are copied only from ``background_srgb`` *outside* the
   mask: a source patch (``patch_size`` x ``patch_size``) must lie entirely in
   the image and entirely outside the (dilated) hole. What the background
   render holds behind the object is never read.
2. **Depth-aware patch distance** (the role of the depth ControlNet). For a
   target patch ``T`` (current estimate, with the known context around the
   hole) and a source patch ``S``::

       d(T, S) = mean|T_rgb - S_rgb|^2 / var_rgb                      colour SSD, normalised
               + depth_weight * mean(z_T - z_S)^2 / ln(depth_tolerance)^2   depth term
               + g * mean_{hole}|G_rgb - S_rgb|^2 / var_rgb          Stage-1 guide (see 4.)

   with ``z = ln(depth)`` per pixel (sky, depth 0, is put ``sky_ratio`` times
   beyond the farthest hit), so the depth term measures the *scale ratio* of
   the surfaces: one unit of cost for surfaces ``depth_tolerance`` times
   nearer/farther. ``var_rgb`` is the colour variance of the source pixels.
   Colours are compared in sRGB (the space the caller passes, Eq. 12); the
   known context of a target patch is ``image_srgb`` outside the mask.
   The depth of the background behind the object is known, so a target pixel
   only takes texture from background at a similar distance (the far wall is
   not pasted onto the near floor).
3. **Synthesis.** Coarse-to-fine image pyramid (2x2 box, hole max-pooled);
   the coarsest hole is initialised with OpenCV Telea; at each level a few EM
   iterations alternate a vectorised PatchMatch (parallel jump-flood
   propagation over the hole, shrinking random search, global random
   candidates; one seeded NumPy generator) with Wexler-style voting: every hole
   pixel is the weighted mean of the overlapping matched source patches, with
   weights ``exp(-(d - d_min) / (2 sigma^2))`` (``d_min`` = best distance among
   the patches covering that pixel, ``sigma^2`` = ``vote_sharpness`` x the
   75th percentile of d; a sharp vote, because the plain Wexler vote averages
   textures into a blur) times a per-pixel depth agreement
   ``exp(-dz^2 / 2)``. The nearest-neighbour field is upsampled to the next
   level, where PatchMatch only refines locally (``refine_radius``) plus global
   random candidates. Low-texture areas (local std of the result below ``flat_std``) are
   blended toward the Telea fill where it agrees with the synthesised local
   mean, which removes small seams in smooth gradients without letting Telea
   smear colour across depth bands.
4. **strength <-> t_start.** Read ``strength`` as the fraction ``s`` of the
   diffusion schedule that is re-noised, with the linear approximation
   ``alpha_bar(t_start) ~ 1 - s`` of the fraction of the Stage-1 signal that
   survives the noise. Then (a) the patch search is guided toward the Stage-1
   render inside the hole with the weight ``g = SNR(t_start) = (1 - s) / s``
   (capped at 100; 0 at s = 1: pure synthesis; large at small s: patches that resemble the
   Stage-1 render), and (b) the result inside the mask keeps the *coarse* content
   of the Stage-1 render and takes the *detail* from the synthesis, as partial
   re-noising does (noise at t_start drowns the fine scales of the input first;
   the denoiser regenerates them): with a Gaussian low-pass ``G`` of width
   ``sigma = detail_sigma * s / (1 - s)`` px,
   ``G * (s * synthesis + (1 - s) * image) + (synthesis - G * synthesis)``.
   So ``strength = 1`` is fully synthesised and ignores ``image_srgb`` inside the
   mask, ``strength -> 0`` returns ``image_srgb``, and at the default 0.5
   isolated Stage-1 defects finer than ~``detail_sigma`` (specular sparkles,
   texel noise) are replaced by background texture instead of being kept at
   half strength, which a plain linear blend would do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from camo_base.errors import CamoError
from camo_base.imaging import REC709_LUMA
from optimizer.optimise.inpainting.base import Inpainter


@dataclass(frozen=True)
class PatchOptions:
    """Options of the ``patch`` backend (``get_inpainter("patch", **options)``)."""

    patch_size: int = 7  # odd, pixels
    depth_weight: float = 1.0  # lambda of the depth term
    depth_tolerance: float = 1.5  # depth ratio that costs one unit
    sky_ratio: float = 8.0  # sky = this many times beyond the farthest hit
    levels: int | None = None  # pyramid levels; None = from the hole size
    em_iters_coarse: int = 6
    em_iters_fine: int = 3
    pm_iters: int = 2  # PatchMatch sweeps per EM iteration
    random_candidates: int = 2  # global random candidates per PatchMatch sweep
    flat_std: float = 0.01  # local std (sRGB) below which an area counts as low-texture
    min_sources: int = 16  # fewest valid source patches a pyramid level must have
    refine_radius: int = 16  # random-search radius on levels initialised from a coarser level
    vote: str = "weighted"  # "weighted" (Wexler) or "best" (lowest-distance covering patch)
    final_vote: str = "weighted"  # voting of the last EM iteration at full resolution
    vote_sharpness: float = 0.05  # scales sigma^2 of the voting weights (small = sharp, less blur)
    detail_sigma: float = 2.0  # px: scale below which the synthesis replaces the render at strength 0.5

    def check(self) -> "PatchOptions":
        if self.patch_size < 3 or self.patch_size % 2 == 0:
            raise CamoError(f"patch inpainter: patch_size must be odd and >= 3, got {self.patch_size}")
        if self.depth_weight < 0:
            raise CamoError(f"patch inpainter: depth_weight must be >= 0, got {self.depth_weight}")
        if self.depth_tolerance <= 1.0:
            raise CamoError(f"patch inpainter: depth_tolerance must be > 1, got {self.depth_tolerance}")
        if self.sky_ratio <= 1.0:
            raise CamoError(f"patch inpainter: sky_ratio must be > 1, got {self.sky_ratio}")
        if self.levels is not None and self.levels < 1:
            raise CamoError(f"patch inpainter: levels must be >= 1, got {self.levels}")
        if not self.detail_sigma > 0:
            raise CamoError(f"patch inpainter: detail_sigma must be > 0, got {self.detail_sigma}")
        for k in ("em_iters_coarse", "em_iters_fine", "pm_iters"):
            if getattr(self, k) < 1:
                raise CamoError(f"patch inpainter: {k} must be >= 1, got {getattr(self, k)}")
        for k in ("vote", "final_vote"):
            if getattr(self, k) not in ("weighted", "best"):
                raise CamoError(f"patch inpainter: {k} must be 'weighted' or 'best', got {getattr(self, k)!r}")
        if self.vote_sharpness <= 0 or self.refine_radius < 1:
            raise CamoError("patch inpainter: vote_sharpness must be > 0 and refine_radius >= 1")
        if self.random_candidates < 0 or self.min_sources < 1 or self.flat_std < 0:
            raise CamoError("patch inpainter: random_candidates, min_sources and flat_std must be >= 0 (min_sources >= 1)")
        return self


# ----------------------------------------------------------------------------- helpers


def log_depth(depth: np.ndarray, sky_ratio: float) -> np.ndarray:
    """Per-pixel ``ln(depth)``; sky (depth <= 0) is placed ``sky_ratio`` x beyond the farthest hit."""
    hit = depth > 0
    z = np.zeros(depth.shape, np.float32)
    if hit.any():
        z[hit] = np.log(depth[hit])
        z[~hit] = float(z[hit].max()) + math.log(sky_ratio)
    return z


def telea_fill(image: np.ndarray, hole: np.ndarray, radius: int = 3) -> np.ndarray:
    """OpenCV Telea inpainting of ``(H, W, C)`` float32 (per channel, no 8-bit quantisation)."""
    import cv2

    m = hole.astype(np.uint8)
    # OpenCV's float path misbehaves on [0, 1] data (overshoots far outside the range); it is
    # fine on the 0..255 scale it was tuned for, so scale there and back (still no quantisation).
    chans = [
        cv2.inpaint(np.ascontiguousarray(image[..., c] * 255.0, dtype=np.float32), m, radius, cv2.INPAINT_TELEA)
        for c in range(image.shape[2])
    ]
    return np.clip(np.stack(chans, axis=-1) / 255.0, 0.0, 1.0).astype(np.float32)


def _down(x: np.ndarray) -> np.ndarray:
    """2x2 box downsampling (edge-padded to even size): fine (2i, 2i+1) -> coarse i."""
    h, w = x.shape[:2]
    pad = [(0, h % 2), (0, w % 2)] + [(0, 0)] * (x.ndim - 2)
    x = np.pad(x, pad, mode="edge")
    h2, w2 = x.shape[0] // 2, x.shape[1] // 2
    return x.reshape(h2, 2, w2, 2, *x.shape[2:]).mean(axis=(1, 3)).astype(np.float32)


def _down_any(m: np.ndarray) -> np.ndarray:
    h, w = m.shape
    m = np.pad(m, [(0, h % 2), (0, w % 2)], mode="edge")
    return m.reshape(m.shape[0] // 2, 2, m.shape[1] // 2, 2).any(axis=(1, 3))


def _dilate(m: np.ndarray, r: int) -> np.ndarray:
    """Binary dilation by a (2r+1)^2 square."""
    import cv2

    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.dilate(m.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def renoise_mix(image: np.ndarray, synth: np.ndarray, strength: float, detail_sigma: float) -> np.ndarray:
    """Coarse scales from a ``strength``-blend of ``image`` and ``synth``, fine scales from ``synth`` (module doc, 4b).

    ``image``, ``synth``: ``(H, W, 3)`` float32 sRGB; the low-pass is a Gaussian of ``detail_sigma * s / (1 - s)``
    px (capped at 64 px; none below 0.05 px, where the result is the plain blend)."""
    import cv2

    s = float(strength)
    if s >= 1.0:
        return synth
    blend = s * synth + (1.0 - s) * image
    sigma = min(detail_sigma * s / (1.0 - s), 64.0)
    if sigma < 0.05:
        return blend

    def low(x):
        return cv2.GaussianBlur(np.ascontiguousarray(x, np.float32), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)

    return low(blend) + (synth - low(synth))


def _local_std(x: np.ndarray, r: int) -> np.ndarray:
    import cv2

    k = (2 * r + 1, 2 * r + 1)
    mu = cv2.blur(x, k, borderType=cv2.BORDER_REFLECT)
    mu2 = cv2.blur(x * x, k, borderType=cv2.BORDER_REFLECT)
    return np.sqrt(np.maximum(mu2 - mu * mu, 0.0))


def _valid_sources(hole: np.ndarray, r: int) -> np.ndarray:
    """Centres whose full patch lies inside the image and outside the hole."""
    h, w = hole.shape
    v = ~_dilate(hole, r)
    v[:r, :] = False
    v[h - r :, :] = False
    v[:, :r] = False
    v[:, w - r :] = False
    return v


# ----------------------------------------------------------------------------- one pyramid level


class _Level:
    """Arrays of one pyramid level, padded by the patch radius, and the patch distance."""

    def __init__(self, canvas, src_rgb, z, guide, hole, r, var_rgb, opts: PatchOptions, g: float):
        self.h, self.w = hole.shape
        self.r = r
        self.hole = hole
        self.wp = self.w + 2 * r
        self.hp = self.h + 2 * r
        dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
        self.offs = (dy * self.wp + dx).ravel().astype(np.int64)  # (P,)
        self.P = self.offs.size
        self.valid = _valid_sources(hole, r)
        self.n_valid = int(self.valid.sum())
        ty, tx = np.nonzero(_dilate(hole, r))  # patches that overlap the hole
        self.ty, self.tx = ty.astype(np.int64), tx.astype(np.int64)
        self.N = ty.size
        self.tmap = np.full((self.h, self.w), -1, np.int64)
        self.tmap[ty, tx] = np.arange(self.N)
        self.tflat = (ty + r) * self.wp + (tx + r)
        vy, vx = np.nonzero(self.valid)
        self.vy, self.vx = vy.astype(np.int64), vx.astype(np.int64)
        # feature scales: colour / sqrt(var), depth * sqrt(lambda) / ln(tol)
        self.cs = 1.0 / math.sqrt(var_rgb)
        self.zs = math.sqrt(opts.depth_weight) / math.log(opts.depth_tolerance)
        self.g = g
        # padded source features: (Np, 4) = rgb*cs, z*zs  (content outside the valid patches is never read)
        src = np.concatenate([src_rgb * self.cs, z[..., None] * self.zs], axis=-1).astype(np.float32)
        self.src = np.pad(src, [(r, r), (r, r), (0, 0)], mode="reflect").reshape(-1, 4)
        self.zpad = np.pad(z * self.zs, r, mode="reflect").astype(np.float32).ravel()
        self.src_rgb = np.pad(src_rgb, [(r, r), (r, r), (0, 0)], mode="reflect").reshape(-1, 3)
        if g > 0:
            gp = np.pad(guide * self.cs, [(r, r), (r, r), (0, 0)], mode="reflect").reshape(-1, 3)
            hp = np.pad(hole, r, mode="reflect").ravel()
            tidx = self.tflat[:, None] + self.offs[None, :]
            self.t_guide = gp[tidx]  # (N, P, 3)
            self.t_ghole = hp[tidx].astype(np.float32)  # (N, P)
        self.canvas = canvas.astype(np.float32).copy()
        self.set_targets()

    def set_targets(self) -> None:
        """Gather the target patches of the current canvas: (N, P, 4)."""
        r = self.r
        cp = np.pad(self.canvas * self.cs, [(r, r), (r, r), (0, 0)], mode="reflect").reshape(-1, 3)
        tidx = self.tflat[:, None] + self.offs[None, :]
        self.t_feat = np.concatenate([cp[tidx], self.zpad[tidx][..., None]], axis=-1)

    _CHUNK = 16384  # targets per block: bounds the (n, P, 4) temporaries to ~13 MB each

    def cost(self, sel: np.ndarray, sy: np.ndarray, sx: np.ndarray) -> np.ndarray:
        """Patch distance of targets ``sel`` to source centres (sy, sx) (all valid)."""
        if sel.size > self._CHUNK:
            return np.concatenate(
                [self._cost(sel[i : i + self._CHUNK], sy[i : i + self._CHUNK], sx[i : i + self._CHUNK])
                 for i in range(0, sel.size, self._CHUNK)]
            )
        return self._cost(sel, sy, sx)

    def _cost(self, sel: np.ndarray, sy: np.ndarray, sx: np.ndarray) -> np.ndarray:
        sflat = (sy + self.r) * self.wp + (sx + self.r)
        s = self.src[sflat[:, None] + self.offs[None, :]]  # (n, P, 4)
        d = ((self.t_feat[sel] - s) ** 2).sum(axis=(1, 2))
        if self.g > 0:
            e = ((self.t_guide[sel] - s[..., :3]) ** 2).sum(axis=2) * self.t_ghole[sel]
            d = d + self.g * e.sum(axis=1)
        return d / self.P

    def candidate(self, sy: np.ndarray, sx: np.ndarray, sel: np.ndarray | None = None):
        """Try source centres (sy, sx) for targets ``sel`` (default all); keep improvements."""
        if sel is None:
            sel = np.arange(self.N)
        ok = (sy >= 0) & (sy < self.h) & (sx >= 0) & (sx < self.w)
        ok[ok] = self.valid[sy[ok], sx[ok]]
        if not ok.any():
            return
        sel, sy, sx = sel[ok], sy[ok], sx[ok]
        c = self.cost(sel, sy, sx)
        better = c < self.d[sel]
        if better.any():
            b = sel[better]
            self.ny[b] = sy[better]
            self.nx[b] = sx[better]
            self.d[b] = c[better]

    def init_nnf(self, ny: np.ndarray, nx: np.ndarray, rng: np.random.Generator) -> None:
        """Set the NNF (random valid source where ny/nx are invalid) and compute its costs."""
        ok = (ny >= 0) & (ny < self.h) & (nx >= 0) & (nx < self.w)
        ok[ok] = self.valid[ny[ok], nx[ok]]
        k = rng.integers(0, self.n_valid, size=self.N)
        self.ny = np.where(ok, ny, self.vy[k]).astype(np.int64)
        self.nx = np.where(ok, nx, self.vx[k]).astype(np.int64)
        self.d = self.cost(np.arange(self.N), self.ny, self.nx)

    def refresh_costs(self) -> None:
        self.d = self.cost(np.arange(self.N), self.ny, self.nx)

    def patchmatch(self, rng: np.random.Generator, iters: int, n_random: int, max_radius: int | None = None) -> None:
        """PatchMatch sweeps. ``max_radius`` (levels initialised from a coarser NNF): local refinement
        only -- propagation jumps 1 and 2 and random search within ``max_radius`` -- plus the global
        random candidates; ``None``: jump-flood propagation and random search over the whole image."""
        jumps = []
        j = 1
        while j < max(self.h, self.w) and len(jumps) < (2 if max_radius else 4):
            jumps.append(j)
            j *= 2 if max_radius else 4
        for _ in range(iters):
            # propagation (parallel, jump-flood style): neighbour t+delta -> s_n - delta
            for jump in jumps:
                for ddy, ddx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                    oy, ox = ddy * jump, ddx * jump
                    py, px = self.ty + oy, self.tx + ox
                    inb = (py >= 0) & (py < self.h) & (px >= 0) & (px < self.w)
                    n = np.full(self.N, -1, np.int64)
                    n[inb] = self.tmap[py[inb], px[inb]]
                    sel = np.nonzero(n >= 0)[0]
                    if sel.size:
                        nb = n[sel]
                        self.candidate(self.ny[nb] - oy, self.nx[nb] - ox, sel)
            # random search around the current match with shrinking radius
            rad = max(self.h, self.w) if not max_radius else min(max(self.h, self.w), int(max_radius))
            while rad >= 1:
                off = rng.integers(-rad, rad + 1, size=(2, self.N))
                self.candidate(self.ny + off[0], self.nx + off[1])
                rad //= 2
            # global random candidates (escape local minima, find the right depth band)
            for _ in range(n_random):
                k = rng.integers(0, self.n_valid, size=self.N)
                self.candidate(self.vy[k], self.vx[k])

    def vote(self, mode: str = "weighted", sharp: float = 1.0) -> None:
        """Voting: every hole pixel from the overlapping matched source patches.

        ``weighted``: Wexler, weighted mean with weights exp(-(d - d_min(pixel)) / (2 sigma^2 sharp)) x
        exp(-dz^2 / 2), where d_min(pixel) is the best distance among the patches covering the pixel and
        dz the (scaled) depth difference of the voting source pixel and the target pixel;
        ``best``: the value from the covering patch with the lowest distance (no averaging).
        """
        r = self.r
        hy, hx = np.nonzero(self.hole)
        if mode == "best":
            # per pixel: the value from the covering patch with the lowest distance (no averaging)
            sflat = (self.ny + r) * self.wp + (self.nx + r)
            tidx = (self.tflat[:, None] + self.offs[None, :]).ravel()
            sidx = (sflat[:, None] + self.offs[None, :]).ravel()
            drep = np.repeat(self.d, self.P)
            order = np.lexsort((drep, tidx))  # by pixel, then distance
            first = np.ones(order.size, bool)
            first[1:] = tidx[order][1:] != tidx[order][:-1]
            pick = order[first]
            img = np.zeros((self.hp * self.wp, 3), np.float32)
            img[tidx[pick]] = self.src_rgb[sidx[pick]]
            img = img.reshape(self.hp, self.wp, 3)[r : r + self.h, r : r + self.w]
            self.canvas[hy, hx] = img[hy, hx]
            self.set_targets()
            return
        sigma2 = float(np.percentile(self.d, 75)) * sharp + 1e-8
        sflat = (self.ny + r) * self.wp + (self.nx + r)
        tidx = (self.tflat[:, None] + self.offs[None, :]).ravel()
        vals = self.src_rgb[(sflat[:, None] + self.offs[None, :]).ravel()]  # (N*P, 3)
        n_pad = self.hp * self.wp
        drep = np.repeat(self.d, self.P)
        dmin = np.full(n_pad, np.inf)
        np.minimum.at(dmin, tidx, drep)
        wrep = np.exp(-(drep - dmin[tidx]) / (2.0 * sigma2))
        # per-pixel depth agreement: a source pixel votes for a target pixel only at a similar depth
        dz = self.zpad[tidx] - self.src[(sflat[:, None] + self.offs[None, :]).ravel(), 3]
        wrep = wrep * np.exp(-0.5 * dz.astype(np.float64) ** 2) + 1e-300
        wsum = np.bincount(tidx, weights=wrep, minlength=n_pad)
        acc = np.stack([np.bincount(tidx, weights=wrep * vals[:, c], minlength=n_pad) for c in range(3)], axis=-1)
        wsum = wsum.reshape(self.hp, self.wp)[r : r + self.h, r : r + self.w]
        acc = acc.reshape(self.hp, self.wp, 3)[r : r + self.h, r : r + self.w]
        ws = wsum[hy, hx]
        good = ws > 0
        self.canvas[hy[good], hx[good]] = (acc[hy[good], hx[good]] / ws[good, None]).astype(np.float32)
        self.set_targets()

    def nnf_maps(self) -> tuple[np.ndarray, np.ndarray]:
        my = np.full((self.h, self.w), -1, np.int64)
        mx = np.full((self.h, self.w), -1, np.int64)
        my[self.ty, self.tx] = self.ny
        mx[self.ty, self.tx] = self.nx
        return my, mx


# ----------------------------------------------------------------------------- the backend


def _auto_levels(hole: np.ndarray, r: int, opts: PatchOptions) -> int:
    from scipy.ndimage import distance_transform_edt

    inradius = float(distance_transform_edt(hole).max())
    n = 1 + max(0, math.ceil(math.log2(max(inradius, 1.0) / max(r, 1))))
    return n if opts.levels is None else opts.levels


class PatchInpainter(Inpainter):
    """Depth-aware exemplar (PatchMatch) inpainting; see the module docstring."""

    name = "patch"

    def __init__(self, **options):
        try:
            self.options = PatchOptions(**options).check()
        except TypeError as exc:
            raise CamoError(f"patch inpainter: {exc}") from None

    def _inpaint(self, image, mask, background, depth, strength, seed):
        opts = self.options
        rng = np.random.default_rng(seed)
        r = opts.patch_size // 2
        z = log_depth(depth, opts.sky_ratio)
        src = background.copy()
        src[mask] = 0.0  # never read; zeroed so nothing behind the object can leak
        ctx = image.copy()
        ctx[mask] = 0.0
        g = min((1.0 - strength) / strength, 100.0)  # SNR(t_start) with alpha_bar ~ 1 - strength

        # pyramid (index 0 = finest); stop when a level has too few source patches
        n_levels = _auto_levels(mask, r, opts)
        pyr = [(ctx, src, z, image, mask)]
        while len(pyr) < n_levels:
            c, s, zz, gd, m = pyr[-1]
            if min(m.shape) < 2 * (2 * r + 1):
                break
            m2 = _down_any(m)
            if int(_valid_sources(m2, r).sum()) < opts.min_sources or m2.all():
                break
            pyr.append((_down(c), _down(s), _down(zz), _down(gd), m2))

        if int(_valid_sources(mask, r).sum()) < opts.min_sources:
            # no room for whole patches outside the hole: smooth fill only
            fill = telea_fill(ctx, mask)
            return renoise_mix(image, fill, strength, opts.detail_sigma)

        valid_px = ~mask
        var_rgb = float(src[valid_px].var(axis=0).mean()) if valid_px.sum() > 1 else 0.0
        var_rgb = max(var_rgb, 1e-4)

        telea_full = telea_fill(ctx, mask)
        prev = None
        for li in range(len(pyr) - 1, -1, -1):
            c, s, zz, gd, m = pyr[li]
            canvas = c.copy()
            if prev is None:
                canvas[m] = telea_fill(c, m)[m] if li > 0 else telea_full[m]
            else:
                up = np.repeat(np.repeat(prev.canvas, 2, axis=0), 2, axis=1)[: m.shape[0], : m.shape[1]]
                canvas[m] = up[m]
            lvl = _Level(canvas, s, zz, gd, m, r, var_rgb, opts, g)
            if prev is None:
                ny = np.full(lvl.N, -1, np.int64)
                nx = np.full(lvl.N, -1, np.int64)
            else:
                my, mx = prev.nnf_maps()
                cy, cx = lvl.ty // 2, lvl.tx // 2
                py, px = my[cy, cx], mx[cy, cx]
                has = py >= 0
                ny = np.where(has, 2 * py + (lvl.ty & 1), -1)
                nx = np.where(has, 2 * px + (lvl.tx & 1), -1)
            lvl.init_nnf(ny, nx, rng)
            radius = None if prev is None else opts.refine_radius  # global search only on the coarsest level
            n_em = opts.em_iters_fine if li == 0 else opts.em_iters_coarse
            for it in range(n_em):
                lvl.patchmatch(rng, opts.pm_iters, opts.random_candidates, radius)
                mode = opts.final_vote if (li == 0 and it == n_em - 1) else opts.vote
                lvl.vote(mode, opts.vote_sharpness)
                lvl.refresh_costs()
            prev = lvl

        synth = prev.canvas
        # low-texture areas: lean on the smooth Telea fill where it agrees with the local synthesised mean
        if opts.flat_std > 0:
            import cv2

            luma = synth @ REC709_LUMA
            std = _local_std(luma.astype(np.float32), 2)
            w_flat = np.clip(1.0 - std / opts.flat_std, 0.0, 1.0)
            local_mean = cv2.blur(synth, (5, 5), borderType=cv2.BORDER_REFLECT)
            agree = np.exp(-((telea_full - local_mean) ** 2).sum(axis=-1) / (2 * 0.02**2))
            wt = (w_flat * agree)[..., None]
            synth = synth + wt * (telea_full - synth)
        return renoise_mix(image, synth, strength, opts.detail_sigma)
