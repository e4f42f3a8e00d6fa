"""Stage 4 of the flow, the asset: the owner of every file format a result lives in. The run directory is
written and read by :mod:`~optimizer.assets.rundir` / :mod:`~optimizer.assets.result`; GLB/glTF, OBJ+MTL and PLY
by :mod:`~optimizer.assets.export` (writers) and :mod:`~optimizer.assets.asset` (readers); Mitsuba scene XML by
:mod:`~optimizer.assets.scene_xml`. The optimiser writes through it and evaluation reads through it, so
evaluating a result never needs the optimiser. Imports :mod:`optimizer.rendering`, :mod:`optimizer.scenes` and
:mod:`camo_base`."""
