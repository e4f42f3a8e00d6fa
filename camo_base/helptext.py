"""Help text computed when it is shown: command-line help generated from a registry whose import is not free.

``camo --help`` and every command build the whole parser; a registry that imports its entries (the metrics import
torch, the baselines numpy) would make every command slower just to have its help ready. :class:`Deferred` is a
help string argparse formats only when ``--help`` prints it.

    >>> import argparse
    >>> p = argparse.ArgumentParser(prog="x")
    >>> _ = p.add_argument("--n", help=Deferred(lambda: "one of: " + ", ".join(["a", "b"])))
    >>> "one of: a, b" in p.format_help()
    True
"""

from __future__ import annotations

from typing import Callable


class Deferred:
    """A help string made by ``make()`` the first time argparse formats it (``%`` with its parameters)."""

    def __init__(self, make: Callable[[], str]):
        self._make = make
        self._text: str | None = None

    def __str__(self) -> str:
        if self._text is None:
            self._text = str(self._make())
        return self._text

    def __bool__(self) -> bool:
        return True

    def strip(self) -> str:
        return str(self).strip()

    def __contains__(self, item: str) -> bool:
        return item in str(self)

    def __mod__(self, params) -> str:
        return str(self) % params
