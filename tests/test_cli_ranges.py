"""Every numeric flag of every `camo` command has a range, and a value outside it is one line on stderr and exit 2.

The flags are read from the real parser (camo.cli.build_parser), so a flag added later is walked too: a numeric
flag must parse with a camo_base.ranges.Range (its argparse ``type``), and each value just outside the range (and
NaN / infinity for a float) is refused before anything runs -- nothing is written.
"""

from __future__ import annotations

import argparse

import pytest

from camo.cli import build_parser, main


def _commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """``(command path, parser)`` of every leaf command."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for action in subs:
        for name, sub in action.choices.items():
            yield from _commands(sub, (*path, name))


def _is_numeric(action: argparse.Action) -> bool:
    t = action.type
    return t in (int, float) or hasattr(t, "range") or getattr(t, "__name__", "") in ("int", "float")


def _filler(parser: argparse.ArgumentParser, skip: argparse.Action, tmp) -> list[str]:
    """Arguments that satisfy the command's other required arguments (never used: parsing stops at the bad flag)."""
    argv: list[str] = []
    for a in parser._actions:
        if a is skip or isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        value = str(a.choices[0]) if a.choices else str(tmp / "x")
        if not a.option_strings and a.nargs not in ("?", "*"):
            argv.append(value)
        elif a.option_strings and a.required:
            argv += [a.option_strings[0], value]
    return argv


NUMERIC = [(path, a) for path, p in _commands(build_parser()) for a in p._actions
           if a.option_strings and _is_numeric(a)]


def test_the_walk_finds_the_flags_it_should():
    found = {(" ".join(path), a.option_strings[0]) for path, a in NUMERIC}
    assert {("optimize", "--map-resolution"), ("optimize", "--resolution"), ("optimize", "--threads"),
            ("evaluate", "--jitter"), ("scenes render", "--spp"), ("grid run", "--workers"),
            ("study serve", "--port"), ("data fetch", "--retries")} <= found
    assert len(NUMERIC) > 50


@pytest.mark.parametrize("path,action", NUMERIC, ids=[f"{' '.join(p)} {a.option_strings[0]}" for p, a in NUMERIC])
def test_every_numeric_flag_refuses_values_outside_its_range(path, action, tmp_path, capsys):
    r = getattr(action.type, "range", None)
    assert r is not None, f"camo {' '.join(path)} {action.option_strings[0]} has no range (give it a Range type)"
    parser = dict(_commands(build_parser()))[path]
    for value in r.outside():
        argv = [*path, *_filler(parser, action, tmp_path), f"{action.option_strings[0]}={value}"]
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("camo: error: ") and err.count("\n") == 1, (argv, err)
        assert action.option_strings[0] in err and "must be" in err, (argv, err)
    assert not any(tmp_path.iterdir())  # nothing was written


def test_values_inside_the_range_parse():
    """The ends of every range parse (a range that refused its own defaults would be a bug of its own)."""
    for path, action in NUMERIC:
        r = action.type.range
        for v in (r.lo, r.hi):
            if v is None or (v == r.lo and r.lo_open) or (v == r.hi and r.hi_open):
                continue
            assert action.type(str(v if r.kind is float else int(v))) == v
        if action.default is not None and not isinstance(action.default, str):
            assert r.contains(action.default), (path, action.option_strings[0], action.default)


@pytest.mark.parametrize("argv,needle", [
    (["optimize", "gravel", "--map-resolution", "1"], "--map-resolution: must be an integer in [8, 16384], got '1'"),
    (["optimize", "gravel", "--resolution", "0"], "--resolution: must be an integer in [8, 8192], got '0'"),
    (["optimize", "gravel", "--threads", "0"], "--threads: must be an integer in [1, 4096], got '0'"),
    (["scenes", "render", "gravel", "--resolution", "0"], "--resolution: must be an integer in [8, 8192]"),
    (["evaluate", "x", "--spp", "nan"], "--spp: must be an integer"),
])
def test_the_cases_of_the_issue(argv, needle, tmp_path, capsys):
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1, err
    assert not (tmp_path / "o").exists()
