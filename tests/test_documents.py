"""``camo_base.documents``: TOML and JSON a user gives, read with one-line errors, seen through the command line."""

from __future__ import annotations

import pytest

from camo_base.documents import read_json, read_toml
from camo_base.errors import CamoError


def test_read_values_and_types(tmp_path):
    (tmp_path / "a.toml").write_text('x = 1\n[t]\ny = "z"\n', encoding="utf-8")
    (tmp_path / "a.json").write_text('[1, {"b": 2.5}]', encoding="utf-8")
    assert read_toml(tmp_path / "a.toml", "thing") == {"x": 1, "t": {"y": "z"}}
    assert read_json(tmp_path / "a.json", "thing", list) == [1, {"b": 2.5}]
    with pytest.raises(CamoError, match=r"^thing .*a\.json: expected a JSON object$"):
        read_json(tmp_path / "a.json", "thing", dict)


@pytest.mark.parametrize("content, needle", [
    (None, "--inputs list not found: "),
    (b"[[run]\npath = 'x'\n", "is not valid TOML: "),
    (b"[[run]]\npath = '\xff\xfe'\n", "is not UTF-8 text (invalid start byte at byte 16)"),
])
def test_input_list_problems_are_one_line(tmp_path, cli, content, needle):
    lst = tmp_path / "inputs.toml"
    if content is not None:
        lst.write_bytes(content)
    rc, out, err = cli("evaluate", "--inputs", str(lst), "--out", str(tmp_path / "ev"))
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("camo: error: ") and needle in lines[0], lines
    assert not (tmp_path / "ev").exists()


def test_renders_json_of_the_wrong_type_is_one_line(tmp_path, cli):
    ev = tmp_path / "ev"
    ev.mkdir()
    (ev / "renders.json").write_text('{"run": "r"}', encoding="utf-8")
    rc, _, err = cli("study", "build-stimuli", str(ev), "--out", str(tmp_path / "st"), "--copy")
    assert rc == 2 and err.strip() == f"camo: error: render list {ev / 'renders.json'}: expected a JSON list"
