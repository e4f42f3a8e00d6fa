"""GANmouflage (Guo, Collins, de Lima, Owens, CVPR 2023): a texture field trained per scene, in torch.

Re-implemented from the paper and the authors' published code
(``rrrrrguo/ganmouflage``: ``model_v4/modules/{texture_model,decoder,patch}.py``,
``trainer/training.py``, ``configs/config_final_4view.yaml``); where the paper
leaves a detail open we do what that code does. Nothing is copied.

Texture field
-------------
The colour of a surface point ``p`` (sRGB in [0, 1]) is an MLP of

* an embedding of ``p`` in object coordinates (``(p - centre) /
  bounding-box diagonal``): the final configuration's ``fixed_sincos`` (NeRF
  sin/cos encoding with 10 octaves plus the input, 63 numbers; the paper
  preset) or the decoder's other option ``cips_learnable`` (``sin(W p)``,
  ``W`` a trained 128 x 3 matrix drawn from U(+-sqrt(3)), zero bias; the
  default, fast preset -- see "What to expect"), and
* for each of ``n_ref = 4`` reference views (evenly spaced over the training
  views; the 4-view configuration): image features sampled bilinearly at
  ``p``'s projection from several scales of an image encoder run on the
  reference background, concatenated with the surface normal and the
  direction of the ray from that reference camera to ``p``, both in the
  reference camera's frame (``cat_surface_normals: True``). Reference
  features are sampled without an occlusion test, as in the original.

MLP (``decoder.py``): ``first_fc`` (63 -> h1) on the encoding; 3 residual
blocks at width ``h1`` whose input is offset by a linear projection of the
per-view features (``fc1(act(x + W z))``, ``fc2`` initialised to zero,
LeakyReLU 0.2); **mean pooling over the reference views**; 3 residual blocks
to width ``h2``; LeakyReLU; linear to RGB; sigmoid.

Image encoder -- the one deliberate difference. The original uses an
ImageNet-pretrained ResNet-18 U-Net (fine-tuned jointly); no pretrained
weights are available offline, so a small randomly initialised U-Net
(16/32/64 channels, 3 scales, trained jointly with the MLP) is used; its
output maps at full, 1/2 and 1/4 resolution plus the (ImageNet-normalised)
image itself are sampled and concatenated.

Rendering during training
-------------------------
As GANmouflage's own image-space renderer: for a view, the object's visible
pixels (ray cast with 4x4 rays per pixel against the full scene, so occluders
are respected -- the original assumes the object is never occluded) get the
mean surface point of their object rays; the field's colours are composited
over the sRGB-encoded background render with the pixel's object coverage as
alpha (the original replaces its foreground pixels outright). Everything is in
torch and differentiable w.r.t. the field and the encoder.

Losses and training (``trainer/training.py``)
-------------------------------------------
* Perceptual L1 on crops around the object (``compute_pix_loss``,
  ``pix_ren_type = perceptual``): the composited image and the background are
  cropped with the same random window around the object's bounding box
  (side ``crop_size`` = 128 px times sqrt of a scale in [0.8, 1.25], aspect in
  [0.8, 1.25], centre offset up to +-10 % of the window; clamped to the image)
  and resized to 128 x 128; L1 between their features at 4 scales, summed.
  The original uses VGG-16 (relu1_2 ... relu4_3, ImageNet weights); offline we
  use a fixed multi-scale filter bank instead (:class:`FilterBankFeatures`:
  opponent colour, Gaussian, oriented first derivatives and a Laplacian at 4
  octaves, half-wave rectified), which measures local colour and edge
  structure at the same scales but knows nothing about objects.
  Weights: ``w_pix_ren = 1`` on supervision views, ``w_pix_ref = 1`` on the
  reference views themselves.
* Adversarial patch loss on the supervision views, ``w_gan_ren = 0.5``,
  standard (BCE) GAN. Discriminator (``patch.py``): 4 stride-2 4x4 convs
  (64-128-256-512 channels, LeakyReLU 0.2, instance norm after the 2nd-4th),
  a final 4x4 conv to one logit map. Real samples: random resized crops of
  background renders (area 80-100 % of the image, aspect 0.8-1.25); fake:
  crops around the object in composited images. Both get a random
  rot90/flip with probability 0.5 and are scaled to [-1, 1] for the D step.
* Adam, ``lr_g = 2e-4``, ``lr_d = 1e-4``, betas (0.5, 0.99), linear warm-up
  of both learning rates over ``lr_warmup`` (200) steps, gradient-norm clip 5.
  Per iteration one discriminator step and one generator step.

Differences in the training loop, made for a per-scene, fixed-object setting
(all settable on :class:`GanmouflageConfig`):

* the original trains on random object poses and scales in one scene
  (``train_rot_limit``, ``train_cube_scale_range``) with batches of 2 samples x
  (2 supervision + 4 reference) views; here the object and its 16 training
  views are fixed, so an iteration renders ``n_sup`` supervision views (drawn
  from the non-reference training views) and ``n_ref_sup`` reference views;
* the discriminator step reuses this iteration's composited images (detached)
  instead of rendering the fake images a second time.

Presets: ``GanmouflageConfig.paper()`` -- 8,000 iterations, widths 256/128,
``fixed_sincos`` embedding, 4 supervision + 4 reference renders per iteration (``--method
ganmouflage-paper``; hours on a CPU). The default ``GanmouflageConfig()`` is
sized for about one to three minutes on 2 CPU cores at the built-in scenes'
128 px: 300 iterations, widths 128/64, ``cips_learnable`` embedding, 1 + 1 renders per iteration, warm-up
30 steps, generator learning rate x5 (1e-3; the discriminator keeps 1e-4)
to make up for the ~25x fewer iterations (about 0.2-0.25 s per iteration at 96 px on 2
idle cores; torch's two OpenMP threads slow down several-fold when the cores
are shared -- ``--threads`` also sets torch's thread count).
``--iterations N`` overrides the iteration count of either preset.

What to expect: the reconstruction (perceptual) term alone drives the field to
the local mean colour of the background. With ``fixed_sincos`` and 300
iterations (no pretrained encoder, so weak image features), the discriminator
wins (its loss falls to ~0.03) and the generator answers with the encoding's
high octaves: each octave varies along one object axis only, so the baked atlas
shows axis-aligned plaid (gravel, in the all-scenes grid; also at the
original generator learning rate 2e-4). The fast preset therefore uses
``cips_learnable``: its frequencies start low (entries of ``W`` at most
sqrt(3) rad per diagonal) and point in random directions, so the colour varies smoothly over
the surface and the texture comes from the reference-view features. Measured
on gravel (8 views, 96 px, 8 novel views, object crop): PSNR 25.63 -> 25.91,
SSIM 0.821 -> 0.836, LPIPS-proxy 0.423 -> 0.417, SIFID-proxy 0.0068 both;
the other built-in scenes are in ``docs/results/README.md``. The paper preset
(8,000 iterations) keeps the final configuration's ``fixed_sincos``.

Bake
----
After training the field is evaluated at every texel's surface point (same
projection into the reference views), the sRGB colours are decoded to linear
and turned into albedo like the painting baselines (global white level,
:mod:`optimizer.optimise.baselines.common`), and written through ``write_result``, so
the result is re-rendered physically like every other method.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from camo_base import imaging, seeds
from optimizer.scenes.cameras import Camera
from optimizer.rendering import projection
from optimizer.optimise.baselines.common import Setup, painted_values, to_albedo
from optimizer.optimise.method import Method

# --------------------------------------------------------------------------- config


@dataclasses.dataclass
class GanmouflageConfig:
    iterations: int = 300
    n_ref: int = 4
    n_sup: int = 1
    n_ref_sup: int = 1
    hidden_1: int = 128
    hidden_2: int = 64
    layers_1: int = 3
    layers_2: int = 3
    pe_octaves: int = 10
    embedder: str = "cips_learnable"  # or "fixed_sincos" (the paper preset); both are in the authors' decoder.py
    pe_dim: int = 128  # width of the "cips_learnable" embedding
    encoder_channels: tuple[int, int, int] = (16, 32, 64)
    disc_channels: int = 64
    crop_size: int = 128
    crop_scale: tuple[float, float] = (0.8, 1.25)
    crop_ratio: tuple[float, float] = (0.8, 1.25)
    crop_offset: float = 0.1
    real_crop_scale: tuple[float, float] = (0.8, 1.25)  # fraction of the image area (clipped at 1)
    lr_g: float = 1e-3
    lr_d: float = 1e-4
    betas: tuple[float, float] = (0.5, 0.99)
    lr_warmup: int = 30
    w_pix_ren: float = 1.0
    w_pix_ref: float = 1.0
    w_gan_ren: float = 0.5
    max_grad_norm: float = 5.0
    flip_prob: float = 0.5
    supersample: int = 4  # rays per pixel side for the object's pixels (coverage and points)
    bake_chunk: int = 16384
    albedo_mode: str = "global"
    visibility_eps: float = 0.01  # only for albedo_mode "local"
    threads: int | None = None
    preset: str = "fast"

    @classmethod
    def paper(cls, **kw) -> "GanmouflageConfig":
        base = dict(iterations=8000, n_sup=4, n_ref_sup=4, hidden_1=256, hidden_2=128, lr_g=2e-4, lr_d=1e-4,
                    lr_warmup=200, embedder="fixed_sincos", preset="paper")
        base.update(kw)
        return cls(**base)


# --------------------------------------------------------------------------- networks


def _torch():
    import torch

    return torch


def _f(t) -> float:
    return float(t.detach()) if hasattr(t, "detach") else float(t)


def positional_encoding(x, octaves: int):
    """NeRF encoding: ``[x, sin(2^k x), cos(2^k x)]`` for k = 0..octaves-1 (``3 + 6 * octaves`` numbers)."""
    torch = _torch()
    out = [x]
    for k in range(octaves):
        f = 2.0 ** k
        out += [torch.sin(f * x), torch.cos(f * x)]
    return torch.cat(out, -1)


def build_networks(cfg: GanmouflageConfig, z_dim: int):
    """``(encoder, field, discriminator)`` torch modules."""
    torch = _torch()
    nn = torch.nn
    F = torch.nn.functional

    class ResBlock(nn.Module):
        def __init__(self, din: int, dout: int):
            super().__init__()
            self.fc1 = nn.Linear(din, dout)
            self.fc2 = nn.Linear(dout, dout)
            self.skip = nn.Linear(din, dout) if din != dout else None
            nn.init.kaiming_normal_(self.fc1.weight, a=0.2, mode="fan_in")
            nn.init.zeros_(self.fc1.bias)
            nn.init.zeros_(self.fc2.weight)
            nn.init.zeros_(self.fc2.bias)

        def forward(self, x, z=None):
            h = x if z is None else x + z
            h = self.fc2(F.leaky_relu(self.fc1(F.leaky_relu(h, 0.2)), 0.2))
            return h + (x if self.skip is None else self.skip(x))

    if cfg.embedder not in ("fixed_sincos", "cips_learnable"):
        raise ValueError(f"GanmouflageConfig.embedder must be fixed_sincos or cips_learnable, got {cfg.embedder!r}")

    class Field(nn.Module):
        def __init__(self):
            super().__init__()
            if cfg.embedder == "cips_learnable":  # decoder.py: Linear(3, pe_dim), U(+-sqrt(9 / 3)), bias 0, then sin
                self.pe = nn.Linear(3, cfg.pe_dim)
                nn.init.uniform_(self.pe.weight, -math.sqrt(9 / 3), math.sqrt(9 / 3))
                nn.init.zeros_(self.pe.bias)
                pe_dim = cfg.pe_dim
            else:
                self.pe = None
                pe_dim = 3 + 6 * cfg.pe_octaves
            self.first = nn.Linear(pe_dim, cfg.hidden_1)
            nn.init.kaiming_normal_(self.first.weight, a=0.2, mode="fan_in")
            nn.init.zeros_(self.first.bias)
            self.blocks1 = nn.ModuleList([ResBlock(cfg.hidden_1, cfg.hidden_1) for _ in range(cfg.layers_1)])
            self.zproj = nn.ModuleList([nn.Linear(z_dim, cfg.hidden_1) for _ in range(cfg.layers_1)])
            self.blocks2 = nn.ModuleList([ResBlock(cfg.hidden_1 if i == 0 else cfg.hidden_2, cfg.hidden_2)
                                          for i in range(cfg.layers_2)])
            self.last = nn.Linear(cfg.hidden_2, 3)

        def forward(self, x, z):
            """``x (K, 3)`` object coordinates, ``z (n_ref, K, z_dim)`` -> sRGB colours ``(K, 3)``."""
            pe = torch.sin(self.pe(x)) if self.pe is not None else positional_encoding(x, cfg.pe_octaves)
            h = self.first(pe).unsqueeze(0)  # (1, K, h1)
            h = h.expand(z.shape[0], -1, -1)
            for blk, proj in zip(self.blocks1, self.zproj):
                h = blk(h, proj(z))
            h = h.mean(0)  # pool over the reference views
            for blk in self.blocks2:
                h = blk(h)
            return torch.sigmoid(self.last(F.leaky_relu(h, 0.2)))

    c0, c1, c2 = cfg.encoder_channels

    def conv(i, o, s=1):
        return nn.Sequential(nn.Conv2d(i, o, 3, s, 1), nn.LeakyReLU(0.2))

    class Encoder(nn.Module):
        """A small U-Net trained jointly (stands in for the pretrained ResNet-18 U-Net)."""

        mean = (0.485, 0.456, 0.406)
        std = (0.229, 0.224, 0.225)

        def __init__(self):
            super().__init__()
            self.e0 = nn.Sequential(conv(3, c0), conv(c0, c0))
            self.e1 = nn.Sequential(conv(c0, c1, 2), conv(c1, c1))
            self.e2 = nn.Sequential(conv(c1, c2, 2), conv(c2, c2))
            self.d1 = conv(c2 + c1, c1)
            self.d0 = conv(c1 + c0, c0)
            self.register_buffer("m", torch.tensor(self.mean).view(1, 3, 1, 1))
            self.register_buffer("s", torch.tensor(self.std).view(1, 3, 1, 1))

        def forward(self, img):
            x = (img - self.m) / self.s
            a = self.e0(x)
            b = self.e1(a)
            c = self.e2(b)
            d1 = self.d1(torch.cat([F.interpolate(c, size=b.shape[-2:], mode="bilinear", align_corners=False), b], 1))
            d0 = self.d0(torch.cat([F.interpolate(d1, size=a.shape[-2:], mode="bilinear", align_corners=False), a], 1))
            return [x, d0, d1, c]

    nh = cfg.disc_channels
    disc = nn.Sequential(
        nn.Conv2d(3, nh, 4, 2, 1, bias=False), nn.LeakyReLU(0.2),
        nn.Conv2d(nh, 2 * nh, 4, 2, 1, bias=False), nn.InstanceNorm2d(2 * nh), nn.LeakyReLU(0.2),
        nn.Conv2d(2 * nh, 4 * nh, 4, 2, 1, bias=False), nn.InstanceNorm2d(4 * nh), nn.LeakyReLU(0.2),
        nn.Conv2d(4 * nh, 8 * nh, 4, 2, 1, bias=False), nn.InstanceNorm2d(8 * nh), nn.LeakyReLU(0.2),
        nn.Conv2d(8 * nh, 1, 4, 1, 0, bias=False),
    )
    return Encoder(), Field(), disc


def encoder_channels(cfg: GanmouflageConfig) -> int:
    c0, c1, c2 = cfg.encoder_channels
    return 3 + c0 + c1 + c2


class FilterBankFeatures:
    """Fixed multi-scale filter-bank features for the perceptual loss (replaces VGG-16; no weights needed).

    Per octave (1, 1/2, 1/4, 1/8 of the crop; 2x2 average pooling between):
    opponent colour ``(lum, R-G, (R+G)/2-B)``; Gaussian blur (sigma 1) of the 3
    channels; derivative-of-Gaussian at 4 orientations on luminance and 2 on
    each chroma channel; a Laplacian of Gaussian on luminance; each response
    split into positive and negative parts (ReLU), 24 maps per octave.
    ``loss(x, y)`` = sum over octaves of the mean L1 difference (as the
    original sums ``F.l1_loss`` over 4 VGG layers).
    """

    def __init__(self, octaves: int = 4, sigma: float = 1.0):
        torch = _torch()
        r = 2
        ax = np.arange(-r, r + 1, dtype=np.float64)
        yy, xx = np.meshgrid(ax, ax, indexing="ij")
        g = np.exp(-(xx ** 2 + yy ** 2) / (2 * sigma ** 2))
        g /= g.sum()
        filt = []  # (out, in) pairs
        for c in range(3):
            filt.append((g, c))
        for ang in (0, 45, 90, 135):
            t = math.radians(ang)
            d = -(math.cos(t) * xx + math.sin(t) * yy) / sigma ** 2 * g
            filt.append((d / np.abs(d).sum(), 0))
        for c in (1, 2):
            for ang in (0, 90):
                t = math.radians(ang)
                d = -(math.cos(t) * xx + math.sin(t) * yy) / sigma ** 2 * g
                filt.append((d / np.abs(d).sum(), c))
        log = ((xx ** 2 + yy ** 2) / sigma ** 4 - 2 / sigma ** 2) * g
        log -= log.mean()
        filt.append((log / np.abs(log).sum(), 0))
        w = np.zeros((len(filt), 3, 2 * r + 1, 2 * r + 1), np.float32)
        for i, (k, c) in enumerate(filt):
            w[i, c] = k
        self.weight = torch.from_numpy(w)
        self.opp = torch.tensor([[1 / 3, 1 / 3, 1 / 3], [1.0, -1.0, 0.0], [0.5, 0.5, -1.0]], dtype=torch.float32)
        self.octaves = octaves
        self.scale = [torch.ones(1, 2 * len(filt), 1, 1) for _ in range(octaves)]

    def _raw(self, x):
        torch = _torch()
        F = torch.nn.functional
        x = torch.einsum("oc,nchw->nohw", self.opp, x)
        out = []
        for k in range(self.octaves):
            if k:
                x = F.avg_pool2d(x, 2)
            r = F.conv2d(F.pad(x, (2, 2, 2, 2), mode="replicate"), self.weight)
            out.append(torch.cat([F.relu(r), F.relu(-r)], 1))
        return out

    def calibrate(self, images) -> "FilterBankFeatures":
        """Scale each octave to unit mean feature magnitude over ``images (N, 3, H, W)`` (the scene's backgrounds).

        VGG activations on ImageNet-normalised input are O(1); with this the
        loss has the magnitude the original weights (w_pix 1, w_gan 0.5) were set for.
        One factor per octave (not per channel: a grey scene's chroma channels
        are ~0 and would be blown up).
        """
        torch = _torch()
        with torch.no_grad():
            for k, f in enumerate(self._raw(images)):
                self.scale[k] = torch.full_like(self.scale[k], 1.0 / max(float(f.abs().mean()), 1e-6))
        return self

    def features(self, x):
        return [f * s for f, s in zip(self._raw(x), self.scale)]

    def loss(self, x, y):
        total = 0.0
        for a, b in zip(self.features(x), self.features(y)):
            total = total + (a - b).abs().mean()
        return total


# --------------------------------------------------------------------------- geometry of the field's inputs


@dataclasses.dataclass
class PointSet:
    """Surface points and what the field needs about them in every reference view (NumPy, float32)."""

    x: np.ndarray  # (K, 3) object coordinates
    grid: np.ndarray  # (n_ref, K, 2) grid_sample coordinates in each reference image
    geo: np.ndarray  # (n_ref, K, 6) normal and ray direction in each reference camera's frame


@dataclasses.dataclass
class ViewPixels:
    """The object's visible pixels in one view."""

    pix: np.ndarray  # (K,) flat pixel index
    alpha: np.ndarray  # (K,) coverage
    points: np.ndarray  # (K, 3) world
    normals: np.ndarray  # (K, 3) interpolated vertex normals
    bbox: tuple[int, int, int, int]  # y0, x0, y1, x1 (inclusive)


def object_frame(positions: np.ndarray) -> tuple[np.ndarray, float]:
    lo, hi = positions.min(0), positions.max(0)
    return ((lo + hi) / 2).astype(np.float64), float(np.linalg.norm(hi - lo))


def point_set(points: np.ndarray, normals: np.ndarray, refs: list[Camera], centre, diag) -> PointSet:
    x = ((np.asarray(points, np.float64) - centre) / diag).astype(np.float32)
    grids, geos = [], []
    for cam in refs:
        px, py, _ = projection.project(points, cam)
        grids.append(np.stack([2 * px / cam.width - 1, 2 * py / cam.height - 1], -1).astype(np.float32))
        ray = np.asarray(points, np.float64) - np.asarray(cam.origin, np.float64)
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        geos.append(np.concatenate([projection.to_camera(normals, cam), projection.to_camera(ray, cam)], 1))
    return PointSet(x, np.stack(grids), np.stack(geos).astype(np.float32))


def _barycentrics(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = np.where(np.abs(d00 * d11 - d01 * d01) < 1e-30, 1e-30, d00 * d11 - d01 * d01)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.clip(np.stack([1 - v - w, v, w], 1), 0.0, 1.0)


def view_pixels(setup: Setup, ss: int) -> list[ViewPixels]:
    """Ray-cast every view (``ss x ss`` rays per pixel, full scene): the object's visible pixels and points."""
    import mitsuba as mi

    from optimizer.rendering.render import camera_rays

    sc, shape = setup.visibility_scene()
    g = setup.geometry
    pos = setup.positions.astype(np.float64)
    nrm = np.asarray(g.normal, np.float64)
    out = []
    for cam in setup.cams:
        si = sc.ray_intersect(camera_rays(cam, ss))
        on = np.asarray(si.is_valid() & (si.shape == mi.ShapePtr(shape)), bool)
        p = np.stack([np.asarray(si.p[k], np.float64) for k in range(3)], 1)
        prim = np.asarray(si.prim_index, np.int64)
        n_sub = ss * ss
        on_px = on.reshape(-1, n_sub)
        cnt = on_px.sum(1)
        pix = np.flatnonzero(cnt > 0)
        hit = np.flatnonzero(on)
        f = g.faces[prim[hit]]
        bary = _barycentrics(p[hit], pos[f])
        nh = np.einsum("nk,nkc->nc", bary, nrm[f])
        owner = hit // n_sub
        psum = np.zeros((cam.width * cam.height, 3))
        nsum = np.zeros((cam.width * cam.height, 3))
        np.add.at(psum, owner, p[hit])
        np.add.at(nsum, owner, nh)
        pts = (psum[pix] / cnt[pix, None]).astype(np.float32)
        nn_ = nsum[pix]
        nn_ = (nn_ / np.maximum(np.linalg.norm(nn_, axis=1, keepdims=True), 1e-12)).astype(np.float32)
        ys, xs = pix // cam.width, pix % cam.width
        bbox = (int(ys.min()), int(xs.min()), int(ys.max()), int(xs.max())) if len(pix) else \
            (cam.height // 2, cam.width // 2, cam.height // 2, cam.width // 2)
        out.append(ViewPixels(pix, (cnt[pix] / n_sub).astype(np.float32), pts, nn_, bbox))
    return out


# --------------------------------------------------------------------------- crops


def crop_window(rng: np.random.Generator, h: int, w: int, bbox, cfg: GanmouflageConfig) -> tuple[float, float, float, float]:
    """A random window ``(y0, x0, hh, ww)`` around ``bbox`` (RandomResizedCropAroundTarget), clamped to the image."""
    s = cfg.crop_size * math.sqrt(rng.uniform(*cfg.crop_scale))
    r = math.exp(rng.uniform(math.log(cfg.crop_ratio[0]), math.log(cfg.crop_ratio[1])))
    ww, hh = min(w, s * math.sqrt(r)), min(h, s / math.sqrt(r))
    cy, cx = (bbox[0] + bbox[2] + 1) / 2, (bbox[1] + bbox[3] + 1) / 2
    y0 = cy - hh * (0.5 + rng.uniform(-cfg.crop_offset, cfg.crop_offset))
    x0 = cx - ww * (0.5 + rng.uniform(-cfg.crop_offset, cfg.crop_offset))
    return float(np.clip(y0, 0, h - hh)), float(np.clip(x0, 0, w - ww)), hh, ww


def real_window(rng: np.random.Generator, h: int, w: int, cfg: GanmouflageConfig) -> tuple[float, float, float, float]:
    """A random resized crop anywhere (kornia ``RandomResizedCrop``'s parameters: area fraction of the image, aspect ratio).

    The window is drawn here rather than by ``kornia.augmentation.RandomResizedCrop`` because kornia's generator
    draws from torch's global stream; drawing from the trainer's own NumPy stream keeps a run reproducible from its
    seed (``camo_base/seeds.py``) whatever else touched torch's RNG. Out-of-range sizes are clipped to the image
    instead of kornia's ten retries and centre-crop fallback. The crop itself is kornia's (:func:`crop`).
    """
    a = min(1.0, rng.uniform(*cfg.real_crop_scale))
    r = math.exp(rng.uniform(math.log(cfg.crop_ratio[0]), math.log(cfg.crop_ratio[1])))
    ww = min(w, math.sqrt(a * h * w * r))
    hh = min(h, math.sqrt(a * h * w / r))
    return float(rng.uniform(0, h - hh)), float(rng.uniform(0, w - ww)), hh, ww


def window_box(win: tuple[float, float, float, float], size: int) -> list[list[float]]:
    """Kornia's box ``(4, 2)`` (x, y corners, inclusive pixel positions) for a continuous window ``(y0, x0, hh, ww)``.

    The window is in continuous image coordinates (pixel ``i`` covers ``[i, i + 1)``); output pixel ``j`` of a
    ``size``-wide crop samples the window at ``x0 + (j + 0.5) * ww / size``, i.e. at pixel position that minus 0.5,
    so the first and last output pixels sit half an output pixel inside the window's edges.

    >>> window_box((0.0, 0.0, 4.0, 4.0), 4)
    [[0.0, 0.0], [3.0, 0.0], [3.0, 3.0], [0.0, 3.0]]
    """
    y0, x0, hh, ww = win
    sy, sx = hh / size, ww / size
    ya, yb = y0 + 0.5 * sy - 0.5, y0 + hh - 0.5 * sy - 0.5
    xa, xb = x0 + 0.5 * sx - 0.5, x0 + ww - 0.5 * sx - 0.5
    return [[xa, ya], [xb, ya], [xb, yb], [xa, yb]]


def crop(img, win, size: int):
    """Bilinear crop-and-resize of ``img (C, H, W)`` to ``(C, size, size)``, differentiable (kornia ``crop_and_resize``).

    Samples outside the image (a window reaching its edge, upsampled) take the border value. Equal to a hand-written
    ``grid_sample`` with ``align_corners=False`` within 2e-5; kornia's box solve costs 1.5-3 ms a crop against 0.2 ms
    (measured on these CPUs), i.e. 10-20 ms for the seven crops of a default step, small beside the step itself.
    """
    torch = _torch()
    from kornia.geometry.transform import crop_and_resize
    box = torch.tensor([window_box(win, size)], dtype=img.dtype)
    return crop_and_resize(img.unsqueeze(0), box, (size, size), mode="bilinear", padding_mode="border",
                           align_corners=True)[0]


def flip_rotate(x, rng: np.random.Generator, p: float):
    torch = _torch()
    if rng.random() >= p:
        return x
    x = torch.rot90(x, int(rng.integers(0, 4)), (1, 2))
    d = int(rng.integers(0, 3))
    return torch.flip(x, (d,)) if d else x


# --------------------------------------------------------------------------- training


class Trainer:
    """Per-scene GANmouflage training (see the module doc); :meth:`step` runs one iteration."""

    def __init__(self, setup: Setup, cfg: GanmouflageConfig, seed: int = 0):
        torch = _torch()
        if cfg.crop_size < 64:
            raise ValueError(f"crop_size must be >= 64 (the discriminator downsamples 16x, then a 4x4 conv), got {cfg.crop_size}")
        if cfg.threads:
            torch.set_num_threads(int(cfg.threads))
        torch.manual_seed(seed)
        self.setup, self.cfg = setup, cfg
        self.rng = np.random.default_rng(seed)
        V = len(setup.cams)
        n_ref = max(1, min(cfg.n_ref, V))
        self.refs = sorted({int(round(i * V / n_ref)) % V for i in range(n_ref)})
        self.sup = [v for v in range(V) if v not in self.refs] or list(self.refs)
        self.ref_cams = [setup.cams[v] for v in self.refs]
        self.centre, self.diag = object_frame(setup.positions)
        bg = imaging.linear_to_srgb(setup.targets.background)  # (V, H, W, 3)
        self.bg = torch.from_numpy(np.ascontiguousarray(bg.transpose(0, 3, 1, 2)))
        self.pixels = view_pixels(setup, cfg.supersample)
        self.inputs = [self._tensors(point_set(p.points, p.normals, self.ref_cams, self.centre, self.diag))
                       for p in self.pixels]
        z_dim = encoder_channels(cfg) + 6
        self.encoder, self.field, self.disc = build_networks(cfg, z_dim)
        self.features = FilterBankFeatures().calibrate(self.bg)
        gparams = list(self.encoder.parameters()) + list(self.field.parameters())
        self.opt_g = torch.optim.Adam(gparams, lr=cfg.lr_g, betas=cfg.betas)
        self.opt_d = torch.optim.Adam(self.disc.parameters(), lr=cfg.lr_d, betas=cfg.betas)
        self.iteration = 0
        self.history: list[dict[str, Any]] = []

    @staticmethod
    def _tensors(ps: PointSet):
        torch = _torch()
        return (torch.from_numpy(ps.x), torch.from_numpy(ps.grid), torch.from_numpy(ps.geo))

    def ref_features(self):
        return self.encoder(self.bg[self.refs])

    def colours(self, feats, inputs):
        """Field colours ``(K, 3)`` for precomputed point inputs ``(x, grid, geo)``."""
        torch = _torch()
        F = torch.nn.functional
        x, grid, geo = inputs
        z = [F.grid_sample(fm, grid.unsqueeze(1), mode="bilinear", padding_mode="zeros", align_corners=False)[:, :, 0]
             for fm in feats]  # (n_ref, C, K)
        z = torch.cat(z, 1).transpose(1, 2)  # (n_ref, K, C)
        return self.field(x, torch.cat([z, geo], -1))

    def render(self, feats, view: int):
        """The composited sRGB image ``(3, H, W)`` of ``view``."""
        torch = _torch()
        px = self.pixels[view]
        bg = self.bg[view]
        img = bg.reshape(3, -1).clone()
        if len(px.pix):
            col = self.colours(feats, self.inputs[view])  # (K, 3)
            idx = torch.from_numpy(px.pix)
            a = torch.from_numpy(px.alpha).unsqueeze(0)
            img[:, idx] = a * col.T + (1 - a) * img[:, idx]
        return img.reshape(bg.shape)

    def _lr_scale(self) -> float:
        w = self.cfg.lr_warmup
        return min(1.0, (self.iteration + 1) / w) if w > 0 else 1.0

    def step(self) -> dict[str, Any]:
        torch = _torch()
        F = torch.nn.functional
        cfg, rng = self.cfg, self.rng
        t0 = time.perf_counter()
        s = self._lr_scale()
        for gopt, lr in ((self.opt_g, cfg.lr_g), (self.opt_d, cfg.lr_d)):
            for pg in gopt.param_groups:
                pg["lr"] = lr * s
        sup = [int(v) for v in rng.choice(self.sup, size=min(cfg.n_sup, len(self.sup)), replace=False)]
        refs = [int(v) for v in rng.choice(self.refs, size=min(cfg.n_ref_sup, len(self.refs)), replace=False)]
        # --- generator step
        for p in self.disc.parameters():
            p.requires_grad_(False)
        self.opt_g.zero_grad(set_to_none=True)
        feats = self.ref_features()
        H, W = self.bg.shape[-2:]
        pix_ren = pix_ref = gan = torch.zeros(())
        fakes = []
        for group, views in (("ren", sup), ("ref", refs)):
            for v in views:
                img = self.render(feats, v)
                fakes.append((img.detach(), v))
                win = crop_window(rng, H, W, self.pixels[v].bbox, cfg)
                both = crop(torch.cat([img, self.bg[v]], 0), win, cfg.crop_size)
                lp = self.features.loss(both[:3].unsqueeze(0), both[3:].unsqueeze(0))
                if group == "ren":
                    pix_ren = pix_ren + lp / len(views)
                    if cfg.w_gan_ren > 0:
                        fc = crop(img, crop_window(rng, H, W, self.pixels[v].bbox, cfg), cfg.crop_size)
                        logits = self.disc((2 * fc - 1).unsqueeze(0))
                        gan = gan + F.binary_cross_entropy_with_logits(logits, torch.ones_like(logits)) / len(views)
                else:
                    pix_ref = pix_ref + lp / len(views)
        loss_g = cfg.w_pix_ren * pix_ren + cfg.w_pix_ref * pix_ref + cfg.w_gan_ren * gan
        loss_g.backward()
        gnorm = [p.grad for p in list(self.encoder.parameters()) + list(self.field.parameters()) if p.grad is not None]
        nonfinite = int(sum(int((~torch.isfinite(g)).sum()) for g in gnorm))
        if nonfinite:
            for g in gnorm:
                torch.nan_to_num_(g, nan=0.0, posinf=0.0, neginf=0.0)
        if cfg.max_grad_norm > 0:
            torch.nn.utils.clip_grad_norm_(list(self.encoder.parameters()) + list(self.field.parameters()), cfg.max_grad_norm)
        self.opt_g.step()
        # --- discriminator step (on this iteration's composites, detached)
        loss_d = torch.zeros(())
        if cfg.w_gan_ren > 0:
            for p in self.disc.parameters():
                p.requires_grad_(True)
            self.opt_d.zero_grad(set_to_none=True)
            fake = torch.stack([flip_rotate(crop(img, crop_window(rng, H, W, self.pixels[v].bbox, cfg), cfg.crop_size),
                                            rng, cfg.flip_prob) for img, v in fakes])
            real_views = rng.choice(len(self.bg), size=len(fakes), replace=True)
            real = torch.stack([flip_rotate(crop(self.bg[int(v)], real_window(rng, H, W, cfg), cfg.crop_size),
                                            rng, cfg.flip_prob) for v in real_views])
            lr_, lf = self.disc(2 * real - 1), self.disc(2 * fake - 1)
            loss_d = F.binary_cross_entropy_with_logits(lr_, torch.ones_like(lr_)) + \
                F.binary_cross_entropy_with_logits(lf, torch.zeros_like(lf))
            loss_d.backward()
            if cfg.max_grad_norm > 0:
                torch.nn.utils.clip_grad_norm_(self.disc.parameters(), cfg.max_grad_norm)
            self.opt_d.step()
        self.iteration += 1
        rec = {
            "iteration": self.iteration,
            "stage": 1,
            "loss": _f(loss_g),
            "loss_photo": _f(cfg.w_pix_ren * pix_ren + cfg.w_pix_ref * pix_ref),
            "loss_pix_render": _f(pix_ren),
            "loss_pix_ref": _f(pix_ref),
            "loss_gan_render": _f(gan),
            "loss_d": _f(loss_d),
            "lr_g": cfg.lr_g * s,
            "views": sup + refs,
            "seconds": time.perf_counter() - t0,
            "nonfinite_grads": nonfinite,
        }
        self.history.append(rec)
        return rec

    def bake_colours(self, surface: projection.TexelSurface):
        """sRGB colours ``(N, 3)`` of the field at every texel's surface point."""
        torch = _torch()
        out = np.zeros((len(surface), 3), np.float32)
        with torch.no_grad():
            feats = self.ref_features()
            for a in range(0, len(surface), self.cfg.bake_chunk):
                b = min(len(surface), a + self.cfg.bake_chunk)
                ps = point_set(surface.points[a:b], surface.shading_normals[a:b], self.ref_cams, self.centre, self.diag)
                out[a:b] = self.colours(feats, self._tensors(ps)).numpy()
        return out

    def render_all(self) -> np.ndarray:
        """Composited sRGB images ``(V, H, W, 3)`` of every training view (inspection, tests)."""
        torch = _torch()
        with torch.no_grad():
            feats = self.ref_features()
            return np.stack([self.render(feats, v).numpy().transpose(1, 2, 0) for v in range(len(self.pixels))])


def compute(setup: Setup, cfg: GanmouflageConfig | None = None, progress: bool = True):
    cfg = cfg or GanmouflageConfig()
    seed = seeds.seed("baseline", setup.seed)
    setup.say(f"ganmouflage: preparing the texture field's inputs ({cfg.preset} preset)")
    tr = Trainer(setup, cfg, seed)
    from tqdm import tqdm

    bar = tqdm(total=cfg.iterations, disable=not progress, desc="ganmouflage", unit="it")
    for _ in range(cfg.iterations):
        rec = tr.step()
        bar.set_postfix(g=f"{rec['loss']:.3f}", d=f"{rec['loss_d']:.3f}")
        bar.update(1)
    bar.close()
    setup.say("ganmouflage: baking the field into the albedo atlas")
    surf = setup.texel_surface()
    srgb = tr.bake_colours(surf)
    lin = imaging.srgb_to_linear(srgb)
    white = None
    if cfg.albedo_mode == "local":
        obs = setup.observe(surf, cfg.visibility_eps)
        w = obs.sample(setup.white_render())
        vis = obs.visible[..., None]
        white = np.where(obs.visible.any(0)[:, None], (w * vis).sum(0) / np.maximum(vis.sum(0), 1), setup.white_level())
    albedo = to_albedo(setup, lin, cfg.albedo_mode, white)
    values = painted_values(setup, projection.bake(surf, albedo, np.ones(len(surf), bool)))
    info = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items() if v is not None}
    info.update(reference_views=tr.refs, texels=len(surf))
    setup.trainer = tr
    return values, tr.history, info


#: The method of this module (collected by :mod:`optimizer.optimise.methods`): ``--iterations`` sets its training
#: iterations; ``ganmouflage-paper`` is the same method with :meth:`GanmouflageConfig.paper`.
METHODS = (Method("ganmouflage", "Guo et al. 2023: texture field, perceptual + adversarial losses (baselines.ganmouflage)",
                  options=GanmouflageConfig, compute=compute, option_names=(("iterations", "options.iterations"),),
                  variants=(("ganmouflage-paper", GanmouflageConfig.paper),)),)
