"""Stage 1 of the flow, the scene: scene packs and the built-in scenes, environments (panoramas, procedural
skies, Mitsuba XML), primitives and mesh preparation (remeshing, UV atlas), cameras and the object's pose, and
fetching real data (``optimizer.scenes.data``). Imports only :mod:`camo_base` and :mod:`optimizer.backend`."""
