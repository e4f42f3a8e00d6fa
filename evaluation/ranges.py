"""The range of every numeric evaluation setting: :class:`evaluation.evaluate.EvalSettings` checks them, and each
numeric flag of ``camo evaluate`` parses with its range (one place a limit is written; a light module, so that
``camo --help`` imports nothing heavy)."""

from __future__ import annotations

from camo_base.ranges import Range

RANGES: dict[str, Range] = {
    "views": Range(int, 1, 1024),
    "jitter": Range(float, 0.0, 100.0, lo_open=True),
    "spp": Range(int, 1, 2**20),
    "resolution": Range(int, 8, 8192),
    "seed": Range(int, 0, 2**63 - 1),
    "threads": Range(int, 1, 4096),
    "seconds": Range(float, 0.0, None),
    "env_width": Range(int, 64, 16384),  # the report viewer's panorama (evaluation.viewer: a multiple of 4, too)
}
