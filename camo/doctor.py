"""``camo doctor``: can the toolkit run here, and which optional local weights are found.

Weights are never downloaded at run time. The LPIPS weights are installed as data
(``camo data fetch data_manifests/lpips_weights.toml``, run by ``make demo`` /
``make test``) into ``$CAMO_WEIGHTS`` / ``$CAMO_CACHE/weights``; each file is listed
as ok, missing or corrupt (SHA-256 against its pin) with the command that fixes it.
The other lookups are those of the metrics (:mod:`evaluation.metrics.weights`) and
of the Stage 2 diffusers backend (``CAMO_SDXL_PATH`` / ``CAMO_CONTROLNET_PATH``).
Exit 0 when the renderer works (weights are optional: every learned metric has a
weight-free proxy and Stage 2 has an offline inpainter).
"""

from __future__ import annotations

import os
import platform

from camo_base.errors import CamoError


def _line(label: str, value: str) -> None:
    print(f"{label:<22} {value}")


def _renderer() -> bool:
    from optimizer import backend

    try:
        info = backend.init()
        import drjit as dr
        import mitsuba as mi

        _line("mitsuba", f"{mi.__version__} (variant {info.variant})")
        _line("drjit", dr.__version__)
        _line("libLLVM", f"{info.llvm.path} (LLVM {info.llvm.version})" if info.llvm else "not used (CUDA)")
        _line("threads", str(info.threads))
        _line("gpu", info.gpu or "none (CPU rendering)")
        sc = mi.load_dict({"type": "scene", "integrator": {"type": "path"}, "s": {"type": "sphere"},
                           "e": {"type": "constant"},
                           "cam": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}}})
        img = mi.render(sc, spp=1)
        ok = bool(dr.all(dr.isfinite(img.array)))
        _line("test render", "ok" if ok else "NON-FINITE pixels")
        return ok
    except CamoError as exc:
        _line("renderer", f"NOT AVAILABLE: {exc}")
    except Exception as exc:  # report, never crash the doctor
        _line("renderer", f"NOT AVAILABLE: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")
    return False


def lpips_rows() -> list[tuple[str, str]]:
    """``(label, status)`` of each installed LPIPS weight file: ``ok``, ``missing`` or ``corrupt`` with the path
    and, when not ok, the command that installs or replaces it."""
    from evaluation.metrics.weights import LPIPS_FILES, LPIPS_FILE_SHA256, fetch_command, weights_dir, weights_sha256

    rows = []
    for net, parts in LPIPS_FILES.items():
        for part, name in parts.items():
            p = weights_dir() / name
            what = "trunk" if part == "trunk" else "heads"
            if not p.is_file():
                rows.append((f"lpips {net} {what}", f"missing: {p}  [run: {fetch_command()}]"))
            elif weights_sha256(p) != LPIPS_FILE_SHA256[name]:
                rows.append((f"lpips {net} {what}", f"corrupt (SHA-256 mismatch): {p}  [run: {fetch_command()}]"))
            else:
                rows.append((f"lpips {net} {what}", f"ok: {p}"))
    return rows


def _weights() -> list[tuple[str, str]]:
    from evaluation.metrics import METRICS, metric_unavailable

    rows = lpips_rows()
    for name, m in METRICS.items():  # every learned metric of the registry: can it run here, else what it needs
        if m.needs_weights:
            why = metric_unavailable(name)
            rows.append((f"metric {name}", "ok (its weights are found)" if why is None
                         else f"not available here  [needs {m.needs or why}]"))
    try:
        from optimizer.optimise.inpaint import diffusers_status

        rows.append(("sdxl+controlnet", diffusers_status(os.environ.get("CAMO_SDXL_PATH"), os.environ.get("CAMO_CONTROLNET_PATH"))))
    except ImportError as exc:
        rows.append(("sdxl+controlnet", f"unavailable ({exc})"))
    return rows


def real_packs(root=None) -> list[tuple[str, bool, str]]:
    """``(pack, present, detail)`` for each real scene pack in ``packs/real/`` (present = every file it names is
    there). ``root`` is the repository (default: the one this package is in). Nothing is loaded or rendered."""
    import tomllib
    from pathlib import Path

    root = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    rows = []
    for pack in sorted((root / "packs" / "real").glob("*.toml")):
        try:
            data = tomllib.loads(pack.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            rows.append((pack.stem, False, f"unreadable: {exc}"))
            continue
        files = [v for sec, key in (("object", "mesh"), ("environment", "panorama"), ("environment", "xml"))
                 if isinstance(v := data.get(sec, {}).get(key), str)]
        missing = [f for f in files if not (pack.parent / f).is_file()]
        rows.append((pack.stem, not missing, f"missing {', '.join(Path(m).name for m in missing)}" if missing else "ok"))
    return rows


def _real_packs_report() -> None:
    rows = real_packs()
    if not rows:
        return
    have = [r for r in rows if r[1]]
    print(f"real scene packs (packs/real): {len(have)} of {len(rows)} present"
          + ("" if len(have) == len(rows) else
             "; the rest need: camo data fetch data_manifests/pmndrs_hdris.toml --dest data/real && "
             "camo data fetch data_manifests/registry_objects.toml --dest data/real"))
    if have:
        names = ", ".join(r[0] for r in have)
        print(f"  present: {names}")


def _video_status() -> str:
    try:
        import av

        from evaluation.video import CODECS

        have = []
        for c in CODECS.values():
            try:
                av.codec.Codec(c.encoder, "w")
                have.append(c.name)
            except Exception:  # this FFmpeg build lacks the encoder
                pass
        return f"PyAV {av.__version__}, encoders: {', '.join(have) or 'none'}"
    except ImportError as exc:
        return f"PyAV not installed ({exc}); pip install av"


def _viewer_status() -> str:
    from evaluation.viewer import FETCH_COMMAND, viewer_script

    p = viewer_script()
    return f"@google/model-viewer pinned copy at {p}" if p else f"JavaScript not fetched: {FETCH_COMMAND}"


def run_doctor() -> int:
    ok = _renderer()
    try:
        import torch

        _line("torch", f"{torch.__version__} (cuda: {'yes' if torch.cuda.is_available() else 'no'})")
    except Exception as exc:
        ok = False
        _line("torch", f"NOT AVAILABLE: {exc}")
    _line("python", f"{platform.python_version()} on {platform.machine()}")
    print("learned-metric weights (installed by camo data fetch; never downloaded at run time):")
    for label, status in _weights():
        _line(f"  {label}", status)
    _real_packs_report()
    _line("video (camo video)", _video_status())
    _line("viewer (camo view)", _viewer_status())
    print("status:", "ok" if ok else "the renderer cannot run; see above")
    return 0 if ok else 1
