"""Stage 2, physically-grounded synthesis (paper Sec. III-C, Eq. 12-14).

Each iteration takes the next training view ``i`` (views cycle in a fixed
order), renders the current result (path tracer), gamma-encodes it (Eq. 12,
``x^(1/2.2)``), and inpaints the object's visible silhouette ``M_i`` starting
from that render with a bounded strength ``t_start``, conditioned on the
background render and its exact depth (Eq. 13). The inpainted image is kept as
the pseudo ground truth of view ``i`` — it replaces an older one — and the BSDF
maps and displacement take one Adam step on the MSE between the sRGB renders
and the pseudo ground truths of every view that has one (Eq. 14). Because each
new pseudo ground truth is inpainted from a render that already carries the
edits made for earlier views, the views are made consistent one after another
(the paper's multi-view argument). The pose stays as Stage 1 left it.

The objective stays Eq. 11 with Eq. 14 as its photometric term: the displacement
regulariser L_disp = E|D| (Eq. 5) remains on, because Eq. 14 redefines only
L_photo (the paper leaves this open). ``log.jsonl`` reports both terms.

The MSE is taken inside Stage 1's loss domain (the object and its shadow);
outside the silhouette the pseudo ground truth equals the render it came from,
so that part acts as a keep-as-is term.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from camo_base import seeds
from optimizer.optimise.stage1 import Stage1

GAMMA = 2.2


@dataclasses.dataclass
class Stage2Settings:
    """Stage 2's settings as a run spec records them (``[stage2]`` of a run's config.toml)."""

    iterations: int = 20  # paper
    strength: float = 0.5  # t_start as a fraction of the schedule (diffusers) / blend for the patch backend
    backend: str = "patch"  # "patch" (offline) or "diffusers"
    prompt: str = "background"
    displacement: bool = True  # paper: "refine the BSDF maps (and displacement)"; False keeps Stage 1's map
    sdxl_path: str | None = None
    controlnet_path: str | None = None


@dataclasses.dataclass
class Stage2Config(Stage2Settings):
    """What a :class:`Stage2` runs with: its settings plus the preview spp the run spec holds with the others."""

    preview_spp: int = 16  # spp of the render each pseudo ground truth is inpainted from (spp.stage2_preview)


def gamma_encode_np(x: np.ndarray) -> np.ndarray:
    """Eq. 12 on linear radiance, clipped to [0, 1] first."""
    return np.power(np.clip(np.nan_to_num(x, nan=0.0), 0.0, 1.0), 1.0 / GAMMA).astype(np.float32)


def gamma_encode_dr(img):
    """Eq. 12 in Dr.Jit, differentiable; clamped below at 1e-4 where the power's slope blows up.

    Values are clipped at 1 like the 8-bit images, but over-exposed pixels (a specular glint of a light) keep
    the slope of ``x^(1/2.2)`` as a straight-through gradient: a hard clip would give them zero gradient, and
    the MSE to a pseudo ground truth in [0, 1] could never dim them."""
    import drjit as dr

    img = dr.select(dr.isfinite(img), img, 0.0)
    enc = dr.power(dr.maximum(img, 1e-4), 1.0 / GAMMA)
    return dr.select(img > 1.0, 1.0 + (enc - dr.detach(enc)), enc)


class Stage2(Stage1):
    STAGE = 2

    def __init__(self, *args, stage2: Stage2Config, inpainter, **kwargs):
        super().__init__(*args, **kwargs)
        self.s2 = stage2
        self.inpainter = inpainter
        self.pseudo: dict[int, Any] = {}
        self.pseudo_np: dict[int, np.ndarray] = {}
        self.inputs_np: dict[int, np.ndarray] = {}  # the gamma-encoded renders each pseudo-GT started from
        self.inpaint_seconds: list[float] = []

    def views_for_step(self) -> list[int]:
        return sorted(self.pseudo)

    def next_view(self) -> int:
        return self.iteration % len(self.cams)

    def make_pseudo_gt(self, view: int) -> np.ndarray:
        """Inpaint view ``view`` of the current result (sRGB, Eq. 12-13) and keep it as its target."""
        import mitsuba as mi

        from optimizer.assets.result import Result, render_result

        res = Result(self.pack, self.env, [self.cams[view]], self.geometry, self.current_values(), self.app,
                     self.shading_integrator(), self.s2.preview_spp, None)
        current = render_result(res, seed=seeds.seed("stage2_render", self.cfg.seed, iteration=self.iteration))[0]
        self.inputs_np[view] = gamma_encode_np(current)
        mask = self.targets.coverage[view] >= 0.5
        t0 = time.perf_counter()
        out = self.inpainter.inpaint(gamma_encode_np(current), mask, gamma_encode_np(self.targets.background[view]),
                                     self.targets.depth[view], self.s2.strength,
                                     seeds.seed("stage2_inpaint", self.cfg.seed, iteration=self.iteration))
        self.inpaint_seconds.append(time.perf_counter() - t0)
        out = np.clip(np.asarray(out, dtype=np.float32), 0.0, 1.0)
        self.pseudo_np[view] = out
        self.pseudo[view] = mi.TensorXf(np.ascontiguousarray(self.window(view, out)))
        return out

    def _batch_loss(self, img, views: list[int]):
        """Per-view MSE to each view's pseudo ground truth, averaged over ``views`` (batch film)."""
        import mitsuba as mi

        W = self.cams[0].width
        total = mi.Float(0.0)
        for v in views:
            lv, _ = self._view_loss(img[:, v * W:(v + 1) * W, :], v)
            total += lv / len(views)
        return total, None

    def _view_loss(self, img, view: int):
        import drjit as dr

        diff = gamma_encode_dr(img) - self.pseudo[view]
        sq = dr.square(diff)
        w = self._w[view]
        if w is None:
            return dr.mean(sq.array), None
        import mitsuba as mi

        wt = mi.TensorXf(np.repeat(w[..., None], 3, axis=-1))
        return dr.sum((sq * wt).array) / max(float(np.sum(w)) * 3.0, 1e-12), None

    def step(self) -> dict[str, Any]:
        t0 = time.perf_counter()
        view = self.next_view()
        self.make_pseudo_gt(view)
        rec = super().step()  # times the gradient step only
        rec["view_inpainted"] = view
        rec["seconds_inpaint"] = self.inpaint_seconds[-1]
        rec["seconds_total"] = time.perf_counter() - t0
        self.elapsed += rec["seconds_total"] - rec["seconds"]  # the schedule's clock counts the pseudo-GT too
        rec["views_with_pseudo_gt"] = len(self.pseudo)
        return rec


    def checkpoint_state(self) -> dict[str, np.ndarray]:
        st = super().checkpoint_state()
        for v, img in self.pseudo_np.items():
            st[f"pseudo/{v}"] = img
            st[f"pseudo_input/{v}"] = self.inputs_np[v]
        return st

    def load_checkpoint_state(self, st: dict[str, np.ndarray]) -> None:
        import mitsuba as mi

        super().load_checkpoint_state(st)
        for key in st:
            if key.startswith("pseudo/"):
                v = int(key.split("/")[1])
                self.pseudo_np[v] = st[key]
                self.inputs_np[v] = st[f"pseudo_input/{v}"]
                self.pseudo[v] = mi.TensorXf(np.ascontiguousarray(self.window(v, st[key])))


def pseudo_gt_strip(stage: Stage2, view: int) -> np.ndarray:
    """sRGB strip: background | the render the pseudo-GT started from | the pseudo ground truth."""
    return np.concatenate([gamma_encode_np(stage.targets.background[view]), stage.inputs_np[view],
                           stage.pseudo_np[view]], axis=1)
