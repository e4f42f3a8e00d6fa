"""Shared pieces every camo package may import: one error type (:mod:`camo_base.errors`), atomic writes
(:mod:`camo_base.atomic`), colour conversions and image files (:mod:`camo_base.imaging`), seed streams
(:mod:`camo_base.seeds`), provenance (:mod:`camo_base.provenance`: library versions). It imports nothing of camo's
and never Mitsuba, Dr.Jit or torch at import time.
"""

#: The toolkit's version (pyproject.toml); :data:`optimizer.__version__` is this one.
__version__ = "0.1.0"
