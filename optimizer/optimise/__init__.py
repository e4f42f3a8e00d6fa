"""Stage 3 of the flow, optimisation: losses (Eq. 2-6), Adam and schedules, the least-squares warm start,
Stage 1 (Sec. III-B), Stage 2 (Sec. III-C) with its inpainting backends, the baselines, and :mod:`~.run` that
drives a method and writes its run directory through :mod:`optimizer.assets`. Imports every lower stage."""
