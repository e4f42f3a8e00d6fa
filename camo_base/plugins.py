"""Discovery of the modules of a registry package: the one dynamic import of the code base.

A registry whose entries are modules (the baselines of :mod:`optimizer.optimise.methods`, the metrics of
:mod:`evaluation.metrics.registry`) calls :func:`submodules` with its package's name **as a string literal**;
``tests/test_layering.py`` reads such calls as imports of every module of that package, so the layering and
cycle checks see them like any ``import`` statement. Nothing else in the tree imports by computed name (the
layering test refuses it).
"""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType


def submodules(package: str) -> list[ModuleType]:
    """The modules directly inside ``package`` (not sub-packages, not ``_private`` ones), imported, by name.

    >>> [m.__name__ for m in submodules("camo_base")][:2]
    ['camo_base.atomic', 'camo_base.documents']
    """
    pkg = importlib.import_module(package)
    names = sorted(info.name for info in pkgutil.iter_modules(pkg.__path__)
                   if not info.ispkg and not info.name.startswith("_"))
    return [importlib.import_module(f"{package}.{name}") for name in names]
