"""Provenance of a result: the versions of camo and of the libraries that computed it, and the backend it ran on.

Recorded in a run's ``config.toml`` (``[versions]``) and an evaluation's ``eval_config.toml``. Nothing heavy is
imported until :func:`versions` is called (it imports Mitsuba and Dr.Jit, which the caller has loaded anyway).
"""

from __future__ import annotations

import platform

from camo_base import __version__


def versions() -> dict[str, str]:
    """``{camo, python, mitsuba, drjit, numpy[, torch][, variant, threads]}`` as strings.

    ``variant`` and ``threads`` are the Mitsuba variant set in this process and Dr.Jit's thread count; both are
    absent before a variant is set (:func:`optimizer.backend.init`). ``torch`` is absent when torch is not
    installed."""
    import drjit
    import mitsuba
    import numpy

    out = {"camo": __version__, "python": platform.python_version(), "mitsuba": mitsuba.__version__,
           "drjit": drjit.__version__, "numpy": numpy.__version__}
    try:
        import torch

        out["torch"] = torch.__version__
    except ImportError:
        pass
    variant = mitsuba.variant()
    if variant:
        out["variant"] = str(variant)
        out["threads"] = str(drjit.thread_count())
    return out
