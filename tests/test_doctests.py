"""The examples in the docstrings are run: a module's ``>>>`` lines are part of its manual (as in kornia and
scikit-image), so an example that no longer holds fails here instead of misleading a reader.

Every module of the toolkit's packages whose source has a ``>>>`` line is imported and its examples run with
:mod:`doctest` (``ELLIPSIS`` on, as tracebacks are written with ``...``). ``study_site/wsgi.py`` is the one module
that cannot be imported without a deployment's settings; it has no examples.
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("camo_base", "optimizer", "evaluation", "study_site", "camo")


def modules_with_examples() -> list[str]:
    """Dotted names of the packages' modules whose source holds a ``>>>`` example."""
    names = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if ">>> " in path.read_text(encoding="utf-8"):
                rel = path.relative_to(ROOT).with_suffix("")
                parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
                names.append(".".join(parts))
    return names


def test_the_examples_are_found():
    names = modules_with_examples()
    assert "evaluation.settings" in names and "optimizer.optimise.adam" in names and len(names) >= 30


@pytest.mark.parametrize("name", modules_with_examples())
def test_docstring_examples_hold(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed (run python -m " \
                               f"pytest --doctest-modules {name.replace('.', '/')}.py for the diff)"
