"""Stand-ins for the registry data (``data/real``): files named as ``data_manifests/pmndrs_hdris.toml`` and
``registry_objects.toml`` land them, so the real packs and grids validate on a clean clone that has not run
``camo data fetch`` (CI). Imported by tests/test_data_registry.py and tests/test_grid.py."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from optimizer.scenes.data import registry as reg
from optimizer.scenes.data.manifest import load_manifest

REPO = Path(__file__).resolve().parents[1]
MANIFESTS = REPO / "data_manifests"

#: A tetrahedron with +Y up, as the registry's OBJ files are before ``obj_y_up_to_z_up``.
Y_UP_OBJ = "# a tetrahedron, +Y up\nmtllib t.mtl\nv 0 0 0\nv 1 0 0\nv 0 0 1\nv 0 2 0\nvn 0 1 0\nusemtl m\nf 1 2 3\nf 1 2 4\nf 2 3 4\nf 1 3 4\n"


def fake_real_data(root: Path) -> None:
    """Write ``root/data/real`` with an 8 x 16 panorama of ones per HDRI and a tetrahedron per object."""
    d = root / "data" / "real"
    d.mkdir(parents=True)
    for m in ("pmndrs_hdris.toml", "registry_objects.toml"):
        for a in load_manifest(MANIFESTS / m).assets:
            if a.kind == "hdri":
                (d / a.filename).write_bytes(reg.write_exr_float32(np.ones((8, 16, 3), np.float32)))
            else:
                (d / a.filename).write_text(Y_UP_OBJ)


def tree_with_fake_real_data(root: Path) -> Path:
    """A copy of the repository's ``grids/`` and ``packs/`` under ``root`` beside fake ``data/real``; returns
    ``root``. Grid and pack paths are relative, so the copies resolve to the stand-ins."""
    for name in ("grids", "packs"):
        shutil.copytree(REPO / name, root / name, ignore=shutil.ignore_patterns("*.py", "__pycache__"))
    fake_real_data(root)
    return root
