"""The evaluation setting pilots' figures in ``bench/bench_planner.py --evaluate-as auto:oidn-through:coarse,auto``
JSON files, as a Markdown table: per scene and pilot its choice, the candidates measured (levels), the chosen one's
error / full tracing's, noise ratio, priced / measured CPU s (2 views), pilot wall s.
Usage: ``python bench/setting_pilot_table.py RUN/bench_planner.json [...]``."""
import argparse
import json
import sys

PILOTS = ("auto:oidn-through:coarse", "auto")


def rows(evals: list[dict]) -> list[str]:
    """One Markdown row per scene and pilot of ``bench_planner.json``'s ``eval`` entries."""
    out = []
    for e in evals:
        for name in PILOTS:
            p = e["evaluate_as"][name]["pilot"]
            ch = p.get("chosen")
            lv = sorted({c["setting"]["spp"] for c in p["candidates"]})
            cand = f"{len(p['candidates'])} ({'/'.join(map(str, lv))})"
            if not ch:
                out.append(f"| {e['scene']} | `{name}` | default | {cand} | - | - | - ({p['full_seconds']:.2f}) | "
                           f"{p['wall_seconds']:.0f} |")
                continue
            c = next(c for c in p["candidates"] if c["setting"]["label"] == ch["label"])
            priced = f"{c['seconds']:.2f}" if p.get("cost") == "model" else "-"
            out.append(f"| {e['scene']} | `{name}` | `{ch['label'].replace('oidn-through:', '')}` | {cand} | "
                       f"{c['error'] * 255:.2f} / {p['target_error'] * 255:.2f} | {c['ratio']:.2f} | {priced} / "
                       f"{c.get('measured_seconds', c['seconds']):.2f} ({p['full_seconds']:.2f}) | "
                       f"{p['wall_seconds']:.0f} |")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("json", nargs="+", help="bench_planner.json files of runs with both pilots")
    args = ap.parse_args()
    table = ["| scene | pilot | chosen | candidates (levels) | its error / full's @64 (/255) | its noise ratio | "
             "its CPU s: priced / measured (full's @64), 2 views | pilot wall s |", "|---|---|---|---|---|---|---|---|"]
    for f in args.json:
        try:
            table += rows(json.load(open(f))["eval"])
        except (OSError, ValueError) as exc:
            sys.exit(f"setting_pilot_table: {f}: {exc}")
        except KeyError as exc:
            sys.exit(f"setting_pilot_table: {f}: no {exc} (run bench_planner --only eval --evaluate-as "
                     f"{','.join(PILOTS)})")
    print("\n".join(table))


if __name__ == "__main__":
    main()
