"""camo optimiser: scenes, rendering and appearance optimisation for 3D camouflage.

Data flow of the toolkit: scene -> render -> optimise -> asset -> evaluate ->
stimuli -> study -> analysis. This package covers the first four steps;
``evaluation`` and ``study_site`` cover the rest.
"""

__version__ = "0.1.0"
