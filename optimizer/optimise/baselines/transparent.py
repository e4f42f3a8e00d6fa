"""The "Transparent" baseline (paper Sec. IV-B (i)): a glass-like object.

Transmittance 1 everywhere; clear glass: metallic 0 and roughness 0 (map value,
rendered with the safe minimum roughness of :mod:`optimizer.rendering.scene`) whatever
the pack's initial material says; albedo from the pack (paper: 0.5); index of
refraction ``eta`` of the appearance config (1.5); principled BSDF; no
displacement, no pose change. Nothing is optimised.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from optimizer.rendering.appearance import initial_values
from optimizer.optimise.baselines.common import Setup
from optimizer.optimise.method import Method


def compute(setup: Setup):
    glass = dataclasses.replace(setup.pack.material, metallic=0.0, roughness=0.0, transmittance=1.0)
    vals = initial_values(setup.app, glass)
    vals["transmittance"] = np.ones_like(vals["transmittance"])
    info = {"transmittance": 1.0, "albedo": list(map(float, glass.albedo)),
            "metallic": 0.0, "roughness": 0.0,
            "eta": float(setup.app.eta)}
    return vals, [], info


#: The method of this module (collected by :mod:`optimizer.optimise.methods`).
METHODS = (Method("transparent", "transmittance 1 everywhere: a glass-like object (baselines.transparent)",
                  compute=lambda setup, options, progress: compute(setup)),)
