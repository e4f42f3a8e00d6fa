"""A simulated observer of the click-to-find study: how likely, and how fast, a person finds the object.

Weight-free, NumPy/SciPy only. Input: the stimulus a participant sees, an sRGB image ``(H, W, 3)`` float32 in
``[0, 1]`` (or uint8). The observer sees **only the image**; the object's mask ``(H, W)`` bool is used afterwards,
to score where the simulated participant clicked (exactly as the study site hit-tests a click).

The model, and what it follows
------------------------------

1. **Discriminability map** (target-distractor discriminability, Rosenholtz 1999 "A simple saliency model
   predicts a number of motion popout phenomena", Vision Res. 39; Rosenholtz, Li & Nakano 2007 "Measuring visual
   clutter", JoV 7(2)): at every place, a feature vector -- CIE L*a*b* colour (luminance and the two opponent
   channels) and the local energy of the luminance in four orientations (steerable second derivatives of a
   Gaussian, Freeman & Adelson 1991; texture / orientation contrast) -- pooled over a small centre, and its
   Mahalanobis distance from the distribution of the same features in a wide Gaussian surround (mean and full
   covariance, plus an internal-noise variance on the diagonal: a just-noticeable colour difference). This is
   the "background statistics it may learn from the rest of the image": distance in units of the background's
   own variability. Computed at several centre scales (Itti, Koch & Niebur 1998 "A model of saliency-based visual
   attention for rapid scene analysis", PAMI 20: centre-surround at several scales); each scale's map is turned
   into a z-score against the image's own distribution of distances (median and MAD: a place is salient if its
   difference is unusual *for this image*, in the spirit of Itti-Koch's map normalisation and of
   self-information saliency, Bruce & Tsotsos 2006), and the scales are combined by the maximum (the observer
   uses the most informative scale). The result ``D`` is in d' units; it is pooled (max) into cells of
   ``cell_deg`` degrees, the candidate places of the search.
2. **Search** (Najemnik & Geisler 2005 "Optimal eye movement strategies in visual search", Nature 434; 2009
   "Simple summation rule for optimal fixation selection in visual search", Vision Res. 49): the first fixation
   is at the image centre (central fixation bias at onset, Tatler 2007). At each fixation every cell is seen
   with a visibility that falls with eccentricity ``e`` as ``v(e) = 1 / (1 + e / e2_deg)`` (the E2 form of
   peripheral sensitivity, Levi, Klein & Aitsebaomo 1985), plus Gaussian noise per look:
   ``W = v(e) D + N(0, look_noise^2)``.
   * **Detection**: if some cell's ``W`` beats the criterion (``criterion``, d' units), the observer clicks the
     best such cell (at the peak of ``D`` smoothed over a cell: inside what it found, not on its edge). The
     functional field of view is not a fixed radius: a cell is detectable out to the eccentricity where
     ``v(e) D`` reaches the criterion, so an easy object is seen from far and a camouflaged one only near
     fixation (Hulleman & Olivers 2017 "The impending demise of the item in visual search", BBS 40). A click on
     a salient background spot is a miss, as in the study.
   * **Next fixation** (MAP rule of Najemnik & Geisler 2009, Itti-Koch winner-take-all): the cell with the
     highest ``W`` minus inhibition of return (Klein 2000 "Inhibition of return", TICS 4; Itti & Koch 2001):
     every past fixation subtracts ``ior_strength * exp(-d^2 / 2 ior_radius_deg^2)``.
3. **Time**: ``fixation_s`` per fixation (about 4 fixations per second in scene search, Rayner 1998
   "Eye movements in reading and information processing", Psych. Bull. 124; Henderson 2003), then a mouse
   movement by Fitts' law ``a + b log2(d / w + 1)`` from the image centre to the click (Soukoreff & MacKenzie
   2004: mouse throughput about 4-5 bit/s). A click later than ``time_limit_s`` (the site's 40 s) is a timeout.

Every default is justified next to it in :class:`ObserverConfig`. The model is **not fitted to human data**
(none exists here): its predictions rank stimuli and methods; absolute rates and times are indicative only.

Outputs: :func:`simulate_search` (per simulated trial: click, time, found), :func:`predict_stimulus` (probability
found, search-time distribution), :func:`predict_eval_dir` (every render of a ``camo evaluate`` directory) and
:func:`predicted_table` (per method, in the shape of the study's Table I).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from camo_base import seeds
from camo_base.errors import CamoError


@dataclass(frozen=True)
class ObserverConfig:
    """The observer's parameters (units in the names: ``_deg`` visual degrees, ``_s`` seconds)."""

    #: Height of the displayed image in visual degrees. The site shows it at 72 % of the viewport height: 576 CSS
    #: px of an 800 px window, ~150 mm on a laptop at ~60 cm is ~14 deg; 680 px on a 24" desktop ~18 deg.
    display_deg: float = 16.0
    #: Resolution of the feature maps (pixels per degree). 10 px/deg resolves 5 cycles/deg: the band that
    #: matters for finding a 1.5-5 deg object in peripheral vision; finer detail is only seen at the fovea.
    feature_px_per_deg: float = 10.0
    #: Centre scales (Gaussian sigma, degrees): from texture-element size to a fifth of the smallest object the
    #: study shows (10 % of the frame width = 1.6 deg).
    centre_sigmas_deg: tuple[float, ...] = (0.15, 0.3, 0.6)
    #: Surround (Gaussian sigma, degrees): wide enough that an object (1.6-4.8 deg in the study) is a minority of
    #: it, local enough that two kinds of ground (the split scene) have their own statistics.
    surround_sigma_deg: float = 4.0
    #: Internal noise, standard deviation per feature in CIE L*a*b* units: one just-noticeable difference,
    #: Delta E*ab ~ 2.3 (Mahy, Van Eycken & Oosterlinck 1994; Sharma 2003). It keeps a flat background from
    #: making any difference infinitely discriminable.
    internal_noise: float = 2.3
    #: Floor of the per-image spread (MAD, Mahalanobis units) used to z-score a map: one internal-noise unit, so
    #: a flat image does not turn noise into salience.
    spread_floor: float = 1.0
    #: Candidate cell size (degrees): about the foveal radius; the grid the search runs on.
    cell_deg: float = 0.5
    #: Eccentricity (degrees) at which discriminability halves. E2 for pattern and contrast tasks is ~1-3 deg
    #: (Levi et al. 1985); Najemnik & Geisler's visibility maps fall by half within ~2-4 deg.
    e2_deg: float = 2.0
    #: Standard deviation of the noise of one look (d' units). D already holds the internal noise (a JND on every
    #: feature); this is the extra fixation-to-fixation variability of the decision. At 0.5 a background place
    #: with D = 2 (a typical textured image's 99th percentile) passes the criterion with p = 0.13 % per look,
    #: while 1.0 made the observer click a background spot at its first fixation on a plain grass texture.
    look_noise: float = 0.5
    #: Detection criterion (d'): a look's W above it is taken for the object. 3.5 keeps a background cell at
    #: D = 0 below it with probability 1 - 2.3e-4 per look (about one false alarm in 4 s of looking at 1,000
    #: cells), the conservative criterion of a participant told there is always an object and paid to find it.
    criterion: float = 3.5
    #: Seconds per fixation, saccade included: 180-275 ms mean fixation in scene search (Rayner 1998) plus
    #: ~30 ms per saccade, i.e. about 4 fixations per second.
    fixation_s: float = 0.25
    #: Inhibition of return: spatial sigma (degrees; about the attended region, Itti & Koch 2001) and strength
    #: (d'; larger than any background D, so a place is rarely fixated twice, as in search of static scenes).
    ior_radius_deg: float = 1.0
    ior_strength: float = 6.0
    #: Fitts' law of the click (Shannon form): intercept (s) and slope (s/bit); mouse throughput ~4-5 bit/s
    #: (Soukoreff & MacKenzie 2004) gives ~0.2 s/bit, intercepts 0.1-0.3 s. The cursor starts at the image
    #: centre; the target width is ``fitts_width_deg`` (the observer does not know the object's size).
    fitts_a_s: float = 0.2
    fitts_b_s: float = 0.2
    fitts_width_deg: float = 1.0
    #: The study site's time limit per trial (TRIAL_TIME_LIMIT_S).
    time_limit_s: float = 40.0
    #: First fixation: "centre" (study stimuli: the object is placed at random) or "random" (uniform; for the
    #: evaluation renders, whose object sits at the image centre).
    start: str = "centre"
    #: Optional learned map instead of step 1: a local TorchScript file (``torch.jit.save``) of a saliency or
    #: camouflaged-object-detection network, ``(1, 3, H, W)`` sRGB in [0, 1] -> ``(1, 1, h, w)`` (or ``(1, h, w)``)
    #: scores, higher = more conspicuous. Its output is resized to the feature grid and z-scored like the
    #: weight-free map (median / MAD of the image). Never downloaded; "" = the weight-free map.
    saliency_model: str = ""

    def validate(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "start":
                if v not in ("centre", "random"):
                    raise CamoError(f"observer start must be 'centre' or 'random', not {v!r}")
                continue
            if f.name == "saliency_model":
                if v and not Path(v).expanduser().is_file():
                    raise CamoError(f"observer saliency_model: file not found: {v}")
                continue
            vals = v if isinstance(v, tuple) else (v,)
            if not vals or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in vals):
                raise CamoError(f"observer {f.name} must be finite numbers, not {v!r}")
            if f.name != "fitts_a_s" and any(x <= 0 for x in vals):
                raise CamoError(f"observer {f.name} must be > 0, not {v!r}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["centre_sigmas_deg"] = list(self.centre_sigmas_deg)
        if self.saliency_model:
            from evaluation.metrics.weights import weights_sha256

            d["saliency_model_sha256"] = weights_sha256(self.saliency_model)
        return d


# --------------------------------------------------------------------------------------------------------------
# discriminability
# --------------------------------------------------------------------------------------------------------------


def _as_srgb(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or a.shape[0] < 8 or a.shape[1] < 8:
        raise CamoError(f"observer: expected an (H, W, 3) image of at least 8x8 px, got shape {a.shape}")
    a = a[..., :3]
    if a.dtype == np.uint8:
        return a.astype(np.float32) / 255.0
    a = a.astype(np.float32)
    if not np.isfinite(a).all() or a.min() < -1e-3 or a.max() > 1 + 1e-3:
        raise CamoError("observer: image values must be finite sRGB in [0, 1]")
    return np.clip(a, 0.0, 1.0)


def srgb_to_lab(srgb: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] ``(..., 3)`` -> CIE L*a*b* (D65), float32: L* in [0, 100], a*, b* roughly [-100, 100]."""
    c = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    m = np.array([[0.4124564, 0.3575761, 0.1804375],
                  [0.2126729, 0.7151522, 0.0721750],
                  [0.0193339, 0.1191920, 0.9503041]], np.float64)
    xyz = c.astype(np.float64) @ m.T / np.array([0.95047, 1.0, 1.08883])
    d = 6.0 / 29.0
    f = np.where(xyz > d ** 3, np.cbrt(xyz), xyz / (3 * d * d) + 4.0 / 29.0)
    lab = np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)
    return lab.astype(np.float32)


def _resample(img: np.ndarray, scale: float) -> np.ndarray:
    """Resize ``(H, W, C)`` by ``scale`` (anti-aliased when shrinking)."""
    from scipy import ndimage

    if abs(scale - 1.0) < 1e-6:
        return img
    if scale < 1.0:
        img = ndimage.gaussian_filter(img, (0.5 / scale, 0.5 / scale, 0), mode="reflect")
    h, w = img.shape[:2]
    oh, ow = max(8, int(round(h * scale))), max(8, int(round(w * scale)))
    return ndimage.zoom(img, (oh / h, ow / w, 1), order=1, mode="nearest", grid_mode=True)


def _features(lab: np.ndarray, sigma_c: float) -> np.ndarray:
    """``(7, h, w)``: L*, a*, b* pooled over the centre, and 4 oriented energies (L* units) at that scale."""
    from scipy import ndimage

    g = lambda x, s: ndimage.gaussian_filter(x, s, mode="reflect")  # noqa: E731
    st = max(0.7, sigma_c / 2.0)
    L = lab[..., 0]
    lxx = ndimage.gaussian_filter(L, st, order=(0, 2), mode="reflect") * st * st
    lyy = ndimage.gaussian_filter(L, st, order=(2, 0), mode="reflect") * st * st
    lxy = ndimage.gaussian_filter(L, st, order=(1, 1), mode="reflect") * st * st
    feats = [g(lab[..., k], sigma_c) for k in range(3)]
    for th in (0.0, math.pi / 4, math.pi / 2, 3 * math.pi / 4):
        c, s = math.cos(th), math.sin(th)
        r = c * c * lxx + 2 * c * s * lxy + s * s * lyy
        feats.append(np.sqrt(g(r * r, sigma_c)))
    return np.stack(feats).astype(np.float64)


def _distance(f: np.ndarray, mu: np.ndarray, cov: np.ndarray, noise: float) -> np.ndarray:
    """Mahalanobis distance of ``f`` ``(k, h, w)`` from mean ``mu`` and covariance ``cov`` ``(k, k, h, w)`` (or
    ``(k,)`` / ``(k, k)`` for one distribution), internal noise ``noise``^2 added to the variances."""
    k = f.shape[0]
    diff = np.moveaxis(f - mu.reshape(mu.shape + (1, 1)[: f.ndim - mu.ndim]), 0, -1)[..., None]
    c = cov.copy()
    c[range(k), range(k)] = np.maximum(c[range(k), range(k)], 0.0) + noise * noise
    if c.ndim > 2:
        c = np.moveaxis(c, (0, 1), (-2, -1))
    sol = np.linalg.solve(np.broadcast_to(c, diff.shape[:-2] + (k, k)), diff)
    return np.sqrt(np.maximum((diff * sol).sum(axis=(-2, -1)), 0.0))


#: Share of the image left out of the background statistics as outliers (the object covers at most ~10 % of a
#: study stimulus; one-step reweighting as in Rousseeuw's reweighted MCD estimator).
TRIM = 0.10


def _mahalanobis(f: np.ndarray, sigma_s: float, noise: float) -> np.ndarray:
    """Distance of each place's features from the background distribution of its Gaussian-weighted surround.

    The background statistics are robust: the places whose features are global outliers (the top :data:`TRIM`
    of the distances from the whole image's mean and covariance) are left out of every surround, so a large
    object does not become its own background. Where a surround is almost all outliers, the whole image's
    trimmed statistics fill in."""
    from scipy import ndimage

    k = f.shape[0]
    flat = f.reshape(k, -1)
    m0 = _distance(f, flat.mean(1), np.cov(flat), noise)
    w = (m0 <= np.quantile(m0, 1.0 - TRIM)).astype(np.float64)
    fw = flat[:, w.reshape(-1) > 0]
    mu_g, cov_g = fw.mean(1), np.cov(fw)
    eps = 0.05  # weight of the whole image's trimmed statistics in every surround
    g = lambda x: ndimage.gaussian_filter(x, sigma_s, mode="reflect")  # noqa: E731
    den = g(w) + eps
    mu = np.stack([(g(w * f[i]) + eps * mu_g[i]) / den for i in range(k)])
    cov = np.empty((k, k) + f.shape[1:])
    for i in range(k):
        for j in range(i, k):
            second = (g(w * f[i] * f[j]) + eps * (cov_g[i, j] + mu_g[i] * mu_g[j])) / den
            cov[i, j] = cov[j, i] = second - mu[i] * mu[j]
    return _distance(f, mu, cov, noise)


_MODELS: dict[tuple, Any] = {}


def load_saliency_model(path: str | Path):
    """A TorchScript saliency network from a local file (cached by path, size and modification time)."""
    import torch

    p = Path(path).expanduser()
    if not p.is_file():
        raise CamoError(f"observer saliency_model: file not found: {p}")
    st = p.stat()
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _MODELS:
        try:
            m = torch.jit.load(str(p), map_location="cpu")
        except Exception as exc:  # torch raises RuntimeError / ValueError / pickle errors for a bad file
            raise CamoError(f"observer saliency_model {p}: not a TorchScript file "
                            f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
        m.eval()
        _MODELS[key] = m
    return _MODELS[key]


def _zscore(m: np.ndarray, floor: float) -> np.ndarray:
    med = float(np.median(m))
    return (m - med) / max(1.4826 * float(np.median(np.abs(m - med))), floor)


def learned_map(srgb: np.ndarray, config: ObserverConfig) -> np.ndarray:
    """``D`` from the TorchScript network of ``config.saliency_model`` at the feature resolution (z-scored)."""
    import torch

    from scipy import ndimage

    scale = config.display_deg * config.feature_px_per_deg / srgb.shape[0]
    img = _resample(srgb, scale)
    model = load_saliency_model(config.saliency_model)
    x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None].float()
    try:
        with torch.no_grad():
            y = model(x)
    except Exception as exc:  # a network that does not take this input
        raise CamoError(f"observer saliency_model: the network failed on a {img.shape[1]}x{img.shape[0]} image "
                        f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    y = np.asarray(y.detach().cpu().numpy(), np.float64).squeeze()
    if y.ndim != 2 or not np.isfinite(y).all():
        raise CamoError(f"observer saliency_model: expected one finite (h, w) map, got shape {tuple(y.shape)}")
    h, w = img.shape[:2]
    y = ndimage.zoom(y, (h / y.shape[0], w / y.shape[1]), order=1, mode="nearest", grid_mode=True)[:h, :w]
    return _zscore(y, 1e-6 + 1e-3 * float(np.std(y))).astype(np.float32)


def discriminability_map(image: np.ndarray, config: ObserverConfig | None = None) -> np.ndarray:
    """The observer's discriminability ``D`` (d' units, float32) at the feature resolution, ``(h, w)`` with
    ``h = display_deg * feature_px_per_deg``. See the module docstring (step 1); with ``saliency_model`` the
    learned network's map (:func:`learned_map`) instead."""
    cfg = config or ObserverConfig()
    srgb = _as_srgb(image)
    if cfg.saliency_model:
        return learned_map(srgb, cfg)
    scale = cfg.display_deg * cfg.feature_px_per_deg / srgb.shape[0]
    lab = srgb_to_lab(_resample(srgb, scale))
    ppd = cfg.feature_px_per_deg
    out = None
    for sc in cfg.centre_sigmas_deg:
        m = _mahalanobis(_features(lab, sc * ppd), cfg.surround_sigma_deg * ppd, cfg.internal_noise)
        z = _zscore(m, cfg.spread_floor)
        out = z if out is None else np.maximum(out, z)
    return out.astype(np.float32)


@dataclass
class Cells:
    """The search grid of one image: cell centres and click points, in degrees and in image pixels."""

    d: np.ndarray  # (C,) discriminability of each cell (max over its feature pixels), d'
    pos_deg: np.ndarray  # (C, 2) cell centre (x, y) in degrees from the image's top-left corner
    click_px: np.ndarray  # (C, 2) int: (x, y) image pixel the observer clicks in this cell (peak of D smoothed)
    width_deg: float
    height_deg: float
    image_shape: tuple[int, int]


def make_cells(image: np.ndarray, config: ObserverConfig | None = None) -> Cells:
    """The search grid of ``image`` (sRGB ``(H, W, 3)``): :func:`discriminability_map` pooled (max) into cells of
    ``cell_deg``, each with its centre in degrees and the image pixel a click on it lands on."""
    cfg = config or ObserverConfig()
    srgb = _as_srgb(image)
    H, W = srgb.shape[:2]
    dmap = discriminability_map(srgb, cfg)
    h, w = dmap.shape
    n = max(1, int(round(cfg.cell_deg * cfg.feature_px_per_deg)))
    ch, cw = math.ceil(h / n), math.ceil(w / n)
    from scipy import ndimage

    def blocks_of(m: np.ndarray) -> np.ndarray:
        pad = np.full((ch * n, cw * n), -np.inf, np.float32)
        pad[:h, :w] = m
        return pad.reshape(ch, n, cw, n).transpose(0, 2, 1, 3).reshape(ch, cw, n * n)

    d = blocks_of(dmap).max(-1)
    # the click goes to the cell's peak of D smoothed over a cell: inside the discriminable region rather than on
    # its edge (texture energy peaks at an object's outline; people click inside what they found)
    arg = blocks_of(ndimage.gaussian_filter(dmap, n / 2.0, mode="reflect")).argmax(-1)
    iy, ix = np.mgrid[0:ch, 0:cw]
    fy = iy * n + arg // n
    fx = ix * n + arg % n
    sy, sx = H / h, W / w
    click = np.stack([np.clip(((fx + 0.5) * sx).astype(int), 0, W - 1),
                      np.clip(((fy + 0.5) * sy).astype(int), 0, H - 1)], -1)
    ppd = cfg.feature_px_per_deg
    cy = np.minimum((iy + 0.5) * n, h - 0.5) / ppd
    cx = np.minimum((ix + 0.5) * n, w - 0.5) / ppd
    return Cells(d.reshape(-1).astype(np.float64), np.stack([cx, cy], -1).reshape(-1, 2), click.reshape(-1, 2),
                 w / ppd, h / ppd, (H, W))


# --------------------------------------------------------------------------------------------------------------
# search
# --------------------------------------------------------------------------------------------------------------


@dataclass
class SearchResult:
    """``n`` simulated trials of one stimulus. Arrays have shape ``(n,)``."""

    clicked: np.ndarray  # bool: the observer clicked within the time limit
    timed_out: np.ndarray  # bool: no click within the limit
    click_x: np.ndarray  # int image pixel column of the click (-1 when timed out)
    click_y: np.ndarray  # int image pixel row (-1 when timed out)
    rt_s: np.ndarray  # float seconds from onset to the click; the time limit for a timeout
    fixations: np.ndarray  # int fixations made
    found: np.ndarray | None = None  # bool: the click hit the mask (None without a mask)


def simulate_search(image: np.ndarray | None, n: int = 200, seed: int = 0, config: ObserverConfig | None = None,
                    mask: np.ndarray | None = None, cells: Cells | None = None) -> SearchResult:
    """Simulate ``n`` independent searches of ``image`` (sRGB ``(H, W, 3)``); score clicks against ``mask``
    (``(H, W)`` bool, optional; never seen by the observer). Deterministic for a given ``seed``. ``cells``: the
    image's :func:`make_cells` when already computed (``image`` is then not read; the study client caches them)."""
    cfg = config or ObserverConfig()
    cfg.validate()
    if n < 1:
        raise CamoError(f"observer: n must be >= 1, got {n}")
    cells = cells if cells is not None else make_cells(image, cfg)
    rng = np.random.default_rng(seed)
    D, pos = cells.d, cells.pos_deg
    C = len(D)
    if cfg.start == "centre":
        fix = np.tile([cells.width_deg / 2, cells.height_deg / 2], (n, 1))
    else:
        fix = rng.uniform([0, 0], [cells.width_deg, cells.height_deg], (n, 2))
    t = np.zeros(n)
    ior = np.zeros((n, C))
    clicked = np.zeros(n, bool)
    done = np.zeros(n, bool)
    click_cell = np.full(n, -1)
    rt = np.full(n, cfg.time_limit_s)
    nfix = np.zeros(n, int)
    centre = np.array([cells.width_deg / 2, cells.height_deg / 2])
    max_steps = int(math.ceil(cfg.time_limit_s / cfg.fixation_s)) + 1
    for _ in range(max_steps):
        act = np.flatnonzero(~done)
        if act.size == 0:
            break
        t[act] += cfg.fixation_s
        nfix[act] += 1
        over = t[act] > cfg.time_limit_s  # this fixation would end after the limit: timeout
        done[act[over]] = True
        act = act[~over]
        if act.size == 0:
            break
        e = np.sqrt(((pos[None, :, :] - fix[act, None, :]) ** 2).sum(-1))  # (a, C) eccentricity, deg
        w = D[None, :] / (1.0 + e / cfg.e2_deg) + cfg.look_noise * rng.standard_normal((act.size, C))
        best = w.argmax(1)
        hit = w[np.arange(act.size), best] > cfg.criterion
        if hit.any():
            a = act[hit]
            dist = np.sqrt(((pos[best[hit]] - centre) ** 2).sum(-1))
            motor = cfg.fitts_a_s + cfg.fitts_b_s * np.log2(dist / cfg.fitts_width_deg + 1.0)
            when = t[a] + motor
            ok = when <= cfg.time_limit_s
            clicked[a[ok]] = True
            click_cell[a[ok]] = best[hit][ok]
            rt[a[ok]] = when[ok]
            done[a] = True
        keep = ~hit
        if keep.any():
            a = act[keep]
            ior[a] += np.exp(-(e[keep] ** 2) / (2 * cfg.ior_radius_deg ** 2))
            nxt = (w[keep] - cfg.ior_strength * ior[a]).argmax(1)
            fix[a] = pos[nxt]
    cx = np.where(clicked, cells.click_px[np.maximum(click_cell, 0), 0], -1)
    cy = np.where(clicked, cells.click_px[np.maximum(click_cell, 0), 1], -1)
    res = SearchResult(clicked, ~clicked, cx, cy, np.where(clicked, rt, cfg.time_limit_s), nfix)
    if mask is not None:
        m = np.asarray(mask).astype(bool)
        if m.shape != cells.image_shape:
            raise CamoError(f"observer: mask is {m.shape[1]}x{m.shape[0]} but the image is "
                            f"{cells.image_shape[1]}x{cells.image_shape[0]}")
        res.found = clicked & m[np.maximum(cy, 0), np.maximum(cx, 0)]
    return res


@dataclass
class StimulusPrediction:
    """What the observer predicts for one stimulus."""

    p_found: float  # probability of a correct click within the limit
    p_miss: float  # a click off the object
    p_timeout: float  # no click within the limit
    rt_found_s: np.ndarray  # search times of the simulated finds (seconds): the distribution
    rt_all_s: np.ndarray  # time on trial of every simulated trial (timeouts at the limit, misses at the click)
    result: SearchResult
    max_d_object: float  # the largest D on the object (d'); how discriminable its best part is
    time_limit_s: float = 40.0

    def summary(self) -> dict[str, float]:
        f = self.rt_found_s
        return {"p_found": self.p_found, "p_miss": self.p_miss, "p_timeout": self.p_timeout,
                "mean_time_found_s": float(f.mean()) if f.size else math.nan,
                "median_time_found_s": float(np.median(f)) if f.size else math.nan,
                "mean_time_all_s": float(self.rt_all_s.mean()), "median_time_all_s": float(np.median(self.rt_all_s)),
                "mean_time_to_find_s": float(self.time_to_find_s.mean()),
                "median_time_to_find_s": float(np.median(self.time_to_find_s)), "max_d_object": self.max_d_object}

    @property
    def time_to_find_s(self) -> np.ndarray:
        """Time to find per simulated trial, misses and timeouts at the time limit (the study's Kaplan-Meier
        convention ``miss_censor="limit"``): the search time that only grows as an object gets harder to find."""
        return np.where(self.result.found, self.result.rt_s, self.time_limit_s)


def predict_stimulus(image: np.ndarray, mask: np.ndarray, n: int = 200, seed: int = 0,
                     config: ObserverConfig | None = None) -> StimulusPrediction:
    """Probability found and the search-time distribution of one stimulus (``n`` simulated trials)."""
    cfg = config or ObserverConfig()
    cfg.validate()
    cells = make_cells(image, cfg)
    res = simulate_search(image, n, seed, cfg, mask, cells)
    m = np.asarray(mask).astype(bool)
    on = m[cells.click_px[:, 1], cells.click_px[:, 0]]
    return StimulusPrediction(float(res.found.mean()), float((res.clicked & ~res.found).mean()),
                              float(res.timed_out.mean()), res.rt_s[res.found], res.rt_s.copy(), res,
                              float(cells.d[on].max()) if on.any() else math.nan, cfg.time_limit_s)


# --------------------------------------------------------------------------------------------------------------
# evaluation directories and Table I
# --------------------------------------------------------------------------------------------------------------

#: Columns of the per-view prediction table (``simulated.parquet`` of an evaluation directory).
PREDICTION_COLUMNS = ("run", "scene", "object", "method", "ablation", "view", "width", "height", "n", "p_found",
                      "p_miss", "p_timeout", "mean_time_found_s", "median_time_found_s", "mean_time_all_s",
                      "median_time_all_s", "mean_time_to_find_s", "median_time_to_find_s", "max_d_object",
                      "mask_pixels")
#: Columns of the per-simulated-trial table (``simulated_trials.parquet``; the input of ``camo study power``).
TRIAL_COLUMNS = ("run", "scene", "method", "ablation", "view", "trial", "found", "timed_out", "rt_s",
                 "time_limit_s")


def _read_rgb(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def _read_mask(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("L")) >= 128


def predict_entries(entries: Sequence[dict[str, Any]], root: Path, n: int = 200, seed: int = 0,
                    config: ObserverConfig | None = None):
    """Predictions for renders.json-style entries (paths relative to ``root``): ``(per view, per trial)``
    DataFrames with :data:`PREDICTION_COLUMNS` / :data:`TRIAL_COLUMNS`. Views whose mask is empty are skipped."""
    import pandas as pd

    cfg = config or ObserverConfig()
    rows, trials = [], []
    for k, e in enumerate(entries):
        try:
            img_p, mask_p = root / str(e["image"]), root / str(e["mask"])
        except KeyError as exc:
            raise CamoError(f"{root}: a renders.json entry lacks {exc}") from None
        if not img_p.is_file() or not mask_p.is_file():
            raise CamoError(f"{root}: missing render {img_p if not img_p.is_file() else mask_p}")
        img, mask = _read_rgb(img_p), _read_mask(mask_p)
        if mask.shape != img.shape[:2]:
            raise CamoError(f"{mask_p}: mask size differs from its image")
        if not mask.any():
            continue
        p = predict_stimulus(img, mask, n, seeds.seed("observer", seed, stimulus=k), cfg)
        ident = {c: e.get(c, "") for c in ("run", "scene", "object", "method", "ablation")}
        ident["ablation"] = str(ident["ablation"] or "none")
        rows.append({**ident, "view": int(e.get("view", 0)), "width": img.shape[1], "height": img.shape[0], "n": n,
                     **p.summary(), "mask_pixels": int(mask.sum())})
        r = p.result
        for i in range(n):
            trials.append((ident["run"], ident["scene"], ident["method"], ident["ablation"], int(e.get("view", 0)),
                           i, bool(r.found[i]), bool(r.timed_out[i]), float(r.rt_s[i]), cfg.time_limit_s))
    return (pd.DataFrame(rows, columns=list(PREDICTION_COLUMNS)),
            pd.DataFrame(trials, columns=list(TRIAL_COLUMNS)))


def predict_eval_dir(eval_dir: str | Path, n: int = 200, seed: int = 0, config: ObserverConfig | None = None,
                     write: bool = True):
    """Run the observer on every render of a ``camo evaluate`` directory (its ``renders.json``). With ``write``,
    store ``simulated.parquet`` / ``.csv`` (per view) and ``simulated_trials.parquet`` (per simulated trial)
    and ``simulated_config.json`` there (atomically). Returns ``(per view, per trial)`` DataFrames."""
    import json

    from camo_base import atomic

    root = Path(eval_dir)
    p = root / "renders.json"
    if not p.is_file():
        raise CamoError(f"{root}: no renders.json (is this an evaluation directory from `camo evaluate`?)")
    try:
        entries = json.loads(p.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise CamoError(f"{p}: not valid JSON ({exc})") from None
    if not isinstance(entries, list):
        raise CamoError(f"{p}: expected a list")
    cfg = config or ObserverConfig(start="random")
    views, trials = predict_entries(entries, root, n, seed, cfg)
    if write:
        with atomic.atomic_path(root / "simulated.parquet") as tmp:
            views.to_parquet(tmp, index=False)
        with atomic.atomic_path(root / "simulated.csv") as tmp:
            views.to_csv(tmp, index=False)
        with atomic.atomic_path(root / "simulated_trials.parquet") as tmp:
            trials.to_parquet(tmp, index=False)
        atomic.write_json(root / "simulated_config.json", {"observer": cfg.to_dict(), "trials_per_view": n,
                                                          "seed": seed})
    return views, trials


def predicted_table(views, by: Sequence[str] = ("method",), trials=None):
    """Table I predicted from per-view predictions (``views``: :data:`PREDICTION_COLUMNS`), per ``by`` group.

    Every view weighs the same (as a scene x method cell of the study does). ``confusion_rate`` = 1 - mean
    p_found; ``p_miss`` / ``p_timeout`` the two ways of not finding. Times: over the simulated finds
    (``mean/median_time_found_s``) and over all trials (timeouts at the limit), from ``trials`` (per simulated
    trial) when given, else the means of the per-view figures. ``easy_views``: views found with p >= 0.95 within
    a median of 2 s (candidates to fix or drop)."""
    import pandas as pd

    out = []
    for key, g in views.groupby(list(by), sort=True):
        key = key if isinstance(key, tuple) else (key,)
        row = dict(zip(by, key))
        row.update(n_views=len(g), n_scenes=int(g["scene"].nunique()), confusion_rate=1.0 - float(g["p_found"].mean()),
                   p_miss=float(g["p_miss"].mean()), p_timeout=float(g["p_timeout"].mean()))
        if trials is not None and len(trials):
            t = trials
            for c, v in row.items():
                if c in by:
                    t = t[t[c] == v]
            f = t.loc[t["found"], "rt_s"]
            row.update(mean_time_found_s=float(f.mean()) if len(f) else math.nan,
                       median_time_found_s=float(f.median()) if len(f) else math.nan,
                       mean_time_all_s=float(t["rt_s"].mean()), median_time_all_s=float(t["rt_s"].median()))
        else:
            row.update(mean_time_found_s=float(g["mean_time_found_s"].mean()),
                       median_time_found_s=float(g["median_time_found_s"].median()),
                       mean_time_all_s=float(g["mean_time_all_s"].mean()),
                       median_time_all_s=float(g["median_time_all_s"].median()))
        row["easy_views"] = int(((g["p_found"] >= 0.95) & (g["median_time_found_s"] <= 2.0)).sum())
        out.append(row)
    return pd.DataFrame(out)
