"""Camera rigs: orbit views around the object, explicit lists, and jitter.

Positions are world-space points (Z-up, scene units). The paper's rig: 16
views uniformly on a circle of radius 4 at a fixed elevation, looking at the
object; evaluation moves each camera by an independent uniform offset of up to
+-0.25 units per axis at radius 4 (scaled with the radius).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

# ``pack`` arguments are :class:`optimizer.scenes.scenepack.ScenePack` (not imported: scenepack imports this module).


@dataclasses.dataclass(frozen=True)
class Camera:
    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    fov: float  # horizontal, degrees
    width: int
    height: int
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)


def object_centre(pack: "ScenePack") -> tuple[float, float, float]:
    """Where cameras look: the object's ground position lifted to half its (normalised) size."""
    tx, ty, tz = pack.object.translation
    return (tx, ty, tz + 0.5 * pack.object.size)


def orbit_positions(centre, radius: float, elevation_deg: float, views: int, azimuth_offset_deg: float = 0.0):
    el = math.radians(elevation_deg)
    out = []
    for i in range(views):
        az = math.radians(azimuth_offset_deg) + 2.0 * math.pi * i / views
        out.append(
            (
                centre[0] + radius * math.cos(el) * math.cos(az),
                centre[1] + radius * math.cos(el) * math.sin(az),
                centre[2] + radius * math.sin(el),
            )
        )
    return out


def camera_positions(pack: "ScenePack") -> list[tuple[float, float, float]]:
    c = pack.cameras
    if c.mode == "list":
        return [tuple(p) for p in c.positions]
    return orbit_positions(object_centre(pack), c.radius, c.elevation, c.views, c.azimuth_offset)


def cameras(pack: "ScenePack", resolution: tuple[int, int] | None = None) -> list[Camera]:
    """The training cameras of a pack."""
    w, h = resolution or pack.render.resolution
    c = pack.cameras
    centre = object_centre(pack)
    targets = c.targets if (c.mode == "list" and c.targets) else [centre] * len(camera_positions(pack))
    return [Camera(tuple(p), tuple(t), c.fov, w, h) for p, t in zip(camera_positions(pack), targets)]


def evenly_spaced(n: int, k: int) -> list[int]:
    """Indices of ``k`` <= ``n`` cameras spread evenly over a rig of ``n`` (sorted, no repeats)."""
    return sorted({int(round(i * n / k)) % n for i in range(k)})


def rig_radius(pack: "ScenePack", training: list[Camera]) -> float:
    """The rig's radius: the orbit radius, or the mean camera-target distance of a camera list."""
    if pack.cameras.mode == "orbit":
        return float(pack.cameras.radius)
    return float(np.mean([math.dist(c.origin, c.target) for c in training]))


def jitter(cams: list[Camera], amount: float, radius: float, seed: int, repeats: int = 1) -> list[Camera]:
    """Novel views: each camera (``repeats`` times) moved by U(-a, a) per axis, a = amount * radius / 4.

    The target stays fixed, so the view direction changes by roughly
    +-4-5 degrees at the paper's setting (0.25 at radius 4). A jittered camera
    that lands exactly on a training camera is re-drawn.
    """
    rng = np.random.default_rng(seed)
    a = amount * radius / 4.0
    out = []
    train = {c.origin for c in cams}
    for _ in range(repeats):
        for c in cams:
            while True:
                off = rng.uniform(-a, a, size=3) if a > 0 else np.zeros(3)
                o = tuple(float(x) for x in np.asarray(c.origin) + off)
                if o not in train or a == 0:
                    break
            out.append(dataclasses.replace(c, origin=o))
    return out
