"""Reading TOML and JSON documents a user gives or a command wrote, with one-line errors.

``what`` names the document in the message (``"scene pack"``, ``"manifest"``): a missing file is
``<what> not found: <path>``, an unreadable one ``cannot read <what> <path>: <reason>``, a malformed one
``<what> <path> is not valid TOML|JSON: <parser's message>``, and a JSON document of the wrong type (``expect``)
``<what> <path>: expected a JSON list|object``. All are :class:`~camo_base.errors.CamoError`.
"""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path
from typing import Any

from camo_base.errors import CamoError

_JSON_TYPES = {list: "list", dict: "object"}


def _text(path: Path, what: str) -> str:
    if not path.is_file():
        raise CamoError(f"{what} not found: {path}")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise CamoError(f"{what} {path} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise CamoError(f"cannot read {what} {path}: {exc.strerror or exc}") from None


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())


def read_toml(path: str | os.PathLike, what: str) -> dict[str, Any]:
    """The TOML document at ``path`` as a dict."""
    p = Path(path)
    text = _text(p, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CamoError(f"{what} {p} is not valid TOML: {_one_line(exc)}") from None


def read_json(path: str | os.PathLike, what: str, expect: type | None = None) -> Any:
    """The JSON document at ``path``; with ``expect`` (``list`` or ``dict``) it must be of that type."""
    p = Path(path)
    text = _text(p, what)
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise CamoError(f"{what} {p} is not valid JSON: {_one_line(exc)}") from None
    if expect is not None and not isinstance(data, expect):
        raise CamoError(f"{what} {p}: expected a JSON {_JSON_TYPES.get(expect, expect.__name__)}")
    return data
