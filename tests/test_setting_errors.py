"""Library errors name settings, the CLI names flags (CONTRIBUTING: "library code does not speak argparse").

A library function raises :class:`camo_base.errors.SettingError` naming its own setting (``out``, ``time_budget``);
``camo`` shows it as the flag whose argparse ``dest`` that setting is (``--out``, ``--time-budget``).
"""

from __future__ import annotations

import ast
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


def _flag_phrased_raises(path: Path, root: Path = ROOT) -> list[str]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call) and node.exc.args:
            name = getattr(node.exc.func, "id", getattr(node.exc.func, "attr", ""))
            start = _message_start(node.exc.args[0])
            if name in ("CamoError", "SettingError") and start is not None and start.lstrip().startswith("--"):
                out.append(f"{path.relative_to(root)}:{node.lineno}")
    return out


def test_no_library_error_starts_with_a_flag():
    """Every library ``raise CamoError("--flag ...")`` names its setting instead (SettingError.of)."""
    files = [p for pkg in LIBRARY for p in sorted((ROOT / pkg).rglob("*.py")) if p.name != "cli.py"]
    assert len(files) > 50
    bad = [hit for p in files for hit in _flag_phrased_raises(p)]
    assert bad == [], f"library errors phrased as CLI flags: {bad}"


def test_the_checker_sees_a_flag_phrased_error(tmp_path):
    p = tmp_path / "m.py"
    p.write_text('def f(x):\n    raise CamoError(f"--out {x} exists")\n\n\ndef g(x):\n'
                 '    raise SettingError.of("out", f" {x} exists")\n')
    assert _flag_phrased_raises(p, tmp_path) == ["m.py:2"]


def test_setting_error_of_keeps_braces_and_renames():
    e = SettingError.of("practice_scenes", ": no such scene {a}")
    assert str(e) == "practice_scenes: no such scene {a}"
    assert e.renamed({"practice_scenes": "--practice-scenes"}) == "--practice-scenes: no such scene {a}"


@pytest.mark.parametrize("argv, expected", [
    # a library error (evaluation.evaluate) shown with the command's flag
    (["evaluate", "RUN", "--metrics", ",", "--out", "{tmp}/ev"],
     "camo: error: --metrics is empty; give a comma list, e.g. psnr,ssim,lpips_proxy"),
    # the power analysis' participants list (study_site.power), range from study_site.ranges
    (["study", "power", "--predicted", "{tmp}", "--out", "{tmp}/p", "--participants", "1,5"],
     "camo: error: --participants must list numbers of participants, each an integer in [2, 100000]"),
])
def test_cli_shows_library_settings_as_flags(tmp_path, capsys, argv, expected):
    rc = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [expected]
