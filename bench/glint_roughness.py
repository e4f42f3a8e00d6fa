"""How rough must the object be before a mirror reflection of the light stops being a glint?

For each scene: find the brightest direction of its environment emitter (the sun of ``sunsky``, the sun
baked into a panorama), place a small flat facet at the object's centre tilted so that it mirrors that
direction into training camera 0, and render the facet alone in a very narrow field of view with the
paper's initial material (albedo 0.5, metallic 0, transmittance 0.5, eta 1.5) at each roughness map value
``r`` (rendered roughness ``0.035 + 0.965 r``, as in the optimiser). The facet's luminance there is the
brightest any surface of that roughness can send to a camera in that scene. It is compared with the
evaluation's glint threshold: twice the 99.5th luminance percentile of the background in the training views
(``bench/glint_sources.py --eval``).

A displaced surface has facets of many orientations, so in some novel view a facet mirrors the light;
below the roughness at which the ratio drops under 1 that facet is a glint. The last lines compare that
roughness with how far Adam can move a map value in the paper's schedule (about one learning rate per
step: 0.01 x (50 + 20)), which the optimiser reaches only if every step pushes the roughness up.

    python bench/glint_roughness.py [--scenes gravel,meadow,split,occluded,panorama] [--spp 1024]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from grid_figures import REC709  # noqa: E402

ROUGHNESS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0)


def fibonacci_hemisphere(n: int) -> np.ndarray:
    """``(n, 3)`` near-uniform unit vectors with z > 0 (Z-up)."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def brightest_direction(elements: dict, n: int = 4_000_000) -> tuple[np.ndarray, float]:
    """Unit vector towards the centre of the brightest spot of the scene's environment emitter (the sun's
    disc, which ``sunsky`` draws without limb darkening), and its luminance.

    Searched on ``n`` directions of the upper hemisphere (~0.07 deg apart at 4M: finer than the sun's
    0.27 deg radius), then on a 0.01 deg grid +-1 deg around the best one, whose pixels above half the
    maximum give the centre."""
    import drjit as dr
    import mitsuba as mi

    from optimizer.rendering import scene as scn

    scene = scn.build_scene(elements)
    env = scene.environment()
    if env is None:
        raise SystemExit("glint_roughness: the scene has no environment emitter (sunsky / envmap)")

    def lum(dirs: np.ndarray) -> np.ndarray:
        si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
        si.wi = mi.Vector3f(*(-dirs.T.astype(np.float32)))
        rgb = env.eval(si)
        return np.asarray(rgb.x) * REC709[0] + np.asarray(rgb.y) * REC709[1] + np.asarray(rgb.z) * REC709[2]

    dirs = fibonacci_hemisphere(n)
    y = lum(dirs)
    best = dirs[int(np.argmax(y))]
    # local grid in the tangent plane
    t = np.cross(best, [0.0, 0.0, 1.0] if abs(best[2]) < 0.9 else [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    b = np.cross(best, t)
    g = np.radians(np.linspace(-1.0, 1.0, 201))
    uu, vv = np.meshgrid(g, g)
    local = best[None] + uu.reshape(-1, 1) * t[None] + vv.reshape(-1, 1) * b[None]
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    yl = lum(local)
    spot = yl >= 0.5 * yl.max()
    centre = local[spot].mean(axis=0)
    return centre / np.linalg.norm(centre), float(yl.max())


def facet(centre, normal, half: float, bsdf: dict) -> dict:
    """A square ``rectangle`` of half-size ``half`` centred at ``centre`` facing ``normal``."""
    import mitsuba as mi

    n = np.asarray(normal, float)
    up = [0.0, 0.0, 1.0] if abs(n[2]) < 0.99 else [1.0, 0.0, 0.0]
    # look_at orients the rectangle's +z (its normal) from the origin towards ``target``
    to_world = mi.ScalarTransform4f().look_at(origin=list(map(float, centre)),
                                               target=list(map(float, np.asarray(centre) + n)), up=up)
    return {"type": "rectangle", "to_world": to_world @ mi.ScalarTransform4f().scale([half, half, 1.0]), "bsdf": bsdf}


def scene_report(name: str, spp: int, roughness: tuple[float, ...]) -> dict:
    import mitsuba as mi

    from optimizer.scenes import builtin_scenes
    from optimizer.scenes.bsdf_maps import material_values
    from optimizer.rendering import scene as scn
    from optimizer.scenes.cameras import Camera, cameras, object_centre
    from optimizer.scenes.environments import get_environment
    from optimizer.rendering.render import render_shaded

    pack = builtin_scenes.get(name)
    env = get_environment(pack.environment)
    integ = {"type": "path", "max_depth": 6, "rr_depth": 6}
    cams = cameras(pack, (96, 96))
    bg = render_shaded(env.build(), None, cams, integ, 64, seed=1)
    threshold = 2.0 * float(np.quantile(bg @ REC709, 0.995))

    sun, sun_y = brightest_direction(env.build())
    centre = np.asarray(object_centre(pack), float)
    eye = np.asarray(cams[0].origin, float)
    view = (eye - centre) / np.linalg.norm(eye - centre)
    h = sun + view
    h /= np.linalg.norm(h)
    # 0.1 deg field of view: every pixel sees the facet within the mirror image of the sun (0.53 deg wide)
    cam = Camera(tuple(eye), tuple(centre), 0.1, 8, 8)
    m = pack.material
    rows = []
    for r in roughness:
        bsdf = scn.principled({**material_values(m), "roughness": r})
        elements = env.build()
        elements["probe"] = facet(centre, h, 0.25, bsdf)
        sc = scn.build_scene(elements, None, [scn.perspective(cam, spp)], integ)
        img = np.asarray(mi.render(sc, spp=spp, seed=3), np.float64)
        y = float(np.median(img @ REC709))
        rows.append((r, float(scn.effective_roughness(r)), y, y / threshold))
    return {"scene": name, "threshold": threshold, "sun": sun, "sun_y": sun_y, "view": view,
            "angle": math.degrees(math.acos(float(np.clip(h @ view, -1, 1)))), "rows": rows}


def needed(rows) -> float | None:
    """Smallest tried map roughness whose facet, and every rougher one, is below the threshold."""
    ok = None
    for r, _, _, ratio in reversed(rows):
        if ratio >= 1.0:
            break
        ok = r
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="gravel,meadow,split,occluded,panorama")
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--lr", type=float, default=1e-2, help="texture-map learning rate (paper 1e-2)")
    ap.add_argument("--steps", type=int, default=70, help="Stage 1 + Stage 2 iterations (paper 50 + 20)")
    args = ap.parse_args(argv)

    from optimizer import backend
    from optimizer.scenes import builtin_scenes

    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    bad = [s for s in scenes if s not in builtin_scenes.names()]
    if bad:
        print(f"glint_roughness: unknown scene(s) {', '.join(bad)}; built-in: {', '.join(builtin_scenes.names())}",
              file=sys.stderr)
        return 2
    backend.init()
    print(f"facet in mirror geometry, paper material, {args.spp} spp; ratio = facet luminance / "
          f"(2 x background 99.5th percentile)")
    summary = []
    for name in scenes:
        rep = scene_report(name, args.spp, ROUGHNESS)
        el = math.degrees(math.asin(float(rep["sun"][2])))
        print(f"\n{name}: light at elevation {el:.1f} deg (luminance {rep['sun_y']:.3g}), glint threshold "
              f"{rep['threshold']:.4f}, incidence {rep['angle']:.1f} deg")
        print(f"{'map r':>6s} {'rendered':>8s} {'facet Y':>10s} {'ratio':>9s}")
        for r, eff, y, ratio in rep["rows"]:
            print(f"{r:6.2f} {eff:8.3f} {y:10.4f} {ratio:9.2f}")
        summary.append((name, needed(rep["rows"])))
    budget = args.lr * args.steps
    print(f"\nAdam moves a map value by about lr per step: at most ~{budget:.2f} in {args.steps} steps at lr {args.lr:g}")
    for name, r in summary:
        verdict = "none of the tried values" if r is None else f"map r >= {r:.2f}"
        print(f"{name:10s} no glint from {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
