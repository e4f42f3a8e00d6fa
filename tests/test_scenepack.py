"""Scene-pack validation: good packs load, bad ones give one clear error (and exit code 2 via the CLI)."""

from __future__ import annotations

import math

import pytest

from camo.cli import main
from camo_base.errors import CamoError
from optimizer.scenes.scenepack import load_pack, parse_pack

GOOD = """
name = "yard"
[object]
primitive = "chair"
size = 1.2
rotation = [0, 0, 30]
translation = [0.5, -0.25]
[environment]
builtin = "gravel"
[cameras]
views = 8
radius = 5.0
elevation = 25
[render]
resolution = [96, 64]
spp = 4
[material]
albedo = [0.2, 0.3, 0.4]
transmittance = 0.0
"""


def write(tmp_path, text, name="pack.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_good_pack_loads_with_values(tmp_path):
    pack = load_pack(write(tmp_path, GOOD))
    assert pack.name == "yard"
    assert pack.object.primitive == "chair" and pack.object.size == 1.2
    assert pack.object.translation == (0.5, -0.25, 0.0)
    assert pack.render.resolution == (96, 64) and pack.render.spp == 4
    assert pack.cameras.views == 8 and pack.material.albedo == (0.2, 0.3, 0.4)
    assert pack.material.roughness == 0.0 and pack.material.eta == 1.5  # paper defaults


def test_defaults_follow_the_paper():
    pack = parse_pack({"object": {"primitive": "torus"}, "environment": {"builtin": "meadow"}})
    assert pack.cameras.views == 16 and pack.cameras.radius == 4.0
    m = pack.material
    assert (m.albedo, m.metallic, m.roughness, m.transmittance) == ((0.5, 0.5, 0.5), 0.0, 0.0, 0.5)
    assert pack.object.target_vertices == 30000


@pytest.mark.parametrize(
    "text, message",
    [
        (GOOD + "\n[extra]\nx = 1\n", "unknown key(s) at top level: extra"),
        (GOOD.replace("spp = 4", "spp = 4\nsamples = 3"), "unknown key(s) in [render]: samples"),
        (GOOD.replace('primitive = "chair"', 'mesh = "missing.obj"'), "mesh file not found"),
        (GOOD.replace('primitive = "chair"', 'primitive = "sofa"'), "unknown primitive 'sofa'"),
        (GOOD.replace("size = 1.2", "size = nan"), "[object] size must be finite"),
        (GOOD.replace("radius = 5.0", "radius = inf"), "[cameras] radius must be finite"),
        (GOOD.replace("radius = 5.0", "radius = 0.3"), "inside the object"),
        (GOOD.replace('builtin = "gravel"', 'panorama = "sky.exr"'), "panorama file not found"),
        (GOOD.replace("transmittance = 0.0", "transmittance = 1.5"), "[material] transmittance must be <= 1.0"),
        (GOOD.replace("views = 8", 'views = "many"'), "[cameras] views must be a number"),
        ("[object\n", "not valid TOML"),
    ],
)
def test_bad_packs_give_one_line_errors(tmp_path, text, message):
    p = write(tmp_path, text)
    with pytest.raises(CamoError) as exc:
        load_pack(p)
    assert message in str(exc.value)
    assert "\n" not in str(exc.value)


def test_cli_exit_code_2_and_one_line(tmp_path, capsys):
    p = write(tmp_path, GOOD.replace("size = 1.2", "size = nan"))
    assert main(["plan", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("camo: error:")


def test_missing_pack_file(capsys):
    assert main(["plan", "no/such/pack.toml"]) == 2
    assert "scene pack not found: no/such/pack.toml" in capsys.readouterr().err
    assert main(["plan", "nowhere"]) == 2
    assert "not a pack file and not a built-in scene" in capsys.readouterr().err


def test_list_cameras_and_targets(tmp_path):
    text = GOOD.replace("views = 8\nradius = 5.0\nelevation = 25",
                        'mode = "list"\npositions = [[4, 0, 1], [0, 4, 1]]\ntargets = [[0, 0, 0.5], [0, 0, 0.5]]')
    pack = load_pack(write(tmp_path, text))
    assert pack.cameras.views == 2
    assert pack.cameras.positions[1] == (0.0, 4.0, 1.0)


def test_mesh_path_relative_to_pack(tmp_path):
    import trimesh

    trimesh.creation.box().export(tmp_path / "crate.obj")
    pack = load_pack(write(tmp_path, GOOD.replace('primitive = "chair"', 'mesh = "crate.obj"')))
    assert pack.object.mesh == str((tmp_path / "crate.obj").resolve())
    assert math.isclose(pack.object.size, 1.2)
