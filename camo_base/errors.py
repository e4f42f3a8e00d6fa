"""User-facing errors.

Anything a user can cause (a bad scene pack, a missing file, a corrupt
checkpoint) raises :class:`CamoError`. The CLI prints it as one line and exits
with status 2; it never shows a traceback for these.
"""


class CamoError(Exception):
    """An error caused by the user's input; printed as one line, exit code 2."""

    exit_code = 2
