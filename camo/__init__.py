"""The top layer: the ``camo`` command line (:mod:`camo.cli`), ``camo doctor`` and experiment grids
(:mod:`camo.grid`). The only package that imports all the others (see CONTRIBUTING.md for the layering)."""


def _lpips_gradients(net: str):
    """The optimiser's perceptual term's network (:mod:`optimizer.optimise.perceptual`): LPIPS from the
    evaluation's metric module, which the optimiser layer may not import itself."""
    from evaluation.metrics.lpips import lpips_linear_grad

    return lpips_linear_grad(net)


def _register() -> None:
    from optimizer.optimise import perceptual

    perceptual.provide(_lpips_gradients)


_register()
