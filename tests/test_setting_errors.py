"""Library errors name settings, the CLI names flags (CONTRIBUTING: "library code does not speak argparse").

A library function raises :class:`camo_base.errors.SettingError` naming its own setting (``out``, ``time_budget``);
``camo`` shows it as the flag whose argparse ``dest`` that setting is (``--out``, ``--time-budget``).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from camo.cli import main
from camo_base.errors import SettingError

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ("camo_base", "optimizer", "evaluation", "study_site")


def _message_start(node: ast.expr) -> str | None:
    """The literal text a message expression starts with ("" when it starts with a value), None if not a string."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        first = node.values[0] if node.values else None
        return first.value if isinstance(first, ast.Constant) else ""
    return None


FLAG = re.compile(r"(?<![\\w-])--[a-z]")


def _texts(node: ast.AST) -> list[str]:
    """The literal text pieces of an expression (string constants, f-string parts), nested calls included."""
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def _flag_phrased_raises(path: Path, root: Path = ROOT) -> list[str]:
    """``file:line`` of each ``raise CamoError / SettingError(...)`` whose message mentions a flag anywhere (at its
    start or mid-sentence as advice: "try --port 0")."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call) and node.exc.args:
            name = getattr(node.exc.func, "id", getattr(node.exc.func, "attr", ""))
            if name in ("CamoError", "SettingError", "of") and any(FLAG.search(t) for a in node.exc.args
                                                                    for t in _texts(a)):
                out.append(f"{path.relative_to(root)}:{node.lineno}")
    return out


def test_no_library_error_mentions_a_flag():
    """Every library ``raise CamoError("--flag ...")`` names its setting instead (SettingError.of), and so does
    advice in mid-sentence ("try {0} 0", "port": the CLI shows ``--port``)."""
    files = [p for pkg in LIBRARY for p in sorted((ROOT / pkg).rglob("*.py")) if p.name != "cli.py"]
    assert len(files) > 50
    bad = [hit for p in files for hit in _flag_phrased_raises(p)]
    assert bad == [], f"library errors phrased as CLI flags: {bad}"


def test_the_checker_sees_a_flag_phrased_error(tmp_path):
    p = tmp_path / "m.py"
    p.write_text('def f(x):\n    raise CamoError(f"--out {x} exists")\n\n\ndef g(x):\n'
                 '    raise SettingError.of("out", f" {x} exists")\n\n\ndef h(x):\n'
                 '    raise CamoError(f"cannot listen on {x}; try --port 0")\n\n\ndef k(x):\n'
                 '    raise SettingError(f"cannot listen on {x}; try {{0}} 0", "port")\n')
    assert _flag_phrased_raises(p, tmp_path) == ["m.py:2", "m.py:10"]


def test_setting_error_of_keeps_braces_and_renames():
    e = SettingError.of("practice_scenes", ": no such scene {a}")
    assert str(e) == "practice_scenes: no such scene {a}"
    assert e.renamed({"practice_scenes": "--practice-scenes"}) == "--practice-scenes: no such scene {a}"


@pytest.mark.parametrize("argv, expected", [
    # a library error (evaluation.evaluate) shown with the command's flag
    (["evaluate", "RUN", "--metrics", ",", "--out", "{tmp}/ev"],
     "camo: error: --metrics is empty; give a comma list, e.g. psnr,ssim,lpips_proxy"),
    # the evaluation settings (evaluation.settings: one schema for the flags and a grid's [evaluate])
    (["evaluate", "RUN", "--weights", "lpips", "--out", "{tmp}/ev"],
     "camo: error: --weights lpips: expected NAME=PATH, e.g. lpips=/path/to/weights"),
    (["evaluate", "RUN", "--weights", "lpips=a", "--lpips-weights", "b", "--out", "{tmp}/ev"],
     "camo: error: --lpips-weights b: weights for lpips given twice"),
    # the power analysis' participants list (study_site.power), range from study_site.ranges
    (["study", "power", "--predicted", "{tmp}", "--out", "{tmp}/p", "--participants", "1,5"],
     "camo: error: --participants must list numbers of participants, each an integer in [2, 100000]"),
])
def test_cli_shows_library_settings_as_flags(tmp_path, capsys, argv, expected):
    rc = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [expected]


def _subparser(parser, path: str):
    import argparse

    for word in path.split():
        action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = action.choices[word]
    return parser


@pytest.mark.parametrize("command, name, shown", [
    # the settings the library's advice names ("try {0} 0", "give {0} or {1}, not both", ...)
    ("view", "port", "--port"),
    ("video", "run_dirs", "RUN_DIR"), ("video", "asset", "--asset"), ("video", "inputs", "--inputs"),
    ("video", "frames", "--frames"), ("video", "resolution", "--resolution"), ("video", "codec", "--codec"),
    ("video", "spp", "--spp"), ("video", "time_budget", "--time-budget"),
    ("evaluate", "run_dirs", "RUN_DIR"), ("evaluate", "scene", "--scene"), ("evaluate", "method", "--method"),
    ("evaluate", "inputs", "--inputs"), ("evaluate", "metrics", "--metrics"), ("evaluate", "resolution", "--resolution"),
    ("evaluate", "lpips_weights", "--lpips-weights"),
    ("study build-stimuli", "copy", "--copy"), ("study build-stimuli", "out", "--out"),
    ("study build-stimuli", "force", "--force"), ("study report", "include_incomplete", "--include-incomplete"),
    ("study serve", "MIN_AGE", "MIN_AGE (--min-age)"), ("data fetch", "pin", "--pin"),
])
def test_each_command_shows_the_settings_its_library_names(command, name, shown):
    from camo.cli import build_parser

    p = _subparser(build_parser(), command)
    assert p.get_default("setting_names")(name, None) == shown


def test_viewer_port_in_use_names_the_port_setting():
    import socket

    from evaluation.viewer import make_server

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(SettingError) as e:
            make_server(ROOT, s.getsockname()[1])
    assert e.value.names == ("port",) and str(e.value).endswith("; try port 0")
    assert e.value.renamed({"port": "--port"}).endswith("; try --port 0")
