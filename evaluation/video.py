"""Video files of rendered frames: MP4/WebM through PyAV (FFmpeg inside the wheel) and animated WebP/GIF through
Pillow, each written atomically (a temporary file beside the target, renamed on success).

Frames are ``(H, W, 3)`` ``uint8`` **sRGB** arrays, all of one size. Browsers play H.264 in MP4 (every browser),
VP9 in WebM or MP4 and AV1 (recent browsers); the encoders and pixel format are chosen for that: ``yuv420p``
(the only chroma layout every player decodes), even width and height (:func:`even_size` pads with black), MP4
with ``+faststart`` (the index first, so a browser starts playing before the whole file is loaded).

Licences: PyAV is BSD-3-Clause; its binary wheel ships FFmpeg's libraries built LGPL-3.0-or-later
(``av._core.library_meta``) together with libx264 (the ``h264`` encoder, GPL-2.0-or-later), libvpx (``vp9``,
BSD-3-Clause) and SVT-AV1 (``av1``, BSD-3-Clause-Clear). Where a GPL encoder is unwelcome, ``--codec vp9`` or
``av1`` encodes without it.

>>> sorted(CODECS)
['av1', 'h264', 'vp9']
>>> container_of("turntable.mp4"), container_of("t.webm")
('mp4', 'webm')
>>> even_size(97, 40)
(98, 40)
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from camo_base.errors import CamoError, SettingError, literal


@dataclasses.dataclass(frozen=True)
class Codec:
    name: str  # what --codec takes
    encoder: str  # FFmpeg encoder
    containers: tuple[str, ...]  # file suffixes (without the dot) it is written in
    quality_option: str  # the encoder's constant-quality option
    quality_range: tuple[int, int]  # lowest and highest value it takes (lower = better)
    default_quality: int
    extra: tuple[tuple[str, str], ...] = ()  # further encoder options
    browsers: str = ""


CODECS: dict[str, Codec] = {c.name: c for c in (
    Codec("h264", "libx264", ("mp4", "mkv"), "crf", (0, 51), 18, (("preset", "medium"),),
          "every browser (H.264 High profile, yuv420p)"),
    Codec("vp9", "libvpx-vp9", ("webm", "mp4", "mkv"), "crf", (0, 63), 30, (("b", "0"), ("row-mt", "1")),
          "Chrome, Firefox, Edge, Safari >= 14.1"),
    Codec("av1", "libsvtav1", ("mp4", "webm", "mkv"), "crf", (1, 63), 35, (),
          "Chrome, Firefox, Edge, Safari >= 17 on recent hardware"),
)}
#: Containers by file suffix.
CONTAINERS = {"mp4": "mp4", "webm": "webm", "mkv": "matroska"}
#: Animated-image formats for docs (Pillow).
PREVIEW_SUFFIXES = (".webp", ".gif")


def container_of(path: str | Path) -> str:
    """The container (``mp4``, ``webm``, ``mkv``) named by a video file's suffix; CamoError for another suffix."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in CONTAINERS:
        raise SettingError.of("out", f" {path}: a video file must end in {', '.join('.' + c for c in CONTAINERS)}")
    return suffix


def check_codec(codec: str, path: str | Path, quality: int | None = None) -> Codec:
    """The :class:`Codec` called ``codec`` for a file ``path``, after checking the pair and ``quality`` (one line
    errors); also checks that this FFmpeg build has the encoder."""
    c = CODECS.get(str(codec).lower())
    if c is None:
        raise SettingError(f"unknown {{0}} {literal(repr(codec))}; known: {', '.join(CODECS)} (browsers play all three)",
                           "codec")
    cont = container_of(path)
    if cont not in c.containers:
        raise SettingError.of("codec", f" {c.name} cannot be written to a .{cont} file; use "
                        f"{' or '.join('.' + x for x in c.containers)}")
    if quality is not None:
        lo, hi = c.quality_range
        if isinstance(quality, bool) or not isinstance(quality, int) or not lo <= quality <= hi:
            raise SettingError.of("quality", f" for {c.name} must be an integer in [{lo}, {hi}] (lower is better), got "
                            f"{quality!r}")
    import av

    try:
        av.codec.Codec(c.encoder, "w")
    except Exception:  # av.codec.codec.UnknownCodecError and friends
        raise SettingError(f"this FFmpeg build (PyAV {av.__version__}) has no {c.encoder} encoder for {{0}} {c.name}; "
                           "try another {0}", "codec") from None
    return c


def even_size(width: int, height: int) -> tuple[int, int]:
    """``(width, height)`` rounded up to even numbers (yuv420p halves both for its chroma planes)."""
    return width + width % 2, height + height % 2


def pad_even(frame: np.ndarray) -> np.ndarray:
    """A ``(H, W, 3)`` uint8 frame padded with black at the right/bottom to even width and height."""
    h, w = frame.shape[:2]
    w2, h2 = even_size(w, h)
    if (w2, h2) == (w, h):
        return frame
    out = np.zeros((h2, w2, 3), np.uint8)
    out[:h, :w] = frame
    return out


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float, codec: str = "h264",
                quality: int | None = None) -> dict:
    """Encode ``frames`` (``(H, W, 3)`` uint8 sRGB, one size) into ``path`` (container from the suffix).

    Returns ``{"frames": n, "bytes": size, "codec": ..., "encoder": ..., "width": w, "height": h, "fps": fps}``.
    The file appears only when it is complete (atomic rename); an earlier file at ``path`` stays until then."""
    import av
    from fractions import Fraction

    from camo_base.atomic import atomic_path

    c = check_codec(codec, path, quality)
    q = c.default_quality if quality is None else int(quality)
    rate = Fraction(fps).limit_denominator(1001)
    n = 0
    size = None
    with atomic_path(path) as tmp:
        options = {"movflags": "+faststart"} if container_of(path) == "mp4" else {}
        with av.open(str(tmp), mode="w", format=CONTAINERS[container_of(path)], options=options) as out:
            stream = None
            for frame in frames:
                frame = pad_even(np.ascontiguousarray(frame, dtype=np.uint8))
                if stream is None:
                    size = (frame.shape[1], frame.shape[0])
                    stream = out.add_stream(c.encoder, rate=rate)
                    stream.width, stream.height = size
                    stream.pix_fmt = "yuv420p"
                    stream.options = {c.quality_option: str(q), **dict(c.extra)}
                elif (frame.shape[1], frame.shape[0]) != size:
                    raise ValueError(f"frame {n} is {frame.shape[1]}x{frame.shape[0]}, the first {size[0]}x{size[1]}")
                vf = av.VideoFrame.from_ndarray(frame, format="rgb24")
                for packet in stream.encode(vf):
                    out.mux(packet)
                n += 1
            if stream is None:
                raise ValueError("no frames to encode")
            for packet in stream.encode():
                out.mux(packet)
    return {"frames": n, "bytes": Path(path).stat().st_size, "codec": c.name, "encoder": c.encoder,
            "quality": q, "width": size[0], "height": size[1], "fps": float(fps)}


def read_video(path: str | Path) -> Iterator[np.ndarray]:
    """Decode a video file's frames as ``(H, W, 3)`` uint8 sRGB (for tests and checks)."""
    import av

    with av.open(str(path)) as f:
        for frame in f.decode(video=0):
            yield frame.to_ndarray(format="rgb24")


def video_info(path: str | Path) -> dict:
    """Codec, size, frame count, frame rate and duration (seconds) of a video file."""
    import av

    with av.open(str(path)) as f:
        s = f.streams.video[0]
        n = s.frames or sum(1 for _ in f.decode(video=0))
        rate = float(s.average_rate) if s.average_rate else math.nan
        return {"codec": s.codec_context.name, "width": s.codec_context.width, "height": s.codec_context.height,
                "frames": int(n), "fps": rate, "pix_fmt": s.codec_context.pix_fmt,
                "seconds": float(n / rate) if rate == rate and rate > 0 else math.nan}


def preview_frames(frames: list[np.ndarray], max_width: int, max_frames: int) -> tuple[list[np.ndarray], int]:
    """Frames for an animated image: every ``step``-th frame (at most ``max_frames``), scaled to at most
    ``max_width`` pixels wide (Lanczos). Returns the frames and ``step``."""
    from PIL import Image

    step = max(1, math.ceil(len(frames) / max(1, max_frames)))
    picked = frames[::step]
    out = []
    for f in picked:
        h, w = f.shape[:2]
        if w > max_width:
            im = Image.fromarray(f).resize((max_width, max(1, round(h * max_width / w))), Image.Resampling.LANCZOS)
            f = np.asarray(im)
        out.append(f)
    return out, step


def write_animation(path: str | Path, frames: list[np.ndarray], fps: float, quality: int = 80) -> int:
    """An endlessly looping animated WebP (lossy, ``quality``) or GIF (256 colours) of ``frames``; returns bytes."""
    from PIL import Image

    from camo_base.atomic import atomic_path

    suffix = Path(path).suffix.lower()
    if suffix not in PREVIEW_SUFFIXES:
        raise SettingError.of("preview", f" {path}: an animated image must end in {' or '.join(PREVIEW_SUFFIXES)}")
    if not frames:
        raise ValueError("no frames")
    ims = [Image.fromarray(np.ascontiguousarray(f, dtype=np.uint8)) for f in frames]
    ms = max(20, int(round(1000.0 / fps)))
    with atomic_path(path) as tmp:
        if suffix == ".webp":
            ims[0].save(tmp, format="WEBP", save_all=True, append_images=ims[1:], duration=ms, loop=0,
                        quality=int(quality), method=4)
        else:
            ims[0].save(tmp, format="GIF", save_all=True, append_images=ims[1:], duration=ms, loop=0,
                        optimize=True, disposal=1)
    return Path(path).stat().st_size
