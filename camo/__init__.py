"""The top layer: the ``camo`` command line (:mod:`camo.cli`), ``camo doctor`` and experiment grids
(:mod:`camo.grid`). The only package that imports all the others (see CONTRIBUTING.md for the layering)."""
