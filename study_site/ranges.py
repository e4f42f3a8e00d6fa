"""The range of every numeric study setting, written once: the site's config check (:func:`study_site.config.resolve`),
the simulated participants (:func:`study_site.simulate.run_simulation`) and the flags of ``camo study`` that set them
parse with these (a light module: ``camo --help`` imports nothing heavy).

>>> CONFIG_RANGES["PRACTICE_TRIALS"].describe()
'an integer in [0, 50]'
"""

from __future__ import annotations

from camo_base.ranges import Range

ADULT_AGE = 18  # the study takes adults only: the youngest age bracket starts here or later

CONFIG_RANGES: dict[str, Range] = {
    "TRIAL_TIME_LIMIT_S": Range(float, 1.0, 600.0),
    "PRACTICE_TRIALS": Range(int, 0, 50),
    "DEADLINE_GRACE_S": Range(float, 0.0, 30.0),
    "RT_FLOOR_MS": Range(float, 0.0, 5000.0),
    "CLOCK_TOLERANCE_MS": Range(float, 50.0, 10000.0),
    "DISPLAY_HEIGHT_SHARE": Range(float, 0.2, 1.0),
    "DISPLAY_MAX_WIDTH_SHARE": Range(float, 0.2, 1.0),
    # the flag also parses 10-17 so that an under-age value gets the "adults only" reason, not a bare range
    "MIN_AGE": Range(int, ADULT_AGE, 99),
}

SIMULATE_RANGES: dict[str, Range] = {
    "participants": Range(int, 1, 10_000),
    "concurrency": Range(int, 1, 500),
    "max_seconds": Range(float, 1.0, 86_400.0),
    "ramp": Range(float, 0.0, 86_400.0),
}
