"""Turntable cost and size (``camo video``): seconds per frame and MP4 bytes at the demo's size and at paper size,
measured side by side in one run (fresh frame caches, so every frame is rendered).

    python bench/bench_video.py demo_out/runs/mean demo_out/runs/ours            # background | Mean | ours
    python bench/bench_video.py RUN... --paper-frames 8 --sizes demo,paper

Sizes (per panel; a side-by-side frame has one panel per input plus the background):

* ``demo``:  96 px, 8 spp, 48 frames at 24 fps (the Makefile's DEMO_VIDEO_OPT);
* ``paper``: 512 px, 64 spp (the evaluation's spp; the paper renders at 800 px), ``--paper-frames`` frames of the
  default 120-frame orbit, its MP4 size extrapolated to 120 frames from the bytes per frame of those frames
  (labelled as such).

Prints one row per size: seconds per frame (all panels) and per panel frame, encoding seconds, MP4 bytes and
bytes per frame, the 120-frame estimate, the animated preview's bytes; and the paper / demo ratio of seconds per
frame (the machine is shared: compare ratios from one run, not absolute seconds across runs).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SIZES = {"demo": {"resolution": 96, "spp": 8, "frames": 48, "fps": 24.0, "preview_frames": 24},
         "paper": {"resolution": 512, "spp": 64, "frames": 120, "fps": 30.0, "preview_frames": 60}}


def measure(runs: list[str], size: str, frames: int, tmp: Path) -> dict:
    from evaluation.inputs import InputSpec
    from evaluation.turntable import VideoSettings, make_video

    cfg = SIZES[size]
    out = tmp / f"{size}.mp4"
    s = VideoSettings(frames=cfg["frames"], resolution=cfg["resolution"], spp=cfg["spp"], fps=cfg["fps"],
                      side_by_side=True, preview_frames=cfg["preview_frames"], progress=False)
    if frames < cfg["frames"]:  # render only the first `frames` frames of the orbit: an arc of the same step
        s.arc = 360.0 * (frames - 1) / cfg["frames"]
        s.frames = frames
    rec = make_video([InputSpec("run", r) for r in runs], out, s, say=lambda m: None)
    enc, sec = rec["encoding"], rec["seconds"]
    per_frame_bytes = enc["bytes"] / enc["frames"]
    return {"size": size, "px": cfg["resolution"], "spp": cfg["spp"], "panels": len(rec["panels"]),
            "frames": enc["frames"], "frame_px": f"{enc['width']}x{enc['height']}",
            "s_frame": sec["per_frame"], "s_panel": sec["seconds_per_panel_frame"], "s_encode": sec["encode"],
            "bytes": enc["bytes"], "bytes_frame": per_frame_bytes,
            "bytes_full": enc["bytes"] if enc["frames"] == cfg["frames"] else per_frame_bytes * cfg["frames"],
            "full_frames": cfg["frames"], "preview": rec["preview_bytes"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="*", default=[str(REPO / "demo_out" / "runs" / "mean"),
                                                 str(REPO / "demo_out" / "runs" / "ours")])
    ap.add_argument("--sizes", default="demo,paper")
    ap.add_argument("--paper-frames", type=int, default=4, help="frames rendered at paper size (default 4)")
    args = ap.parse_args(argv)
    from optimizer import backend

    backend.init()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for size in args.sizes.split(","):
            n = SIZES[size]["frames"] if size == "demo" else args.paper_frames
            rows.append(measure(args.runs, size, n, Path(d)))
            r = rows[-1]
            print(f"{r['size']:>5}: {r['panels']} panels of {r['px']} px at {r['spp']} spp ({r['frame_px']} frame), "
                  f"{r['frames']} frames rendered: {r['s_frame']:.2f} s/frame ({r['s_panel']:.3f} s/panel frame), "
                  f"encode {r['s_encode']:.2f} s; MP4 {r['bytes'] / 1e6:.3f} MB = {r['bytes_frame'] / 1e3:.1f} kB/frame"
                  f" -> {r['full_frames']} frames: {r['bytes_full'] / 1e6:.2f} MB"
                  + ("" if r["frames"] == r["full_frames"] else " (extrapolated)")
                  + f", {r['full_frames'] * r['s_frame'] / 60:.1f} min to render; preview {r['preview'] / 1e3:.0f} kB",
                  flush=True)
    if len(rows) == 2:
        print(f"ratio {rows[1]['size']} / {rows[0]['size']} seconds per frame: {rows[1]['s_frame'] / rows[0]['s_frame']:.1f}"
              f" (pixels x spp: {(rows[1]['px'] / rows[0]['px']) ** 2 * rows[1]['spp'] / rows[0]['spp']:.0f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
