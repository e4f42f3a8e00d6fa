"""Shared test set-up: a per-session cache folder, the Mitsuba backend on demand, and helpers for bench/ scripts."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import numpy as np
import pytest

# Keep generated caches (prepared meshes, panoramas) inside the repo's ignored .cache
# folder so tests never depend on a user's home directory state.
os.environ.setdefault("CAMO_CACHE", str(Path(__file__).resolve().parents[1] / ".cache" / "camo"))


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
