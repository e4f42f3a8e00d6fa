"""Regenerate the real scene packs of this folder from the registry manifests (``camo data pack``).

    camo data fetch data_manifests/pmndrs_hdris.toml --dest data/real
    camo data fetch data_manifests/registry_objects.toml --dest data/real
    python packs/real/make_packs.py          # rewrites packs/real/*.toml

Packs: ``hdri_<name>.toml`` (each HDRI with the built-in panorama's default object, a utility box),
``object_<name>.toml`` (each object on the built-in meadow) and ``<hdri>-<object>.toml`` (the pairs of
``grids/real.toml``) and ``cross/<hdri>-<object>.toml`` (every HDRI of the pairs with every object of the pairs,
8 x 8, for ``grids/real_cross.toml``). Every pack starts at roughness 0.5 (the built-in scenes' start: each of these
environments has a compact light, a sun or lamps, that a smooth start mirrors as glints).
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
DATA = REPO / "data" / "real"
HDRIS = REPO / "data_manifests" / "pmndrs_hdris.toml"
OBJECTS = REPO / "data_manifests" / "registry_objects.toml"

#: HDRI i with object i (grids/real.toml): sun, overcast, forest shade, dawn, low sun, dusk, two interiors.
PAIRS = [("sky", "duck"), ("city", "cone"), ("forest", "teddy"), ("dawn", "soccerball"), ("sunset", "mug"),
         ("venice", "duplo"), ("apartment", "bunny"), ("warehouse", "tray")]

MATERIAL = "\n# Start rough (as the built-in scenes): a compact light mirrored by a smooth start stays as glints.\n" \
           "[material]\nroughness = 0.5\n"


def main() -> int:
    sys.path.insert(0, str(REPO))
    from camo.cli import main as camo
    from optimizer.scenes.data.manifest import load_manifest

    hdris = [a.name for a in load_manifest(HDRIS).assets]
    objects = [a.name for a in load_manifest(OBJECTS).assets]
    jobs = []
    for h in hdris:
        short = h.removeprefix("pmndrs_")
        jobs.append((HERE / f"hdri_{short}.toml", [str(HDRIS), h, "--name", f"real-{short}"]))
    for o in objects:
        jobs.append((HERE / f"object_{o}.toml", [str(OBJECTS), o, "--builtin", "meadow", "--name", f"{o}-in-meadow"]))
    for h, o in PAIRS:
        jobs.append((HERE / f"{h}-{o}.toml", [str(HDRIS), f"pmndrs_{h}", "--with", f"{OBJECTS}:{o}",
                                              "--name", f"real-{h}-{o}"]))
    cross = HERE / "cross"
    cross.mkdir(exist_ok=True)
    for h, _ in PAIRS:
        for _, o in PAIRS:
            jobs.append((cross / f"{h}-{o}.toml", [str(HDRIS), f"pmndrs_{h}", "--with", f"{OBJECTS}:{o}",
                                                  "--name", f"real-{h}-{o}"]))
    for out, args in jobs:
        rc = camo(["data", "pack", *args, "--dest", str(DATA), "--out", str(out), "--overwrite"])
        if rc != 0:
            return rc
        out.write_text(out.read_text(encoding="utf-8") + MATERIAL, encoding="utf-8")
    print(f"{len(jobs)} packs in {HERE}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
