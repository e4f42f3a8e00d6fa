"""User-facing errors.

Anything a user can cause (a bad scene pack, a missing file, a corrupt
checkpoint) raises :class:`CamoError`. The CLI prints it as one line and exits
with status 2; it never shows a traceback for these.

A library function names a setting by its own name (a run spec field such as
``spp.train``, an argument such as ``resume``); :class:`SettingError` keeps those
names apart from the text, so a front end can show them as its own (``camo
optimize`` shows ``--spp``, ``--resume``; a grid file its keys).
"""

from __future__ import annotations

from typing import Callable, Mapping


class CamoError(Exception):
    """An error caused by the user's input; printed as one line, exit code 2."""

    exit_code = 2


class SettingError(CamoError):
    """A CamoError about named settings: ``template`` names them ``{0}``, ``{1}``, ... (``str()`` shows the
    library's names; :meth:`renamed` a front end's).

    >>> e = SettingError("{0} must be >= 1, got 0", "spp.train")
    >>> str(e), e.renamed({"spp.train": "--spp"})
    ('spp.train must be >= 1, got 0', '--spp must be >= 1, got 0')
    """

    def __init__(self, template: str, *names: str):
        self.template, self.names = template, tuple(names)
        super().__init__(template.format(*names))

    @classmethod
    def of(cls, name: str, rest: str) -> "SettingError":
        """A message that starts with the setting ``name``; ``rest`` is plain text (its braces are kept as they are).

        >>> e = SettingError.of("env_width", " must be >= 64, got {3}")
        >>> str(e), e.renamed({"env_width": "--env-width"})
        ('env_width must be >= 64, got {3}', '--env-width must be >= 64, got {3}')
        """
        return cls("{0}" + literal(rest), name)

    def renamed(self, rename: Mapping[str, str] | Callable[[str], str]) -> str:
        """The message with each name passed through ``rename`` (a mapping: names it lacks stay as they are)."""
        fn = rename if callable(rename) else (lambda n: rename.get(n, n))
        return self.template.format(*(fn(n) for n in self.names))


def literal(text: object) -> str:
    """``text`` for a :class:`SettingError` template: its braces doubled (user input may hold some)."""
    return str(text).replace("{", "{{").replace("}", "}}")


def renamed(exc: CamoError, rename: Mapping[str, str] | Callable[[str], str]) -> str:
    """The one-line message of ``exc`` with its setting names passed through ``rename`` (any CamoError)."""
    return exc.renamed(rename) if isinstance(exc, SettingError) else str(exc)
