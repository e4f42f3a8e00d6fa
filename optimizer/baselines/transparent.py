"""The "Transparent" baseline (paper Sec. IV-B (i)): a glass-like object.

Transmittance 1 everywhere; the other maps keep the pack's initial material
(the paper's defaults: albedo 0.5, metallic 0, roughness 0 map value, rendered
with the safe minimum roughness of :mod:`optimizer.scene`), index of
refraction ``eta`` of the appearance config (1.5); principled BSDF; no
displacement, no pose change. Nothing is optimised.
"""

from __future__ import annotations

import numpy as np

from ..appearance import initial_values
from .common import Setup


def compute(setup: Setup):
    vals = initial_values(setup.app, setup.pack.material)
    vals["transmittance"] = np.ones_like(vals["transmittance"])
    info = {"transmittance": 1.0, "albedo": list(map(float, setup.pack.material.albedo)),
            "metallic": float(setup.pack.material.metallic), "roughness": float(setup.pack.material.roughness),
            "eta": float(setup.app.eta)}
    return vals, [], info
