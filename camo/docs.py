"""The docs' tables generated from the registries: ``python -m camo.docs`` rewrites them, ``--check`` says which
are stale (``tests/test_registries.py`` runs the check, so a registry entry and its docs cannot drift apart).

A generated table sits between ``<!-- camo.docs: NAME -->`` and ``<!-- /camo.docs -->`` in a Markdown file; only
what lies between the markers is rewritten. The tables (:data:`TABLES`): the methods
(:data:`optimizer.optimise.methods.METHODS`), the presets (:data:`optimizer.optimise.presets.PRESETS`), the
ablations (:data:`optimizer.assets.conditions.ABLATIONS`), the BSDF maps (:data:`optimizer.scenes.bsdf_maps.MAPS`),
the run options of ``camo optimize`` (:data:`optimizer.optimise.options.OPTIONS`), the metrics
(:data:`evaluation.metrics.METRICS`) and the evaluation settings (:data:`evaluation.settings.OPTIONS`).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]


def methods_table() -> str:
    from optimizer.optimise.methods import methods_table as table

    return table()


def presets_table() -> str:
    from optimizer.optimise.presets import PRESETS, DEFAULT_PRESET

    rows = ["| `--preset` | what it sets |", "|---|---|"]
    for p in PRESETS.values():
        rows.append(f"| `{p.name}`{' (default)' if p.name == DEFAULT_PRESET else ''} | {p.summary} |")
    return "\n".join(rows)


def ablations_table() -> str:
    from optimizer.assets.conditions import ABLATIONS

    rows = ["| `--ablate` | Table II row | what is switched off |", "|---|---|---|"]
    for a in ABLATIONS.values():
        rows.append(f"| `{a.name}` | {a.label} | {a.help} |")
    return "\n".join(rows)


def maps_table() -> str:
    from optimizer.scenes.bsdf_maps import maps_table as table

    return table()


def options_table() -> str:
    from optimizer.optimise.options import OPTIONS, RANGES

    rows = ["| flag | sets | values |", "|---|---|---|"]
    for o in OPTIONS.values():
        if o.name == "scene":
            continue
        r = RANGES.get(o.field) if o.kind in (int, float) else None
        values = r.describe() if r else ("one of " + ", ".join(f"`{c}`" for c in o.choices) if o.choices else
                                        "a switch" if o.kind is bool else "text")
        rows.append(f"| `{o.flag}` | `{o.field}`{' (negated)' if o.negate else ''} | {values} |")
    return "\n".join(rows)


def eval_settings_table() -> str:
    from camo.grid.spec import RESERVED
    from evaluation.settings import OPTIONS

    rows = ["| flag | grid `[evaluate]` key | values | default | what |", "|---|---|---|---|---|"]
    for o in OPTIONS.values():
        values = o.range.describe() if o.range else "a switch" if o.kind is bool else \
            f"`{o.metric}=PATH` of `--weights`" if o.metric else \
            "one of " + ", ".join(f"`{c}`" for c in o.choices) + (f" (the flag alone, or `true`: `{o.const}`)"
                                                                   if o.const else "") if o.choices else "text"
        default = "-" if o.default is None or o.kind is bool else f"`{o.default}`"
        key = "set by the grid" if o.name in RESERVED["evaluate"] else f"`{o.name.replace('_', '-')}`"
        rows.append(f"| `{o.flag}` | {key} | {values} | {default} | {o.help} |")
    return "\n".join(rows)


def metrics_table() -> str:
    from evaluation.metrics.registry import metrics_table as table

    return table()


#: ``{name: (file, generator)}`` of every generated table.
TABLES: dict[str, tuple[str, Callable[[], str]]] = {
    "methods": ("docs/optimizer.md", methods_table),
    "presets": ("docs/optimizer.md", presets_table),
    "ablations": ("docs/optimizer.md", ablations_table),
    "maps": ("docs/optimizer.md", maps_table),
    "options": ("docs/cli.md", options_table),
    "metrics": ("docs/evaluation.md", metrics_table),
    "eval_settings": ("docs/evaluation.md", eval_settings_table),
}

_BLOCK = re.compile(r"(<!-- camo\.docs: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /camo\.docs -->)", re.S)


def render(text: str, tables: dict[str, str]) -> str:
    """``text`` with every marked block replaced by its table from ``tables`` (blocks of other names kept)."""
    return _BLOCK.sub(lambda m: m.group(1) + tables[m.group("name")].rstrip() + "\n" + m.group(4)
                      if m.group("name") in tables else m.group(0), text)


def update(root: Path = ROOT, check: bool = False) -> list[str]:
    """Rewrite the generated tables under ``root`` (``check``: only say which are stale); returns the stale or
    rewritten files, and raises ValueError for a table whose markers are missing."""
    by_file: dict[str, dict[str, str]] = {}
    for name, (file, make) in TABLES.items():
        by_file.setdefault(file, {})[name] = make()
    changed = []
    for file, tables in by_file.items():
        path = root / file
        text = path.read_text(encoding="utf-8")
        found = {m.group("name") for m in _BLOCK.finditer(text)}
        missing = sorted(set(tables) - found)
        if missing:
            raise ValueError(f"{file}: no <!-- camo.docs: {missing[0]} --> block")
        new = render(text, tables)
        if new != text:
            changed.append(file)
            if not check:
                from camo_base.atomic import write_text

                write_text(path, new)
    return changed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m camo.docs", description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="only list the files whose tables are stale (exit 1)")
    args = ap.parse_args(argv)
    changed = update(check=args.check)
    for f in changed:
        print(f"{'stale' if args.check else 'rewrote'} {f}")
    return 1 if args.check and changed else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
