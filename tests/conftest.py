"""Shared test set-up: a per-session cache folder, the Mitsuba backend on demand, and helpers for bench/ scripts."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import numpy as np
import pytest

# The installed learned-metric weights (`camo data fetch data_manifests/lpips_weights.toml`, run by `make test`):
# where camo itself looks (evaluation.metrics.weights.weights_dir), taken before CAMO_CACHE is changed below. They
# are hidden from the tests by default, so that a test sees the same metrics on every machine; the tests of the
# real LPIPS ask for them with the `installed_lpips` fixture (skipped, with the fix, where they are missing).
# Kept in CAMO_TEST_INSTALLED_WEIGHTS for pytest-xdist's workers, which inherit the environment changed below.
INSTALLED_WEIGHTS = Path(os.environ.get("CAMO_TEST_INSTALLED_WEIGHTS") or os.environ.get("CAMO_WEIGHTS") or (
    Path(os.environ["CAMO_CACHE"]) if os.environ.get("CAMO_CACHE") else Path.home() / ".cache" / "camo") / "weights")
os.environ["CAMO_TEST_INSTALLED_WEIGHTS"] = str(INSTALLED_WEIGHTS)

# Keep generated caches (prepared meshes, panoramas) inside the repo's ignored .cache
# folder so tests never depend on a user's home directory state.
os.environ.setdefault("CAMO_CACHE", str(Path(__file__).resolve().parents[1] / ".cache" / "camo"))
_NO_WEIGHTS = Path(__file__).resolve().parents[1] / ".cache" / "camo-test-no-weights"
_NO_WEIGHTS.mkdir(parents=True, exist_ok=True)
os.environ["CAMO_WEIGHTS"] = str(_NO_WEIGHTS)


@pytest.fixture()
def installed_lpips(monkeypatch) -> Path:
    """The installed LPIPS weights folder, made visible to the code under test (and its subprocesses); skips the
    test with the command that installs them when they are missing (CI installs them: `make test`)."""
    from evaluation.metrics.weights import LPIPS_FILES, LPIPS_MANIFEST

    missing = [f for net in LPIPS_FILES.values() for f in net.values() if not (INSTALLED_WEIGHTS / f).is_file()]
    if missing:
        pytest.skip(f"LPIPS weights not installed in {INSTALLED_WEIGHTS} ({', '.join(missing)}): run "
                    f"camo data fetch {LPIPS_MANIFEST} --dest {INSTALLED_WEIGHTS}")
    monkeypatch.setenv("CAMO_WEIGHTS", str(INSTALLED_WEIGHTS))
    return INSTALLED_WEIGHTS


@pytest.fixture(scope="session")
def mi_backend():
    """Initialise the Mitsuba backend once; returns ``(mi, dr)``."""
    from optimizer import backend

    backend.init()
    import drjit as dr
    import mitsuba as mi

    return mi, dr


@pytest.fixture(autouse=True, scope="module")
def _restore_thread_count():
    """Tests that run `--threads 1` in-process must not leave Dr.Jit single-threaded for later modules."""
    yield
    from optimizer import backend

    if backend.info() is not None:
        backend.set_threads(backend.default_threads())


@pytest.fixture()
def cli(capsys):
    """``cli(*argv) -> (exit code, stdout, stderr)``: the ``camo`` command line run in-process."""
    from camo.cli import main

    def run(*argv) -> tuple[int, str, str]:
        capsys.readouterr()
        rc = main(list(argv))
        out, err = capsys.readouterr()
        return rc, out, err

    return run


@pytest.fixture()
def loopback_http(monkeypatch):
    """``serve(handler_class) -> "http://127.0.0.1:PORT/"``: a threading HTTP server on an ephemeral loopback port,
    stopped after the test. Nothing leaves this machine: proxies are cleared, and ``camo data``'s downloads
    (``optimizer.scenes.data.fetch._open``) fail the test for any host but 127.0.0.1 (timeouts capped at 5 s)."""
    import http.server
    import threading
    import urllib.parse

    from optimizer.scenes.data import fetch as fetch_mod

    for var in ("http_proxy", "https_proxy", "HTTP_PROXY", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("no_proxy", "127.0.0.1")
    real_open = fetch_mod._open

    def guarded_open(url, headers, timeout):
        assert urllib.parse.urlsplit(url).hostname == "127.0.0.1", f"test tried to reach {url}"
        return real_open(url, headers, min(timeout, 5.0))

    monkeypatch.setattr(fetch_mod, "_open", guarded_open)
    servers = []

    def serve(handler) -> str:
        httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        httpd.daemon_threads = True
        thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        thread.start()
        servers.append((httpd, thread))
        return f"http://127.0.0.1:{httpd.server_address[1]}/"

    yield serve
    for httpd, thread in servers:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=5)


@pytest.fixture(scope="session")
def tiny_metric_weights(tmp_path_factory) -> dict[str, str]:
    """Random (He-initialised, seed 0) weight files in the real key layouts, written once per session: an AlexNet
    trunk and LPIPS v0.1 linear layers (``lpips_dir``/``alexnet-test.pth`` and ``alex.pth``, also as
    ``lpips_trunk`` / ``lpips_lin``), a VGG16 trunk and its linear layers (``lpips_vgg_trunk`` / ``lpips_vgg_lin``)
    and an Inception v3 stem (``sifid``). These keys are what :func:`evaluation.metrics.compute_metrics` takes as
    weights."""
    import torch

    d = tmp_path_factory.mktemp("tiny_metric_weights")
    lp = d / "lpips"
    lp.mkdir()
    g = torch.Generator().manual_seed(0)
    trunk = {}
    alex_convs = {0: (64, 3, 11), 3: (192, 64, 5), 6: (384, 192, 3), 8: (256, 384, 3), 10: (256, 256, 3)}
    for i, (o, c, k) in alex_convs.items():
        trunk[f"features.{i}.weight"] = torch.randn(o, c, k, k, generator=g) * (2.0 / (c * k * k)) ** 0.5
        trunk[f"features.{i}.bias"] = 0.05 * torch.randn(o, generator=g)
    lin = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) * 0.1
           for k, c in enumerate((64, 192, 384, 256, 256))}
    inc = {}
    for name, cin, cout in (("Conv2d_1a_3x3", 3, 32), ("Conv2d_2a_3x3", 32, 32), ("Conv2d_2b_3x3", 32, 64)):
        inc[f"{name}.conv.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * (2.0 / (cin * 9)) ** 0.5
        inc[f"{name}.bn.weight"] = 1 + 0.1 * torch.randn(cout, generator=g)
        inc[f"{name}.bn.bias"] = 0.1 * torch.randn(cout, generator=g)
        inc[f"{name}.bn.running_mean"] = 0.1 * torch.randn(cout, generator=g)
        inc[f"{name}.bn.running_var"] = 0.5 + torch.rand(cout, generator=g)
    vgg, c = {}, 3
    convs = [i for i, v in enumerate((64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512,
                                      512)) if v != "M"]
    widths = (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512)
    idx = 0
    for j, o in enumerate(widths):  # torchvision's features indices: conv, relu (, pool)
        vgg[f"features.{idx}.weight"] = torch.randn(o, c, 3, 3, generator=g) * (2.0 / (c * 9)) ** 0.5
        vgg[f"features.{idx}.bias"] = 0.05 * torch.randn(o, generator=g)
        c = o
        idx += 3 if j + 1 < len(convs) and convs[j + 1] - convs[j] == 2 else 2
    vgg_lin = {f"lin{k}.model.1.weight": torch.rand(1, c_, 1, 1, generator=g) * 0.1
               for k, c_ in enumerate((64, 128, 256, 512, 512))}
    torch.save(trunk, lp / "alexnet-test.pth")
    torch.save(lin, lp / "alex.pth")
    torch.save(vgg, lp / "vgg16-test.pth")
    torch.save(vgg_lin, lp / "vgg.pth")
    torch.save(inc, d / "inception_v3_google-test.pth")
    return {"lpips_dir": str(lp), "lpips_trunk": str(lp / "alexnet-test.pth"), "lpips_lin": str(lp / "alex.pth"),
            "lpips_vgg_trunk": str(lp / "vgg16-test.pth"), "lpips_vgg_lin": str(lp / "vgg.pth"),
            "sifid": str(d / "inception_v3_google-test.pth")}


@pytest.fixture(scope="session")
def bench_module():
    """``bench_module("grid_figures")`` imports ``bench/grid_figures.py`` (bench/ is not a package)."""
    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / "bench" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    return load


@pytest.fixture(scope="session")
def write_eval_renders():
    """``write(ev, bg, img, mask, views=2, **fields)``: a ``camo evaluate`` folder's 8-bit renders and renders.json,
    the same images in every view; ``fields`` are added to each record (e.g. ``run="box"``)."""
    def write(ev: Path, bg: np.ndarray, img: np.ndarray, mask: np.ndarray, views: int = 2, **fields) -> None:
        from PIL import Image

        (ev / "renders").mkdir(parents=True)
        recs = []
        for v in range(views):
            for kind, arr in (("bg", bg), ("obj", img), ("mask", mask)):
                Image.fromarray(arr).save(ev / "renders" / f"view_{v}_{kind}.png")
            recs.append({"background": f"renders/view_{v}_bg.png", "image": f"renders/view_{v}_obj.png",
                         "mask": f"renders/view_{v}_mask.png", "view": v, **fields})
        (ev / "renders.json").write_text(json.dumps(recs))
    return write


@pytest.fixture(scope="session")
def postgres_url():
    """A throw-away PostgreSQL database for the study's storage tests: CAMO_TEST_POSTGRES_URL when set (a
    database named *test*, whose study tables are dropped), else a private cluster started here (initdb +
    pg_ctl in a temporary folder, unix socket only; `.ci/system-deps postgresql` installs the server if
    missing) and deleted afterwards."""
    url = os.environ.get("CAMO_TEST_POSTGRES_URL", "")
    if url:
        from sqlalchemy.engine import make_url

        if "test" not in (make_url(url).database or ""):
            pytest.fail("CAMO_TEST_POSTGRES_URL must name a throw-away database whose name contains 'test'")
        yield url
        return
    try:
        import psycopg  # noqa: F401
    except ImportError:
        pytest.fail("psycopg is missing (the PostgreSQL driver): pip install -e '.[dev]' (or '.[postgres]')")
    from study_site.testing import ThrowawayPostgres

    pg = ThrowawayPostgres(install=True)
    try:
        yield pg.start()
    finally:
        pg.stop()
