"""What a method is to the rest of the tool: :class:`Method`, the record each method module declares.

A baseline module in :mod:`optimizer.optimise.baselines` declares its methods in a module-level ``METHODS`` tuple;
:mod:`optimizer.optimise.methods` collects them (and ``ours``) into the one registry that ``camo optimize
--method``, the run spec, the grid and the docs read. This module imports no method, so every method module may
import it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

#: What every method reads of a run spec: the scene, the seed, the background targets and loss domain (the target
#: spp, Stage 1's loss settings), the albedo atlas' resolution and the index of refraction, the effect planner's
#: inputs.
COMMON_READS = ("scene", "pack", "method", "seed", "preset", "spp.target", "stage1.loss", "stage1.alpha", "stage1.eps",
                "stage1.domain", "stage1.domain_dilate", "stage1.shadow_threshold", "appearance.map_resolution",
                "appearance.eta", "planner", "shadow_gradients")


@dataclasses.dataclass(frozen=True)
class Method:
    """One ``--method`` and what it reads of a run spec.

    ``reads``: spec fields (``"stage1.iterations"``) or whole tables (``"stage2"``, ``"options"``); ``"*"`` is
    every field but ``options``. ``options``: the dataclass of the method's own options (``[options]`` of its
    spec; None: it has none). ``option_names``: ``camo optimize`` option names (the flags, ``-`` as ``_``; also the
    keys of a grid's ``[optimize]`` table) that set the method's own options instead of the field they set for
    ``ours`` -- ``--iterations`` is GANmouflage's training iterations, not Stage 1's. ``compute(setup, options,
    progress) -> (values, history, info)``: a baseline's work on its :class:`~optimizer.optimise.baselines.common.
    Setup` (None for ``ours``, which :mod:`optimizer.optimise.run` drives). ``variants``: further ``--method``
    names that are this method with other default options, ``(name, options factory)``."""

    name: str
    summary: str
    reads: tuple[str, ...] = COMMON_READS
    options: type | None = None
    option_names: tuple[tuple[str, str], ...] = ()
    compute: Callable[[Any, Any, bool], tuple[dict, list, dict]] | None = None
    variants: tuple[tuple[str, Callable[[], Any]], ...] = ()

    def reads_path(self, path: str) -> bool:
        """Whether the method reads spec field ``path`` (dotted: ``"stage2.iterations"``, ``"options.backend"``)."""
        if path == "spec_version":
            return True
        if path == "options" or path.startswith("options."):
            return self.options is not None
        for r in self.reads:
            if r == "*" or path == r or path.startswith(r + "."):
                return True
        return False

    def make_options(self) -> Any:
        """The method's default options (None when it has none)."""
        return self.options() if self.options is not None else None
