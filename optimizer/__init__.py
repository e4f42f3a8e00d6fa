"""camo optimiser: scenes, rendering and appearance optimisation for 3D camouflage.

Data flow of the toolkit: scene -> render -> optimise -> asset -> evaluate ->
stimuli -> study -> analysis. This package covers the first four steps;
``evaluation`` and ``study_site`` cover the rest.
"""

from camo_base import __version__  # noqa: F401 - the toolkit's version, owned by camo_base
