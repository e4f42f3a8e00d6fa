"""The camouflage appearance model (paper Sec. III-B): pose, anamorphic displacement, SV-BSDF.

Parameters (all optimised with Adam, all in Dr.Jit arrays):

=============== ================= =========================================================
name            shape             meaning
=============== ================= =========================================================
albedo          (R, R, 3)         the BSDF maps (:data:`optimizer.scenes.bsdf_maps.MAPS`: albedo
metallic        (R, R, 1)         linear base colour, metallic, roughness (map value; rendered with
roughness       (R, R, 1)         the safe minimum 0.035), transmittance = principled ``spec_trans``),
transmittance   (R, R, 1)         each in [0, 1]; paper start 0.5, 0, 0, 0.5
displacement    (Rd, Rd, 1)       d in [-1, 1]; D = d * bound, bound = displacement_bound *
                                  object size (scene units); v' = v + D(u) n (Eq. 4)
translation     (3,)              dt, clipped to +-translation_fraction * size; dz = 0
                                  unless allow_dz
rotation        (1,)              theta_z in radians
=============== ================= =========================================================

Model matrix (Eq. 3): ``T_new = T_dt T_t R_z(theta) R S``. Displacement is applied
on the *welded* mesh (xatlas seams split vertices; each welded vertex takes the
mean of D at its UV copies, so both sides of a seam move together and the
surface never cracks), then gathered to the UV-split render mesh.

Choices the paper leaves open: displacement is stored normalised by its
amplitude bound so the paper's learning rate 1e-1 means 10 % of the bound per
step; L_disp = E|d| on that normalised map; the bound defaults to 2 % of the
object's size (a fabrication limit); pose learning rates are 2e-3 scene units
(translation) and 1e-2 rad (rotation) per step.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from optimizer.scenes.bsdf_maps import MAPS
from optimizer.scenes.pose import euler_xyz_deg, model_matrix
from optimizer.rendering import scene as scn
from optimizer.scenes.scenepack import MaterialSpec, ObjectSpec


@dataclasses.dataclass
class AppearanceConfig:
    map_resolution: int = 800  # paper: 800 x 800
    displacement_resolution: int = 256
    displacement_bound: float = 0.02  # fraction of the object's size
    translation_fraction: float = 0.05  # paper: dt clipped to 5 % of the object's size
    allow_dz: bool = False  # paper: dz = 0 (stay on the ground)
    pose: bool = True
    displacement: bool = True
    bsdf: bool = True  # False: albedo only (a Lambertian surface)
    transmittance: bool = True  # False: transmittance forced to 0
    eta: float = 1.5
    lr_maps: float = 1e-2  # paper
    lr_displacement: float = 1e-1  # paper
    lr_translation: float = 2e-3
    lr_rotation: float = 1e-2
    displacement_weight: float = 1.0  # weight of L_disp (Eq. 11 uses 1)
    # > 0: after each Adam step, shrink d towards 0 by this fraction of the step's displacement rate (the proximal
    # step of an L1 term in Adam's normalised units; optimizer/optimise/schedule.py says why). 0 = the paper.
    displacement_shrink: float = 0.0
    # > 0: the displacement's rate ramps up linearly over this many Adam steps of each stage (optimizer/optimise/
    # adam.py says why: Adam's first step moves every texel by a full rate, whatever the gradient's size). 0 = paper.
    displacement_warmup: int = 0
    # > 0: each step, the BSDF maps' gradients are blurred by a Gaussian of this many texels (sigma) before Adam.
    # Adam normalises every texel's step, so at a few spp each texel of a noise-dominated map (metallic,
    # transmittance, roughness) random-walks by ~lr per step: salt-and-pepper maps that render as sparkles. A
    # blurred gradient keeps the smooth signal and averages the per-texel noise (a Sobolev-style preconditioner);
    # the drift left is smooth. 0 = the paper (per-texel gradients).
    grad_blur: float = 0.0
    # "large_steps": each BSDF map's gradient is preconditioned by (I + map_smoothness L)^-2 (L the texel grid's
    # Laplacian; optimizer.optimise.adam.smooth_texels) and its Adam step normalised by the map's largest second
    # moment (uniform Adam), after Nicolet et al. 2021, "Large Steps in Inverse Rendering of Geometry": a texel
    # cannot move alone, so the maps cannot turn salt-and-pepper. "adam": per-texel Adam (the paper).
    map_update: str = "adam"
    map_smoothness: float = 16.0  # lambda of map_update "large_steps", in texels^2
    freeze_displacement: bool = False  # displacement applied from the initial values, not optimised (Stage 2 option)

    def map_on(self, name: str) -> bool:
        """Whether BSDF map ``name`` is optimised (every switch it needs is on; else it is fixed at its ``off``)."""
        return all(getattr(self, s) for s in MAPS[name].switches)

    def trainable(self) -> list[str]:
        names = [n for n in MAPS if self.map_on(n)]
        if self.displacement and not self.freeze_displacement:
            names.append("displacement")
        if self.pose:
            names += ["translation", "rotation"]
        return names

    def planner_params(self) -> set[str]:
        """The optimised parameter groups in the effect planner's vocabulary."""
        groups = {"albedo"}
        moving = self.displacement and not self.freeze_displacement
        groups |= {g for g, on in (("pose", self.pose), ("displacement", moving), ("bsdf", self.bsdf)) if on}
        if self.bsdf and self.transmittance:
            groups.add("transmittance")
        return groups

    def learning_rates(self) -> dict[str, float]:
        lr = {k: self.lr_maps for k in MAPS}
        lr.update(displacement=self.lr_displacement, translation=self.lr_translation, rotation=self.lr_rotation)
        return {k: lr[k] for k in self.trainable()}


def initial_values(cfg: AppearanceConfig, material: MaterialSpec) -> dict[str, np.ndarray]:
    """Initial parameter arrays: each BSDF map (:data:`~optimizer.scenes.bsdf_maps.MAPS`) at the material's value,
    or its ``off`` value when switched off (paper: albedo 0.5, metallic 0, roughness 0, transmittance 0.5); zero
    displacement, translation and turn."""
    r, rd = cfg.map_resolution, cfg.displacement_resolution
    out: dict[str, np.ndarray] = {}
    for name, m in MAPS.items():
        value = getattr(material, name) if cfg.map_on(name) else m.off
        if m.colour:
            out[name] = np.broadcast_to(np.asarray(value, np.float32), (r, r, m.channels)).copy()
        else:
            out[name] = np.full((r, r, 1), value, np.float32)
    out.update(displacement=np.zeros((rd, rd, 1), np.float32), translation=np.zeros(3, np.float32),
               rotation=np.zeros(1, np.float32))
    return out


def bilinear_taps(uv: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel indices ``(N, 4)`` and weights ``(N, 4)`` of a bilinear lookup at ``uv (N, 2)``.

    Same convention as Mitsuba's bitmap texture: ``x = u W - 0.5``,
    ``y = v H - 0.5`` (row 0 at v = 0), clamped at the borders.
    """
    x = np.clip(uv[:, 0] * width - 0.5, 0.0, width - 1.0)
    y = np.clip(uv[:, 1] * height - 0.5, 0.0, height - 1.0)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    x1 = np.minimum(x0 + 1, width - 1)
    y1 = np.minimum(y0 + 1, height - 1)
    fx, fy = x - x0, y - y0
    idx = np.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], axis=1)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    return idx, w.astype(np.float32)


def seam_averaged_taps(uv: np.ndarray, uv_to_welded: np.ndarray, height: int, width: int):
    """Sparse operator ``(welded_rows, texels, weights)``: D of a welded vertex = mean of D at its UV copies."""
    idx, w = bilinear_taps(uv, height, width)
    counts = np.bincount(uv_to_welded).astype(np.float32)
    rows = np.repeat(uv_to_welded, 4)
    weights = (w / counts[uv_to_welded][:, None]).ravel()
    return rows, idx.ravel(), weights.astype(np.float32)


def displacement_per_uv_vertex(d_map: np.ndarray, taps, uv_to_welded: np.ndarray) -> np.ndarray:
    """NumPy reference of the seam-averaged lookup: d (normalised) at each UV vertex."""
    rows, tex, w = taps
    d_w = np.zeros(int(uv_to_welded.max()) + 1)
    np.add.at(d_w, rows, w * d_map.reshape(-1)[tex])
    return d_w[uv_to_welded]


@dataclasses.dataclass
class Geometry:
    """Constant per-UV-vertex arrays for the differentiable vertex transform."""

    base: np.ndarray  # (Nu, 3) R S v (object rotated and scaled, not yet translated / spun)
    normal: np.ndarray  # (Nu, 3) R n (unit)
    faces: np.ndarray  # (F, 3) UV-mesh faces
    uvs: np.ndarray  # (Nu, 2)
    taps: tuple[np.ndarray, np.ndarray, np.ndarray]  # seam-averaged displacement taps (welded rows)
    uv_to_welded: np.ndarray  # (Nu,)
    translation: np.ndarray  # (3,) T_t
    size: float
    bound: float  # displacement bound, scene units

    @classmethod
    def build(cls, prepared, obj: ObjectSpec, cfg: AppearanceConfig) -> "Geometry":
        R = euler_xyz_deg(obj.rotation)[:3, :3]
        w2u = prepared.uv_to_welded
        base = (prepared.vertices[w2u] * obj.size) @ R.T
        normal = prepared.normals[w2u] @ R.T
        taps = seam_averaged_taps(prepared.uvs, w2u, cfg.displacement_resolution, cfg.displacement_resolution)
        return cls(base.astype(np.float32), normal.astype(np.float32), prepared.uv_faces, prepared.uvs.astype(np.float32),
                   taps, np.asarray(w2u), np.asarray(obj.translation, np.float64), obj.size,
                   cfg.displacement_bound * obj.size)

    def positions_np(self, d_map: np.ndarray | None = None, dt=(0.0, 0.0, 0.0), theta: float = 0.0) -> np.ndarray:
        """World positions ``(Nu, 3)`` in NumPy (for export and tests)."""
        p = self.base.astype(np.float64)
        if d_map is not None:
            d = displacement_per_uv_vertex(d_map, self.taps, self.uv_to_welded)
            p = p + (self.bound * d)[:, None] * self.normal
        m = model_matrix(1.0, (0, 0, 0), self.translation, dt, theta)
        return (p @ m[:3, :3].T + m[:3, 3]).astype(np.float32)

    def normals_np(self, theta: float = 0.0) -> np.ndarray:
        """Unit vertex normals ``(Nu, 3)`` in the frame of :meth:`positions_np` at the turn ``theta`` (radians about
        z): ``normal`` is in the unturned frame, so a projection onto a turned object must orient its faces with
        these (with ``normal`` a turn of pi would make every face look inward; issue 29). The displacement's tilt
        of the normals is not included (orientation only)."""
        m = model_matrix(1.0, (0, 0, 0), (0, 0, 0), (0, 0, 0), theta)
        return (self.normal.astype(np.float64) @ m[:3, :3].T).astype(np.float32)

    def positions_dr(self, d_map=None, dt=None, theta=None):
        """World positions as a flat ``mi.Float`` (x0, y0, z0, x1, ...), differentiable in all inputs."""
        import drjit as dr
        import mitsuba as mi

        n = len(self.base)
        px, py, pz = (mi.Float(self.base[:, k]) for k in range(3))
        if d_map is not None:
            rows, tex, w = self.taps
            vals = dr.gather(mi.Float, d_map.array, mi.UInt32(tex.astype(np.uint32))) * mi.Float(w)
            d_w = dr.zeros(mi.Float, int(self.uv_to_welded.max()) + 1)
            dr.scatter_add(d_w, vals, mi.UInt32(rows.astype(np.uint32)))
            d = dr.gather(mi.Float, d_w, mi.UInt32(self.uv_to_welded.astype(np.uint32))) * self.bound
            px = px + d * mi.Float(self.normal[:, 0])
            py = py + d * mi.Float(self.normal[:, 1])
            pz = pz + d * mi.Float(self.normal[:, 2])
        if theta is not None:
            th = dr.gather(mi.Float, theta, 0)  # indexing would detach it
            c, s = dr.cos(th), dr.sin(th)
            px, py = c * px - s * py, s * px + c * py
        t = [float(x) for x in self.translation]
        if dt is not None:
            d3 = [dr.gather(mi.Float, dt, k) for k in range(3)]
            px, py, pz = px + (t[0] + d3[0]), py + (t[1] + d3[1]), pz + (t[2] + d3[2])
        else:
            px, py, pz = px + t[0], py + t[1], pz + t[2]
        idx = dr.arange(mi.UInt32, n)
        out = dr.zeros(mi.Float, 3 * n)
        for k, comp in enumerate((px, py, pz)):
            dr.scatter(out, comp, idx * 3 + k)
        return out


def clamp_projections(cfg: AppearanceConfig, size: float) -> dict[str, Any]:
    """Per-parameter projections applied after each Adam step (maps to [0, 1] -- albedo to [ALBEDO_MIN, 1] --,
    d to [-1, 1], dt clipped)."""
    import drjit as dr
    import mitsuba as mi

    lim = cfg.translation_fraction * size

    def unit(low: float):  # a map: [low, 1] (albedo: ALBEDO_MIN, the principled BSDF's sqrt tint is infinite at 0)
        return lambda x: dr.clip(dr.select(dr.isfinite(x), x, low), low, 1.0)

    def signed(x):
        return dr.clip(dr.select(dr.isfinite(x), x, 0.0), -1.0, 1.0)

    def offset(x):
        x = dr.clip(dr.select(dr.isfinite(x), x, 0.0), -lim, lim)
        if not cfg.allow_dz:
            x = x * mi.Float([1.0, 1.0, 0.0])
        return x

    def angle(x):
        # Wrap to [-pi, pi]. Beyond ~1e7 rad a float32 angle has no fractional part left, so its direction
        # is meaningless (and sin/cos return NaN): such angles and non-finite ones reset to 0.
        ok = dr.isfinite(x) & (dr.abs(x) < 1e7)
        x = dr.select(ok, x, 0.0)
        return dr.clip(x - 2 * math.pi * dr.round(x / (2 * math.pi)), -math.pi, math.pi)

    return {**{name: unit(m.low) for name, m in MAPS.items()},
            "displacement": signed, "translation": offset, "rotation": angle}


def rendered_maps(values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The maps as rendered (:meth:`~optimizer.scenes.bsdf_maps.BsdfMap.rendered`: roughness through the safe
    minimum), for export."""
    return {k: m.rendered(values[k]) for k, m in MAPS.items()}


def object_bsdf(values: dict[str, np.ndarray], app: AppearanceConfig) -> dict:
    """The object's BSDF dict for parameter ``values`` (albedo only -> Lambertian)."""
    if not app.bsdf:
        return {"type": "diffuse", "reflectance": scn.texture(values["albedo"])}
    return scn.principled({k: values[k] for k in MAPS}, app.eta)


def object_mesh(geometry: Geometry, values: dict[str, np.ndarray], app: AppearanceConfig) -> dict:
    """The object's Mitsuba mesh dict for parameter ``values``: world positions, UV faces, BSDF."""
    return scn.object_mesh(world_positions(geometry, values, app), geometry.faces, geometry.uvs,
                           object_bsdf(values, app))


def world_positions(geometry: Geometry, values: dict[str, np.ndarray], app: AppearanceConfig) -> np.ndarray:
    """World positions ``(Nu, 3)`` of the UV-split mesh for parameter ``values``."""
    d = values["displacement"][..., 0] if app.displacement else None
    return geometry.positions_np(d, values["translation"], float(values["rotation"][0]))


def world_normals(geometry: Geometry, values: dict[str, np.ndarray]) -> np.ndarray:
    """Unit vertex normals ``(Nu, 3)`` in the frame of :func:`world_positions` (the learned turn applied)."""
    return geometry.normals_np(float(values["rotation"][0]))


def pose_record(obj: ObjectSpec, values: dict[str, np.ndarray]) -> dict[str, Any]:
    """``pose.json``: the learned offset and angle, and the final model matrix (Eq. 3)."""
    dt = [float(x) for x in values["translation"]]
    th = float(values["rotation"][0])
    return {"dx": dt[0], "dy": dt[1], "dz": dt[2], "theta_z": th, "theta_z_deg": math.degrees(th),
            "model_matrix": model_matrix(obj.size, obj.rotation, obj.translation, dt, th).tolist()}
