"""Shared test set-up: a per-session cache folder, and the Mitsuba backend on demand."""

from __future__ import annotations

import os
from pathlib import Path

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
