"""Interactive 3D viewer pages: each result's glTF in ``<model-viewer>`` (orbit controls), lit by and standing in
the scene's environment, next to its path-traced stills (``camo view RUN``; the viewer section of ``camo report``).

What the page holds, and where it comes from:

* **The viewer** is ``<model-viewer>`` from the npm package ``@google/model-viewer`` (pinned in
  ``data_manifests/viewer.toml``, fetched by ``make demo`` / ``make test`` into ``data/vendor/``;
  :func:`viewer_script`). Pages copy it beside themselves and load it with a classic ``<script src>``: nothing comes
  from a CDN, and the page works offline, from disk (``file://``) or served (:func:`serve`).
* **The result**: a run directory's ``result.glb`` (glTF 2.0 PBR textures + ``KHR_materials_transmission``; the
  displaced, posed mesh in scene coordinates turned Y-up), or an external asset placed in its scene and written
  as glTF by :func:`optimizer.assets.export.glb_bytes` (what the path tracer renders, as a GLB).
* **The environment** (:func:`environment_panorama`): the scene without the object, path-traced into an
  equirect HDR panorama from above the object's ground point at the object centre's height (the panorama scenes'
  HDRI, the built-in ``sunsky`` with its sun, the ground, walls and lamps alike), in three.js's equirect
  convention, written as Radiance ``.hdr``. ``<model-viewer>`` lights the object with it (image-based lighting)
  and shows it as the background, projected onto the ground plane (``skybox-height`` = the capture height), so the
  object stands on the scene's ground.
* **Cameras**: the viewer opens at a camera of the stills (the evaluation's or the run's), with the same field of
  view; clicking a still moves the viewer there, so the rasterised and path-traced pictures can be compared view
  by view. Tone mapping is ``linear`` at exposure 1: the same ``sRGB(clip(radiance))`` as the stills.
* Because pages must open from disk, where Chromium refuses ``fetch()`` of ``file://`` URLs, every GLB and
  panorama travels as a small JavaScript file (``assets/<id>.js``: base64 in a string) that a ``<script src>``
  loads; the page turns it into a ``blob:`` URL for ``<model-viewer>``.

The rasteriser approximates light transport (:data:`RASTER_LIMITS` says how, on the page) and links the
path-traced turntable (``camo video``) as the reference.
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import html
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from camo_base.errors import CamoError, SettingError, literal

REPO = Path(__file__).resolve().parents[1]
MANIFEST = REPO / "data_manifests" / "viewer.toml"
VIEWER_JS = "model-viewer-umd.min.js"
VENDOR_DIR = REPO / "data" / "vendor"
FETCH_COMMAND = "camo data fetch data_manifests/viewer.toml --dest data/vendor"
#: Equirect panorama of the environment: width (height = width / 2) and samples per pixel.
ENV_WIDTH, ENV_SPP = 1024, 16

#: What the rasteriser does differently from the path tracer (shown on every viewer page).
RASTER_LIMITS = (
    ("Refraction", "transmissive texels (KHR_materials_transmission) show a blurred copy of what is rendered behind "
     "the object, bent as through a thin wall; the path tracer refracts through the closed mesh (front face, back "
     "face) with its index of refraction, and shows caustics."),
    ("Shadows", "the object's shadow is a soft contact shadow straight below it; the path tracer casts the sun's "
     "(or the lamp's) shadow with its direction and sharpness, onto the real ground texture."),
    ("Interreflection", "no light bounces between the object and the ground or walls (no colour bleeding, no "
     "ground light under the object beyond the panorama's), which the path tracer simulates."),
    ("Environment", "the background is one panorama captured at the object, projected onto a flat ground; away "
     "from that point, parallax and the ground's detail are approximate (walls and occluders are painted on it, "
     "they do not hide the object)."),
    ("Sun and glints", "the sun is a small bright spot of the panorama, pre-filtered per roughness: mirror-like "
     "glints are close, but not identical, to the path tracer's."),
    ("Noise", "the rasteriser has none; the path-traced stills and video carry Monte Carlo noise at their spp."),
)


# --------------------------------------------------------------------------------------------------------------
# the viewer's JavaScript
# --------------------------------------------------------------------------------------------------------------


def viewer_script() -> Path | None:
    """The ``<model-viewer>`` bundle: ``$CAMO_VIEWER_JS`` or ``data/vendor/model-viewer-umd.min.js``, when it is
    there and matches the manifest's pin (size and SHA-256); else None."""
    from optimizer.scenes.data.manifest import load_manifest

    path = Path(os.environ.get("CAMO_VIEWER_JS") or VENDOR_DIR / VIEWER_JS)
    if not path.is_file():
        return None
    pin = load_manifest(MANIFEST).get("model-viewer")
    if path.stat().st_size != pin.size or _sha256(path.read_bytes()) != pin.sha256:
        return None
    return path


def require_viewer_script() -> Path:
    p = viewer_script()
    if p is None:
        raise CamoError(f"the viewer's JavaScript (@google/model-viewer) is not installed or does not match its pin; "
                        f"run: {FETCH_COMMAND}  (make demo and make test do it)")
    return p


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# --------------------------------------------------------------------------------------------------------------
# the environment as an equirect panorama
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Environment:
    """A scene's environment for the viewer: the panorama (linear radiance, three.js equirect convention) and
    where it was captured."""

    image: np.ndarray  # (H, 2H, 3) float32 linear radiance
    capture: tuple[float, float, float]  # world (Z-up) point it was captured from
    grounded: bool  # project the lower half onto the ground plane z = 0 (skybox-height = capture height)

    @property
    def height(self) -> float:
        return float(self.capture[2])


def to_threejs_equirect(pano: np.ndarray) -> np.ndarray:
    """A panorama in :mod:`optimizer.scenes.panorama`'s convention (world Z-up; column ``u`` looks along azimuth
    ``2 pi u`` from +y towards +x) turned into three.js's (Y-up ``(x, z, -y)`` as glTF; column ``u`` looks along
    ``atan2(z3, x3) = 2 pi (u - 1/2)``): the same rows, columns rolled by a quarter turn.

    World +x is column 1/4 in ours and 1/2 in three.js, world +y 0 and 1/4: ``u3 = u + 1/4`` (both turn from +y
    towards +x as ``u`` grows), hence ``np.roll`` by ``W / 4``. Rows: both put the zenith in row 0.
    """
    w = pano.shape[1]
    if w % 4:
        raise ValueError(f"panorama width must be a multiple of 4, got {w}")
    return np.roll(pano, w // 4, axis=1)


def capture_point(pack) -> tuple[float, float, float]:
    """Where the viewer's panorama is captured: above the world origin (the glTF origin, which ``<model-viewer>``
    puts its projected ground around) at the object centre's height."""
    from optimizer.scenes.cameras import object_centre

    return 0.0, 0.0, max(float(object_centre(pack)[2]), 0.05)


def environment_panorama(pack, width: int = ENV_WIDTH, spp: int = ENV_SPP, seed: int = 0,
                         say: Callable[[str], None] = lambda m: None) -> Environment:
    """The scene's environment (without the object) path-traced into an equirect panorama (module docstring);
    cached in ``$CAMO_CACHE/viewer/`` by the environment, capture point, width, spp and seed."""
    from camo_base.imaging import load_hdr_image
    from optimizer.scenes.environments import cache_dir, get_environment
    from optimizer.scenes.panorama import render_equirect

    if width < 64 or width % 4:
        raise SettingError.of("env_width", f" must be a multiple of 4 and >= 64, got {width}")
    origin = capture_point(pack)
    env_spec = dataclasses.asdict(pack.environment)
    key = hashlib.sha256(json.dumps({"env": env_spec, "origin": origin, "w": width, "spp": spp, "seed": seed,
                                     "v": 1}, sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = cache_dir() / "viewer" / f"env_{key}_{width}.hdr"
    grounded = not (pack.environment.panorama and not pack.environment.ground)
    if path.is_file():
        try:
            return Environment(load_hdr_image(path).astype(np.float32), origin, grounded)
        except Exception:  # a damaged cache file is rendered again
            pass
    say(f"rendering the environment panorama of {pack.name} ({width}x{width // 2}, {spp} spp)")
    env = get_environment(pack.environment)
    pano = render_equirect(env.build(), origin=origin, width=width, spp=spp, seed=seed)
    img = to_threejs_equirect(np.nan_to_num(np.maximum(pano, 0.0), nan=0.0, posinf=0.0))
    write_hdr(path, img)
    return Environment(load_hdr_image(path).astype(np.float32), origin, grounded)


def write_hdr(path: str | Path, img: np.ndarray) -> None:
    """A Radiance RGBE ``.hdr`` file (run-length encoded, OpenCV's writer), written atomically."""
    import cv2

    from camo_base.atomic import atomic_path

    a = np.ascontiguousarray(np.asarray(img, np.float32)[..., ::-1])  # OpenCV: BGR
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), a):
            raise OSError(f"cannot write {path}")


def hdr_bytes(env: Environment) -> bytes:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "env.hdr"
        write_hdr(p, env.image)
        return p.read_bytes()


# --------------------------------------------------------------------------------------------------------------
# cameras: our Camera -> <model-viewer> attributes
# --------------------------------------------------------------------------------------------------------------


def to_gltf(p: Sequence[float]) -> tuple[float, float, float]:
    """World (Z-up) point -> glTF / three.js (Y-up): ``(x, y, z) -> (x, z, -y)`` (as the GLB's node rotation)."""
    return float(p[0]), float(p[2]), -float(p[1])


def camera_attributes(origin: Sequence[float], target: Sequence[float], fov_deg: float, aspect: float = 1.0) -> dict:
    """``camera-orbit`` (``theta phi radius``: azimuth about +Y from +Z, polar angle from +Y, distance),
    ``camera-target`` and ``field-of-view`` (vertical, for a viewer of width / height ``aspect``) of a camera at
    ``origin`` looking at ``target`` with horizontal field of view ``fov_deg`` (world coordinates, Z-up).

    >>> camera_attributes((0, -4, 0), (0, 0, 0), 30.0)["camera-orbit"]
    '0.0000deg 90.0000deg 4.000000m'
    """
    o, t = np.array(to_gltf(origin)), np.array(to_gltf(target))
    d = o - t
    r = float(np.linalg.norm(d))
    theta = math.degrees(math.atan2(d[0], d[2]))
    phi = math.degrees(math.acos(max(-1.0, min(1.0, d[1] / max(r, 1e-12)))))
    vfov = math.degrees(2 * math.atan(math.tan(math.radians(fov_deg) / 2) / aspect))
    return {"camera-orbit": f"{theta:.4f}deg {phi:.4f}deg {r:.6f}m",
            "camera-target": f"{t[0]:.6f}m {t[1]:.6f}m {t[2]:.6f}m", "field-of-view": f"{vfov:.4f}deg"}


# --------------------------------------------------------------------------------------------------------------
# page pieces
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Still:
    """A path-traced picture (sRGB PNG bytes) and the camera it was rendered from (world coordinates)."""

    png: bytes
    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    fov: float
    caption: str = ""


@dataclasses.dataclass
class Card:
    """One result in a viewer page."""

    id: str
    label: str
    glb: bytes
    env_id: str
    stills: list[Still]
    camera: tuple[tuple[float, float, float], tuple[float, float, float], float]  # origin, target, fov to open at
    note: str = ""


class Bundle:
    """The files a viewer page needs beside it: ``viewer/model-viewer-umd.min.js`` and ``viewer/assets/<id>.js``
    (each a GLB or an HDR panorama as base64, registered in ``window.camoViewerAssets``)."""

    def __init__(self, root: str | Path, folder: str = "viewer"):
        self.root, self.folder = Path(root), folder
        self.ids: list[str] = []

    @property
    def dir(self) -> Path:
        return self.root / self.folder

    def install_script(self) -> None:
        from camo_base.atomic import atomic_path

        src = require_viewer_script()
        dst = self.dir / VIEWER_JS
        if not (dst.is_file() and dst.stat().st_size == src.stat().st_size and
                _sha256(dst.read_bytes()) == _sha256(src.read_bytes())):
            with atomic_path(dst) as tmp:
                shutil.copyfile(src, tmp)

    def add(self, asset_id: str, data: bytes, mime: str, fragment: str = "") -> str:
        """Write ``assets/<asset_id>.js`` (the bytes as base64); returns ``asset_id``."""
        from camo_base import atomic

        b64 = base64.b64encode(data).decode("ascii")
        js = ("(window.camoViewerAssets = window.camoViewerAssets || {})[" + json.dumps(asset_id) + "] = "
              + json.dumps({"mime": mime, "fragment": fragment, "b64": b64}) + ";\n")
        atomic.write_text(self.dir / "assets" / f"{asset_id}.js", js)
        self.ids.append(asset_id)
        return asset_id

    def add_environment(self, env: Environment, name: str) -> str:
        return self.add(f"env-{name}", hdr_bytes(env), "application/octet-stream", "#environment.hdr")

    def script_tags(self) -> str:
        tags = [f'<script src="{html.escape(self.folder)}/assets/{html.escape(i)}.js"></script>' for i in self.ids]
        tags.append(f'<script src="{html.escape(self.folder)}/{VIEWER_JS}"></script>')
        return "\n".join(tags)


def asset_id(text: str, data: bytes) -> str:
    from evaluation.inputs import safe_name

    return f"{safe_name(text)[:40]}-{_sha256(data)[:10]}"


def card_html(card: Card, env: Environment, size: int = 384) -> str:
    """A ``<model-viewer>`` for ``card`` and its stills (clicking one moves the viewer to its camera)."""
    cam = camera_attributes(*card.camera)
    attrs = {
        "id": f"mv-{card.id}", "class": "camo-mv", "data-glb": card.id, "data-env": card.env_id,
        "camera-controls": "", "loading": "eager", "interaction-prompt": "none", "tone-mapping": "linear",
        "exposure": "1",
        "shadow-intensity": "1", "shadow-softness": "0.6", "min-camera-orbit": "auto 0deg 0.05m",
        "max-camera-orbit": "auto 180deg 1000m", "min-field-of-view": "5deg", "max-field-of-view": "120deg",
        "interpolation-decay": "60", "alt": f"{card.label}: interactive 3D view",
        "skybox-height": f"{env.height:.4f}m" if env.grounded else "0m", **cam,
    }
    a = " ".join(f'{k}="{html.escape(v)}"' if v else k for k, v in attrs.items())
    stills = []
    for i, s in enumerate(card.stills):
        c = camera_attributes(s.origin, s.target, s.fov)
        data = base64.b64encode(s.png).decode("ascii")
        stills.append(f'<figure class="camo-still"><img src="data:image/png;base64,{data}" alt="'
                      f'{html.escape(card.label)}, path traced, {html.escape(s.caption or f"view {i}")}" '
                      f'data-mv="mv-{card.id}" data-orbit="{c["camera-orbit"]}" data-target="{c["camera-target"]}" '
                      f'data-fov="{c["field-of-view"]}" title="show this camera in the viewer">'
                      f'<figcaption>{html.escape(s.caption or f"view {i}")}</figcaption></figure>')
    note = f'<p class="camo-note">{html.escape(card.note)}</p>' if card.note else ""
    return (f'<div class="camo-card"><h3>{html.escape(card.label)}</h3>{note}<div class="camo-row">'
            f'<model-viewer {a} style="width:{size}px;height:{size}px"></model-viewer>'
            f'<div class="camo-stills"><p>Path traced (click: show that camera in the viewer)</p>{"".join(stills)}'
            f'</div></div></div>')


def limits_html(videos: Sequence[tuple[str, str]] = ()) -> str:
    """The rasteriser's approximations (:data:`RASTER_LIMITS`) and the path-traced references (``(href, text)``)."""
    items = "".join(f"<li><b>{html.escape(k)}</b>: {html.escape(v)}</li>" for k, v in RASTER_LIMITS)
    if videos:
        refs = ", ".join(f'<a href="{html.escape(h)}">{html.escape(t)}</a>' for h, t in videos)
        ref = f"<p><b>Reference</b>: the path-traced turntable{'s' if len(videos) > 1 else ''} {refs} (<code>camo video</code>): what the evaluation measures.</p>"
    else:
        ref = ("<p><b>Reference</b>: the path-traced stills beside each viewer, and a turntable made with "
               "<code>camo video RUN --side-by-side</code>.</p>")
    return ('<div class="camo-limits"><p>This viewer is a <b>rasteriser</b> (three.js in <code>&lt;model-viewer&gt;'
            '</code>) showing the result\'s glTF: use it to turn the object and look from any side. It approximates '
            f'the light transport that the path tracer (and every metric) computes:</p><ul>{items}</ul>{ref}</div>')


STYLE = (".camo-card{margin:1em 0;}.camo-row{display:flex;gap:12px;align-items:flex-start;flex-wrap:wrap;}"
         "model-viewer{background:#222;--poster-color:#222;}"
         ".camo-stills{display:flex;flex-wrap:wrap;gap:6px;max-width:640px;align-content:flex-start;}"
         ".camo-stills p{width:100%;margin:0;font-size:90%;}"
         ".camo-still{margin:0;text-align:center;font-size:80%;}"
         ".camo-still img{width:128px;height:128px;image-rendering:pixelated;cursor:pointer;display:block;}"
         ".camo-limits{border-left:4px solid #c90;padding:0 1em;background:#fff8e6;}"
         ".camo-note{color:#555;}")

#: Turns the registered assets into blob: URLs and sets every viewer's model and environment; clicking a still
#: moves its viewer to the still's camera. ``window.camoViewerReady`` resolves when every viewer has loaded.
SCRIPT = """<script>
(function () {
  const A = window.camoViewerAssets || {};
  const urls = {};
  function url(id) {
    if (!(id in urls)) {
      const a = A[id];
      if (!a) { return null; }
      const bin = atob(a.b64);
      const bytes = new Uint8Array(bin.length);
      for (let i = 0; i < bin.length; i++) { bytes[i] = bin.charCodeAt(i); }
      urls[id] = URL.createObjectURL(new Blob([bytes], {type: a.mime})) + (a.fragment || "");
    }
    return urls[id];
  }
  const viewers = Array.from(document.querySelectorAll("model-viewer.camo-mv"));
  const ready = viewers.map(function (mv) {
    return new Promise(function (resolve) {
      let model = false, env = false;
      function done() { if (model && env) { resolve(mv.id); } }
      mv.addEventListener("load", function () { model = true; done(); });
      mv.addEventListener("environment-change", function () { env = true; done(); });
      mv.addEventListener("error", function (e) { mv.dataset.error = String(e.detail && e.detail.type || "error"); });
      const envUrl = url(mv.dataset.env);
      if (envUrl) { mv.environmentImage = envUrl; mv.skyboxImage = envUrl; } else { env = true; }
      mv.src = url(mv.dataset.glb);
    });
  });
  window.camoViewerReady = Promise.all(ready);
  document.querySelectorAll(".camo-still img").forEach(function (img) {
    img.addEventListener("click", function () {
      const mv = document.getElementById(img.dataset.mv);
      mv.cameraTarget = img.dataset.target;
      mv.cameraOrbit = img.dataset.orbit;
      mv.fieldOfView = img.dataset.fov;
      mv.jumpCameraToGoal();
    });
  });
})();
</script>"""


def page(title: str, body: str, bundle: Bundle) -> str:
    return ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>" + html.escape(title) + "</title><style>"
            "body{font-family:sans-serif;max-width:1200px;margin:2em auto;}" + STYLE + "</style></head><body>\n"
            + body + "\n" + bundle.script_tags() + "\n" + SCRIPT + "\n</body></html>\n")


# --------------------------------------------------------------------------------------------------------------
# results -> cards
# --------------------------------------------------------------------------------------------------------------


def glb_of(entry) -> bytes:
    """The GLB a card shows: a run's ``result.glb``; an external asset placed in its scene, written as glTF."""
    if entry.kind == "run":
        p = Path(entry.path) / "result.glb"
        if not p.is_file():
            raise CamoError(f"{entry.path}: no result.glb (a run directory of `camo optimize` writes one)")
        return p.read_bytes()
    from optimizer.assets.export import glb_bytes
    from optimizer.scenes.bsdf_maps import MAPS

    a = entry.asset
    maps = {k: v[..., 0] if not MAPS[k].colour and np.ndim(v) == 3 else v for k, v in a.maps.items() if k in MAPS}
    return glb_bytes(a.vertices, a.faces, a.uvs, maps, a.eta, name=entry.name)


def png_bytes(srgb: np.ndarray) -> bytes:
    import io

    from PIL import Image

    from camo_base.imaging import to_uint8

    a = srgb if srgb.dtype == np.uint8 else to_uint8(srgb)
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def run_stills(run, max_views: int = 8) -> list[Still]:
    """A run's own path-traced stills: ``renders.npz``'s final renders at its training cameras (evenly spaced, at
    most ``max_views``)."""
    from camo_base.imaging import linear_to_srgb
    from optimizer.scenes.cameras import cameras, evenly_spaced

    p = Path(run.path) / "renders.npz"
    if not p.is_file():
        return []
    try:
        with np.load(p, allow_pickle=False) as d:
            final = np.asarray(d["final"], np.float32)
    except Exception as exc:  # damaged file: no stills, said on the page
        raise CamoError(f"{p}: cannot read ({type(exc).__name__})") from None
    cams = cameras(run.pack, (final.shape[2], final.shape[1]))
    if len(cams) != len(final):
        return []
    spp = run.summary().get("final_render", {}).get("spp")
    out = []
    for v in evenly_spaced(len(final), min(max_views, len(final))):
        c = cams[v]
        out.append(Still(png_bytes(linear_to_srgb(final[v])), c.origin, c.target, c.fov,
                         f"training view {v}" + (f", {spp} spp" if spp else "")))
    return out


def write_run_viewer(run_dir: str | Path, out: str | Path | None = None, video: str | Path | None = None,
                     env_width: int = ENV_WIDTH, threads: int | None = None,
                     say: Callable[[str], None] = print) -> Path:
    """``camo view``: ``OUT/index.html`` (default ``RUN_DIR/viewer/``) showing the run's result; returns its path."""
    from camo_base import atomic
    from evaluation.inputs import InputSpec, resolve
    from evaluation.report import method_label
    from optimizer import backend

    require_viewer_script()
    (entry,) = resolve([InputSpec("run", str(run_dir))])
    out = Path(out) if out else Path(run_dir) / "viewer"
    if out.exists() and not out.is_dir():
        raise SettingError.of("out", f" {out} exists and is not a folder")
    if video is None and (Path(run_dir) / "turntable.mp4").is_file():
        video = Path(run_dir) / "turntable.mp4"
    if video is not None and not Path(video).is_file():
        raise SettingError.of("video", f" {video}: no such file")
    from optimizer.scenes.cameras import cameras

    glb = glb_of(entry)
    stills = run_stills(entry.run)
    c = cameras(entry.pack)[0]
    camera = (stills[0].origin, stills[0].target, stills[0].fov) if stills else (c.origin, c.target, c.fov)
    backend.init(threads=threads)
    env = environment_panorama(entry.pack, env_width, say=say)
    bundle = Bundle(out)
    bundle.install_script()
    env_id = bundle.add_environment(env, entry.pack.name)
    cid = bundle.add(asset_id(entry.name, glb), glb, "model/gltf-binary")
    label = f"{method_label(entry.method, entry.ablation)}: {entry.name} ({entry.scene})"
    card = Card(cid, label, glb, env_id, stills, camera,
                "" if stills else "this run has no renders.npz: no path-traced stills")
    videos = []
    body = [f"<h1>{html.escape(label)}</h1>"]
    if video is not None:
        from camo_base.atomic import atomic_path

        dst = out / Path(video).name
        if Path(video).resolve() != dst.resolve():
            with atomic_path(dst) as tmp:
                shutil.copyfile(video, tmp)
        videos.append((dst.name, dst.name))
    body.append(limits_html(videos))
    body.append(card_html(card, env, 512))
    if videos:
        body.append(video_html(videos[0][0], "Path-traced turntable (the reference)"))
    atomic.write_text(out / "index.html", page(f"camo view: {entry.name}", "\n".join(body), bundle))
    return out / "index.html"


def video_html(href: str, caption: str) -> str:
    return (f'<figure><video src="{html.escape(href)}" controls loop muted playsinline preload="metadata" '
            f'style="max-width:100%;min-width:480px">'
            f'</video><figcaption>{html.escape(caption)} — <a href="{html.escape(href)}">{html.escape(href)}</a>'
            f'</figcaption></figure>')


def make_server(root: str | Path, port: int = 8030):
    """An HTTP server of ``root`` on 127.0.0.1:``port`` (0: any free port; ``server.server_port`` says which)."""
    import functools
    import http.server

    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise SettingError.of("port", f" must be an integer in [0, 65535], got {port!r}")

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *a):  # no line per request on the terminal
            pass

    handler = functools.partial(Quiet, directory=str(root))
    try:
        return http.server.ThreadingHTTPServer(("127.0.0.1", port), handler)
    except OSError as exc:
        raise SettingError(f"cannot listen on 127.0.0.1:{port} ({literal(exc.strerror or exc)}); try {{0}} 0",
                           "port") from None


def serve(srv, page_name: str = "index.html") -> None:
    """Run a :func:`make_server` server until Ctrl-C (the page also opens from disk; serving suits a remote machine
    with a forwarded port)."""
    print(f"serving http://127.0.0.1:{srv.server_port}/{page_name} (Ctrl-C stops)", flush=True)
    try:
        srv.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        srv.server_close()


# --------------------------------------------------------------------------------------------------------------
# the report's viewer section
# --------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Section:
    """Markdown and HTML of a report section (:func:`evaluation.report.write_report`'s ``sections``), and the
    viewer bundle its HTML needs (None: no viewer in it)."""

    md: list[str]
    html: list[str]
    bundle: Bundle | None = None

    @property
    def style(self) -> str:
        return STYLE if self.bundle is not None else ""

    @property
    def tail(self) -> str:
        return "\n" + self.bundle.script_tags() + "\n" + SCRIPT if self.bundle is not None else ""


def report_sections(eval_dirs: Sequence[str | Path], videos: Sequence[str | Path] = (), viewer: bool = True,
                    env_width: int = ENV_WIDTH, say: Callable[[str], None] = lambda m: None):
    """``sections`` for :func:`evaluation.report.write_report`: the turntables ``videos`` (copied into
    ``OUT/videos/``) and, with ``viewer``, the interactive viewer of every evaluated result. Checks the videos
    exist before anything is written (CamoError)."""
    for v in videos:
        if not Path(v).is_file():
            raise SettingError.of("video", f" {v}: no such file")
    if viewer and (env_width < 64 or env_width % 4):
        raise SettingError.of("env_width", f" must be a multiple of 4 and >= 64, got {env_width}")

    def make(out: Path) -> list[Section]:
        copied = copy_videos(videos, out)
        secs = [videos_section(copied)]
        if viewer:
            secs.append(report_section(eval_dirs, out, copied, env_width, say=say))
        return secs

    return make


def copy_videos(videos: Sequence[str | Path], out: Path) -> list[dict[str, Any]]:
    """Copy ``camo video`` outputs (and their animated previews) into ``out/videos/``; returns, per video, its href
    (relative to ``out``), preview href, label and record (:func:`evaluation.turntable.read_sidecar`)."""
    from camo_base.atomic import atomic_path
    from evaluation.turntable import read_sidecar

    done = []
    for v in videos:
        v = Path(v)
        if not v.is_file():
            raise SettingError.of("video", f" {v}: no such file")
        rec = read_sidecar(v) or {}
        item = {"label": v.name, "record": rec}
        for key, src in (("href", v), ("preview", Path(rec["preview"]) if rec.get("preview") else None)):
            if src is None or not src.is_file():
                continue
            dst = out / "videos" / src.name
            if src.resolve() != dst.resolve():
                with atomic_path(dst) as tmp:
                    shutil.copyfile(src, tmp)
            item[key] = dst.relative_to(out).as_posix()
        if rec.get("panels"):
            spp = rec.get("spp")
            item["label"] = (f"{v.name}: {' | '.join(rec['panels'])} ({rec.get('scene', '?')}, "
                             f"{rec.get('encoding', {}).get('frames', '?')} frames, {spp} spp)")
        done.append(item)
    return done


def _eval_inputs(eval_dirs: Sequence[str | Path]) -> list[dict[str, Any]]:
    """Every rendered input of the evaluations (run directories and assets; not triplets), once, with its stills
    (``renders.json`` images and the evaluation's cameras)."""
    from evaluation.evaldir import read_eval_config, renders_json

    seen: dict[str, dict[str, Any]] = {}
    for d in eval_dirs:
        d = Path(d).resolve()
        cfg = read_eval_config(d)
        scenes = {s.get("camera_set"): s for s in cfg.get("scenes", []) if isinstance(s, dict)}
        images: dict[str, dict[int, Path]] = {}
        for e in renders_json(d):
            try:
                images.setdefault(str(e["run"]), {})[int(e["view"])] = d / str(e["image"])
            except (KeyError, TypeError, ValueError):
                continue
        for r in cfg.get("runs", []):
            if not isinstance(r, dict) or r.get("kind") not in ("run", "asset") or not r.get("path"):
                continue
            key = f"{r['kind']}:{r['path']}"
            if key in seen:
                continue
            cams = scenes.get(r.get("camera_set"), {})
            stills = []
            for v, img in sorted(images.get(str(r.get("name")), {}).items()):
                try:
                    stills.append((img, tuple(cams["cameras"][v]), tuple(cams["targets"][v])))
                except (KeyError, IndexError, TypeError):
                    continue
            seen[key] = {**r, "stills": stills, "eval_dir": str(d),
                         "spp": (cfg.get("evaluate") or {}).get("spp")}
    return list(seen.values())


def report_section(eval_dirs: Sequence[str | Path], out: Path, videos: Sequence[dict[str, Any]] = (),
                   env_width: int = ENV_WIDTH, max_stills: int = 8,
                   say: Callable[[str], None] = lambda m: None) -> Section:
    """The report's "Interactive 3D viewer" section: per scene, a viewer of each evaluated run / asset with its
    evaluation stills (module docstring), the rasteriser's limits and the turntables ``videos`` (from
    :func:`copy_videos`) as the reference. Inputs that cannot be read any more (moved, deleted) are listed."""
    from evaluation.inputs import InputSpec, resolve
    from evaluation.report import method_label
    from optimizer.scenes.cameras import evenly_spaced

    refs = [(v["href"], v["label"]) for v in videos if v.get("href")]
    md = ["## Interactive 3D viewer", ""]
    ht = ["<h2>Interactive 3D viewer</h2>"]
    if viewer_script() is None:
        msg = (f"The interactive viewer needs its JavaScript (@google/model-viewer, pinned): run `{FETCH_COMMAND}` "
               "(make demo and make test do it), then `camo report` again.")
        say(f"warning: {msg}")
        return Section(md + [msg, ""], ht + [f"<p>{html.escape(msg)}</p>"])
    from optimizer import backend

    inputs = _eval_inputs(eval_dirs)
    missing, cards_by_scene = [], {}
    envs: dict[str, tuple[Environment, str]] = {}
    bundle = Bundle(out)
    for r in inputs:
        try:
            spec = InputSpec(r["kind"], r["path"], method=r.get("method"), scene=r.get("scene_source"),
                             placement=r.get("placement", "auto"), name=r.get("name"))
            (entry,) = resolve([spec])
            glb = glb_of(entry)
        except CamoError as exc:
            missing.append(f"{r.get('name')}: {exc}")
            continue
        backend.init()
        from evaluation.turntable import scene_key

        skey = scene_key(entry.pack)
        if skey not in envs:
            env = environment_panorama(entry.pack, env_width, say=say)
            envs[skey] = (env, bundle.add_environment(env, f"{entry.scene}-{skey[:8]}"))
        env, env_id = envs[skey]
        picked = [r["stills"][i] for i in evenly_spaced(len(r["stills"]), min(max_stills, len(r["stills"])))] \
            if r["stills"] else []
        stills = []
        for img, origin, target in picked:
            if img.is_file():
                stills.append(Still(img.read_bytes(), origin, target, entry.pack.cameras.fov,
                                    f"{img.stem.split('_obj')[0]}, {r.get('spp')} spp"))
        from optimizer.scenes.cameras import cameras

        c = cameras(entry.pack)[0]
        camera = (stills[0].origin, stills[0].target, stills[0].fov) if stills else (c.origin, c.target, c.fov)
        label = method_label(entry.method, entry.ablation)
        cid = bundle.add(asset_id(entry.name, glb), glb, "model/gltf-binary")
        cards_by_scene.setdefault(entry.scene, []).append(
            (Card(cid, f"{label} — {entry.name}", glb, env_id, stills, camera), env))
    if not cards_by_scene:
        note = "No result could be shown: " + ("; ".join(missing) if missing else "the evaluations hold no 3D result")
        return Section(md + [note, ""], ht + [f"<p>{html.escape(note)}</p>"])
    bundle.install_script()
    md += ["Open `report.html`: each result's glTF in an interactive viewer (orbit with the mouse), lit by the scene's "
           "environment, next to its path-traced evaluation views. The viewer is a rasteriser; what it approximates "
           "is listed there" + (", with the path-traced turntables as the reference: " +
                                ", ".join(f"[{t}]({h})" for h, t in refs) if refs else "") + ".", ""]
    ht.append(limits_html(refs))
    for scene, cards in sorted(cards_by_scene.items()):
        ht.append(f"<h3>{html.escape(scene)}</h3>")
        ht += [card_html(card, env, 384) for card, env in cards]
    if missing:
        md += ["Not shown (cannot be read): " + "; ".join(missing), ""]
        ht.append(f"<p>Not shown (cannot be read): {html.escape('; '.join(missing))}</p>")
    return Section(md, ht, bundle)


def videos_section(videos: Sequence[dict[str, Any]]) -> Section:
    """The report's "Path-traced turntables" section (the videos copied by :func:`copy_videos`)."""
    if not videos:
        return Section([], [])
    md, ht = ["## Path-traced turntables", ""], ["<h2>Path-traced turntables</h2>"]
    for v in videos:
        rec = v.get("record") or {}
        sec = rec.get("seconds") or {}
        enc = rec.get("encoding") or {}
        facts = []
        if enc:
            facts.append(f"{enc.get('width')}x{enc.get('height')} px, {enc.get('codec')}, "
                         f"{(enc.get('bytes') or 0) / 1e6:.2f} MB")
        if rec.get("integrator"):
            facts.append(f"{rec['integrator'].get('type')} max_depth {rec['integrator'].get('max_depth')}, "
                         f"{rec.get('spp')} spp, seed {rec.get('seed')}")
        if sec.get("per_frame"):
            facts.append(f"{sec['per_frame']:.2f} s per frame to render")
        text = v["label"] + (" (" + "; ".join(facts) + ")" if facts else "")
        md += [f"- [{text}]({v['href']})" + (f" — animated preview: ![]({v['preview']})" if v.get("preview") else ""),
               ""]
        ht.append(video_html(v["href"], text))
    return Section(md, ht)
