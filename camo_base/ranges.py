"""Ranges of numeric settings: one :class:`Range` per setting, checked wherever a value arrives.

The same record checks a command-line flag (as its argparse ``type``: :meth:`Range.parse`), a grid file's value and
a run spec field (:meth:`Range.check`), so a limit is written once. :func:`convert` turns a plain value (a TOML
value, a parsed flag) into a setting's type the way argparse turns the flag's text, so a grid file and a command
line with the same settings give the same values (the run options of ``camo optimize``, the evaluation settings of
``camo evaluate``). ``tests/test_cli_ranges.py`` walks every numeric
flag of every command, reads its Range from the parser and tries values outside it.

    >>> Range(int, 1).check(0, "spp")
    Traceback (most recent call last):
    ...
    camo_base.errors.SettingError: spp must be an integer >= 1, got 0
    >>> Range(float, 0.0, 1.0, lo_open=True).describe()
    'a number in (0, 1]'
    >>> convert(["psnr", "ssim"], str, "metrics"), convert(2, float, "jitter", rng=Range(float, 0.0, 100.0))
    ('psnr,ssim', 2.0)
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from typing import Any

from camo_base.errors import SettingError, literal


@dataclasses.dataclass(frozen=True)
class Range:
    """``kind`` (int or float) values in ``[lo, hi]`` (either end open with ``lo_open`` / ``hi_open``; None: no
    bound). Floats must be finite."""

    kind: type
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, v: Any) -> bool:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return False
        if self.kind is int and not isinstance(v, int):
            return False
        if not math.isfinite(v):
            return False
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            return False
        return True

    def describe(self) -> str:
        what = "an integer" if self.kind is int else "a number"
        g = (lambda x: f"{x:g}") if self.kind is float else (lambda x: f"{x:d}" if isinstance(x, int) else f"{x:g}")
        if self.lo is not None and self.hi is not None:
            return f"{what} in {'(' if self.lo_open else '['}{g(self.lo)}, {g(self.hi)}{')' if self.hi_open else ']'}"
        if self.lo is not None:
            return f"{what} {'>' if self.lo_open else '>='} {g(self.lo)}"
        if self.hi is not None:
            return f"{what} {'<' if self.hi_open else '<='} {g(self.hi)}"
        return f"a finite {'integer' if self.kind is int else 'number'}"

    def check(self, v: Any, name: str, given: Any = None) -> Any:
        """``v`` when inside; SettingError naming ``name`` (``{0}``) otherwise, quoting ``given`` when it is the number
        as the user wrote it (``0``, not its conversion ``0.0``), else ``v``."""
        if not self.contains(v):
            shown = given if isinstance(given, (int, float)) and not isinstance(given, bool) else v
            raise SettingError(f"{{0}} must be {self.describe()}, got {literal(repr(shown))}", name)
        return v

    def parse(self, text: str) -> Any:
        """argparse ``type``: the text as ``kind``, inside the range; ArgumentTypeError (one line) otherwise."""
        try:
            v = self.kind(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"must be {self.describe()}, got {text!r}") from None
        if not self.contains(v):
            raise argparse.ArgumentTypeError(f"must be {self.describe()}, got {text!r}")
        return v

    def arg_type(self):
        """A callable for ``add_argument(type=...)`` that carries this range (``.range``) for the flag walk."""
        def parse(text: str):
            return self.parse(text)

        parse.range = self  # type: ignore[attr-defined]
        parse.__name__ = self.kind.__name__  # argparse names the type in its messages
        return parse

    def outside(self) -> list[Any]:
        """Values just outside the range (and NaN / infinity for floats), for tests."""
        out: list[Any] = []
        step = 1 if self.kind is int else 1e-6
        if self.lo is not None:
            out.append(self.lo if self.lo_open else (self.lo - step if self.kind is float else int(math.ceil(self.lo)) - 1))
        if self.hi is not None:
            out.append(self.hi if self.hi_open else (self.hi + step if self.kind is float else int(math.floor(self.hi)) + 1))
        if self.kind is float:
            out += [math.nan, math.inf]
        return out


def _kind_text(kind: type) -> str:
    return {int: "an integer", float: "a number", str: "a string or a list"}.get(kind, "a value")


def convert(value: Any, kind: type, name: str, *, choices: tuple[str, ...] | None = None,
            rng: Range | None = None) -> Any:
    """``value`` as a setting of type ``kind`` (int, float, str, or bool: a switch), as argparse converts the text
    of its flag: a str setting takes a list as its comma-joined items and one of ``choices`` when given; a number
    must be finite and inside ``rng``. SettingError naming ``name`` (``{0}``) otherwise."""
    if kind is bool:
        if not isinstance(value, bool):
            raise SettingError(f"{{0}} is a flag: write true or false, not {literal(repr(value))}", name)
        return value
    if isinstance(value, bool) or isinstance(value, dict) or value is None:
        raise SettingError(f"{{0}} must be {_kind_text(kind)}, not {literal(repr(value))}", name)
    if kind is str:
        if isinstance(value, (list, tuple)):
            if not value or any(isinstance(v, (list, tuple, dict, bool)) for v in value):
                raise SettingError(f"{{0}}: a list must hold plain numbers or strings, got {literal(repr(value))}", name)
            value = ",".join(str(v) for v in value)
        text = str(value)
        if choices is not None and text not in choices:
            raise SettingError(f"{{0}} must be one of {', '.join(choices)}, got {literal(repr(text))}", name)
        return text
    if isinstance(value, (list, tuple)):
        raise SettingError(f"{{0}} must be {_kind_text(kind)}, not {literal(repr(value))}", name)
    if isinstance(value, float) and not math.isfinite(value):
        raise SettingError(f"{{0}} must be finite, got {literal(repr(value))}", name)
    try:
        v = kind(value) if isinstance(value, str) or kind is float else value
    except (TypeError, ValueError):
        raise SettingError(f"{{0}} must be {_kind_text(kind)}, got {literal(repr(value))}", name) from None
    if kind is int and not isinstance(v, int):
        raise SettingError(f"{{0}} must be an integer, got {literal(repr(value))}", name)
    if rng is not None:
        rng.check(v, name, given=value)  # the error quotes what was written: 0, not 0.0
    return v
