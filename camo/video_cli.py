"""``camo video`` (path-traced turntables, :mod:`evaluation.turntable`) and ``camo view`` (the interactive viewer
page of a run, :mod:`evaluation.viewer`): argument parsing only, nothing heavy imported while building the parser."""

from __future__ import annotations

#: = evaluation.turntable defaults, repeated so that building the parser imports nothing heavy.
DEFAULT_FRAMES, DEFAULT_RESOLUTION, DEFAULT_SPP, DEFAULT_FPS = 120, 256, 64, 30.0


def _r(kind: type, lo=None, hi=None, **kw):
    """A flag's Range type (the limits of evaluation.turntable.check_settings / evaluation.viewer, which check the
    settings again for callers of the library; a codec's own quality range is checked there)."""
    from camo_base.ranges import Range

    return Range(kind, lo, hi, **kw).arg_type()


def register(sub) -> None:
    p = sub.add_parser("video", help="path-traced turntable video of run directories and assets (MP4 + animated "
                       "WebP/GIF), side by side with the background")
    p.add_argument("run_dirs", nargs="*", metavar="RUN_DIR", help="output of `camo optimize` (ours or a baseline)")
    p.add_argument("--asset", action="append", default=[], metavar="FILE",
                   help="a glTF/GLB or OBJ+MTL result of any method, placed in --scene (repeatable)")
    p.add_argument("--inputs", metavar="LIST.toml", help="many inputs: [[run]] and [[asset]] tables (as camo evaluate)")
    p.add_argument("--scene", help="for --asset: built-in scene, scene pack .toml or a run directory")
    p.add_argument("--method", help="method label of --asset")
    p.add_argument("--placement", default="auto", choices=("auto", "scene", "pack"), help="--asset coordinates (as "
                   "camo evaluate)")
    p.add_argument("--out", required=True, metavar="FILE", help="video file: .mp4 (default codec h264), .webm, .mkv")
    p.add_argument("--side-by-side", action="store_true",
                   help="the background (scene without the object) as the first panel; implied by two or more inputs")
    p.add_argument("--difference", action="store_true",
                   help="a second row: 4 x |panel - background| (sRGB) under each panel (implies --side-by-side)")
    p.add_argument("--frames", type=_r(int, 2, 10000), default=DEFAULT_FRAMES, help=f"frames of the orbit (default {DEFAULT_FRAMES})")
    p.add_argument("--arc", type=_r(float, 0.0, 360.0, lo_open=True), default=360.0,
                   help="degrees of azimuth covered (default 360: a seamless loop; less: both ends included)")
    p.add_argument("--start", type=_r(float, -3600.0, 3600.0), help="azimuth of the first frame in degrees (default: the rig's first "
                   "camera)")
    p.add_argument("--elevation", type=_r(float, -89.0, 89.0), help="camera elevation in degrees (default: the evaluation's)")
    p.add_argument("--radius", type=_r(float, 0.0, 1e6, lo_open=True), help="orbit radius in scene units (default: the evaluation's)")
    p.add_argument("--resolution", type=_r(int, 16, 4096), default=DEFAULT_RESOLUTION,
                   help=f"panel width = height in pixels (default {DEFAULT_RESOLUTION})")
    p.add_argument("--spp", type=_r(int, 1, 4096), help=f"samples per pixel (default {DEFAULT_SPP}, the evaluation's)")
    p.add_argument("--time-budget", type=_r(float, 0.0, 1e7, lo_open=True), metavar="SECONDS",
                   help="choose the spp from a short pilot so that rendering fits in SECONDS (instead of --spp)")
    p.add_argument("--seed", type=_r(int, 0, 2**31 - 1), default=0, help="sampler seed (every panel of a frame shares it)")
    p.add_argument("--fps", type=_r(float, 1.0, 120.0), default=DEFAULT_FPS, help=f"frames per second (default {DEFAULT_FPS:g})")
    p.add_argument("--codec", default="h264", help="h264 (default; every browser), vp9 or av1")
    p.add_argument("--quality", type=_r(int, 0, 63), help="constant-quality value of the codec (crf; lower is better; "
                   "defaults h264 18, vp9 30, av1 35)")
    p.add_argument("--preview", metavar="FILE", help="animated image for docs, .webp or .gif (default: OUT with "
                   ".webp)")
    p.add_argument("--no-preview", action="store_true", help="no animated image")
    p.add_argument("--preview-width", type=_r(int, 16, 4096), default=480, help="animated image width in pixels (default 480)")
    p.add_argument("--preview-frames", type=_r(int, 1, 10000), default=60,
                   help="at most this many frames in the animated image (every k-th frame; default 60)")
    p.add_argument("--cache", metavar="DIR", help="frame cache (default: OUT.frames/); rerun to continue")
    p.add_argument("--threads", type=_r(int, 1, 1024), help="CPU threads for the LLVM backend")
    p.add_argument("--quiet", action="store_true", help="no progress bar or messages")
    p.set_defaults(func=run_video)

    p = sub.add_parser("view", help="interactive 3D viewer page of a run's result (orbit controls, the scene's "
                       "environment), served locally")
    p.add_argument("run_dir", metavar="RUN_DIR", help="output of `camo optimize`")
    p.add_argument("--out", metavar="DIR", help="where the page is written (default: RUN_DIR/viewer)")
    p.add_argument("--video", metavar="FILE", help="a `camo video` of this run to link as the path-traced reference "
                   "(default: RUN_DIR/turntable.mp4 when it exists)")
    p.add_argument("--env-width", type=_r(int, 64, 16384), default=1024, help="width of the environment panorama (default 1024)")
    p.add_argument("--port", type=_r(int, 0, 65535), default=8030, help="local port (default 8030; 0 = any free port)")
    p.add_argument("--no-serve", action="store_true", help="write the page and exit (it also opens from disk)")
    p.add_argument("--threads", type=_r(int, 1, 1024), help="CPU threads for the LLVM backend")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run_view)


def _say(args):
    import sys

    return (lambda m: None) if getattr(args, "quiet", False) else (lambda m: print(m, file=sys.stderr))


def run_video(args) -> int:
    from camo_base.errors import CamoError
    from evaluation.inputs import InputSpec, read_input_list
    from evaluation.turntable import VideoSettings, make_video

    if args.asset and not (args.method and args.scene):
        raise CamoError("--asset needs --method LABEL and --scene (a built-in scene, pack .toml or run directory)")
    if args.no_preview and args.preview:
        raise CamoError("give --preview FILE or --no-preview, not both")
    specs = [InputSpec("run", d) for d in args.run_dirs]
    specs += [InputSpec("asset", a, method=args.method, scene=args.scene, placement=args.placement)
              for a in args.asset]
    if args.inputs:
        specs += read_input_list(args.inputs)
    if not specs:
        raise CamoError("video needs at least one input: RUN_DIR, --asset FILE or --inputs LIST.toml")
    s = VideoSettings(frames=args.frames, arc=args.arc, start=args.start, elevation=args.elevation,
                      radius=args.radius, resolution=args.resolution, spp=args.spp, time_budget=args.time_budget,
                      seed=args.seed, fps=args.fps, codec=args.codec, quality=args.quality,
                      side_by_side=args.side_by_side, difference=args.difference,
                      preview=None if args.no_preview else (args.preview or ""), preview_width=args.preview_width,
                      preview_frames=args.preview_frames, cache=args.cache, threads=args.threads,
                      progress=not args.quiet)
    rec = make_video(specs, args.out, s, _say(args))
    sec = rec["seconds"]
    per = f", {sec['per_frame']:.2f} s per frame" if sec.get("per_frame") else ""
    print(f"wrote {rec['video']} ({rec['encoding']['frames']} frames, {rec['encoding']['width']}x"
          f"{rec['encoding']['height']}, {rec['encoding']['bytes'] / 1e6:.2f} MB{per})"
          + (f" and {rec['preview']} ({rec['preview_bytes'] / 1e3:.0f} kB)" if rec["preview"] else ""))
    return 0


def run_view(args) -> int:
    from pathlib import Path

    from evaluation.viewer import make_server, serve, write_run_viewer

    out = args.out or str(Path(args.run_dir) / "viewer")
    srv = None if args.no_serve else make_server(out, args.port)  # a busy port fails before anything is written
    try:
        page = write_run_viewer(args.run_dir, out, video=args.video, env_width=args.env_width,
                                threads=args.threads, say=_say(args))
        print(f"wrote {page}")
        if srv is not None:
            serve(srv, page.name)
    finally:
        if srv is not None:
            srv.server_close()
    return 0
