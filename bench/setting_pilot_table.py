"""The evaluation setting pilots' figures in ``bench/bench_planner.py --evaluate-as auto:oidn-through:coarse,auto``
JSON files, as a Markdown table: per scene and pilot its choice, the candidates measured (levels), the chosen one's
error / full tracing's, noise ratio, priced / measured CPU s (2 views), pilot wall s.
Usage: ``python bench/setting_pilot_table.py RUN/bench_planner.json [...]``."""
import json, sys
print("| scene | pilot | chosen | candidates (levels) | its error / full's @64 (/255) | its noise ratio | its CPU s: priced / measured (full's @64), 2 views | pilot wall s |")
print("|---|---|---|---|---|---|---|---|")
for f in sys.argv[1:]:
    for e in json.load(open(f))["eval"]:
        for name in ("auto:oidn-through:coarse", "auto"):
            p = e["evaluate_as"][name]["pilot"]
            ch = p.get("chosen")
            lv = sorted({c["setting"]["spp"] for c in p["candidates"]})
            cand = f"{len(p['candidates'])} ({'/'.join(map(str, lv))})"
            if ch:
                c = next(c for c in p["candidates"] if c["setting"]["label"] == ch["label"])
                priced = f"{c['seconds']:.2f}" if p.get("cost") == "model" else "-"
                print(f"| {e['scene']} | `{name}` | `{ch['label'].replace('oidn-through:', '')}` | {cand} | {c['error']*255:.2f} / "
                      f"{p['target_error']*255:.2f} | {c['ratio']:.2f} | {priced} / {c.get('measured_seconds', c['seconds']):.2f} "
                      f"({p['full_seconds']:.2f}) | {p['wall_seconds']:.0f} |")
            else:
                print(f"| {e['scene']} | `{name}` | default | {cand} | - | - | - ({p['full_seconds']:.2f}) | {p['wall_seconds']:.0f} |")
