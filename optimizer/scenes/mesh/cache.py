"""Mesh preparation, all steps: :func:`prepare_mesh` (load -> clean -> normalise -> remesh -> UV-unwrap) and its
on-disk cache (``$CAMO_CACHE/meshes``, keyed by the input arrays, the parameters, the source of this package and
the xatlas version)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
import warnings
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from camo_base.atomic import atomic_path
from camo_base.errors import CamoError
from optimizer.scenes.mesh.clean import _clean_arrays, clean_mesh, normalise
from optimizer.scenes.mesh.load import _one_line, _trimesh, load_mesh
from optimizer.scenes.mesh.remesh import DEFAULT_TARGET_VERTICES, _check_target, _remesh, _resolve_decimator
from optimizer.scenes.mesh.uv import DEFAULT_UNWRAP_OPTIONS, UVMesh, uv_unwrap

#: bump when the cache file layout changes (the module source is hashed as well)
CACHE_FORMAT = 1


@dataclasses.dataclass(eq=False)
class PreparedMesh(UVMesh):
    """Output of :func:`prepare_mesh`: a :class:`UVMesh` plus where it came from.

    ``report``: the :func:`clean_mesh` report with ``remesh``, ``unwrap``,
    ``seconds`` and ``source`` entries added. ``transform``: (4, 4) float64,
    input coordinates -> prepared coordinates (normalisation). ``key``: cache
    key. ``cache_hit``: whether it was read from the cache.
    """

    report: dict = dataclasses.field(default_factory=dict)
    transform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    key: str = ""
    cache_hit: bool = False


_ARRAY_FIELDS = ("vertices", "faces", "normals", "uv_vertices", "uv_faces", "uvs", "uv_to_welded")


def default_cache_dir() -> Path:
    """``$CAMO_CACHE/meshes`` when ``CAMO_CACHE`` is set, else ``~/.cache/camo/meshes``."""
    root = os.environ.get("CAMO_CACHE")
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "camo"
    return base / "meshes"


_CODE_DIGEST: str | None = None


def _code_digest() -> str:
    global _CODE_DIGEST
    if _CODE_DIGEST is None:
        try:
            h = hashlib.sha256()
            for module in sorted(Path(__file__).parent.glob("*.py")):  # every step's source
                h.update(module.name.encode() + b"\0" + module.read_bytes())
            _CODE_DIGEST = h.hexdigest()[:16]
        except OSError:  # pragma: no cover - frozen installs
            _CODE_DIGEST = "unknown"
    return _CODE_DIGEST


def _xatlas_version() -> str:
    try:
        from importlib.metadata import version

        return version("xatlas")
    except Exception:
        return "unknown"


def _cache_key(v: np.ndarray, f: np.ndarray, params: Mapping[str, Any]) -> str:
    h = hashlib.sha256()
    meta = {"format": CACHE_FORMAT, "code": _code_digest(), "xatlas": _xatlas_version(), **params}
    h.update(json.dumps(meta, sort_keys=True).encode())
    h.update(np.ascontiguousarray(v, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(f, dtype="<i8").tobytes())
    return h.hexdigest()[:32]


def _read_cache(path: Path, key: str) -> PreparedMesh | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            arrays = {name: np.array(z[name]) for name in _ARRAY_FIELDS}
            report = json.loads(str(z["report"]))
            transform = np.array(z["transform"], dtype=np.float64)
    except Exception:
        return None
    nw, nu = len(arrays["vertices"]), len(arrays["uv_vertices"])
    ok = (
        arrays["vertices"].shape == (nw, 3) and arrays["normals"].shape == (nw, 3)
        and arrays["uv_vertices"].shape == (nu, 3) and arrays["uvs"].shape == (nu, 2)
        and arrays["uv_to_welded"].shape == (nu,) and arrays["faces"].ndim == 2 and arrays["faces"].shape[1] == 3
        and arrays["uv_faces"].shape == arrays["faces"].shape and transform.shape == (4, 4)
        and nw > 0 and len(arrays["faces"]) > 0
        and arrays["faces"].min() >= 0 and arrays["faces"].max() < nw
        and arrays["uv_faces"].min() >= 0 and arrays["uv_faces"].max() < nu
        and arrays["uv_to_welded"].min() >= 0 and arrays["uv_to_welded"].max() < nw
        and all(np.isfinite(arrays[k]).all() for k in ("vertices", "normals", "uv_vertices", "uvs"))
        and isinstance(report, dict)
    )
    if not ok:
        return None
    atlas = {k: v for k, v in report.get("unwrap", {}).items() if k in ("charts", "atlas_width", "atlas_height",
                                                                      "dropped_faces", "dropped_vertices")}
    return PreparedMesh(**arrays, atlas=atlas, report=report, transform=transform, key=key, cache_hit=True)


def _write_cache(path: Path, prep: PreparedMesh) -> None:
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh, key=np.array(prep.key), report=np.array(json.dumps(prep.report)),
                    transform=prep.transform, **{k: getattr(prep, k) for k in _ARRAY_FIELDS},
                )
    except OSError as exc:
        warnings.warn(f"could not write the mesh cache {path}: {_one_line(exc)}", RuntimeWarning, stacklevel=3)


def prepare_mesh(
    path_or_mesh,
    target_vertices: int = DEFAULT_TARGET_VERTICES,
    size: float = 1.0,
    cache_dir: str | os.PathLike | None = None,
    *,
    tol: float = 0.15,
    use_cache: bool = True,
    decimator: str = "auto",
    unwrap_options: Mapping[str, Any] | None = None,
) -> PreparedMesh:
    """load -> clean -> normalise -> remesh -> UV-unwrap, cached on disk.

    ``path_or_mesh``: a file path (see :data:`SUPPORTED_EXTENSIONS`) or a
    ``trimesh.Trimesh``. ``target_vertices``: welded vertex count (the paper
    uses about 30,000; the result is within ``+-tol``, normally exact).
    ``size``: largest bounding-box side after normalisation. The cache key
    hashes the input vertex and face arrays, every parameter, this package's
    source and the xatlas version; ``cache_dir`` defaults to
    :func:`default_cache_dir`; a corrupt cache file is rebuilt.
    """
    trimesh = _trimesh()
    if isinstance(path_or_mesh, (str, os.PathLike)):
        source = str(path_or_mesh)
        mesh = load_mesh(path_or_mesh)
    elif isinstance(path_or_mesh, trimesh.Trimesh):
        source = "<trimesh>"
        mesh = path_or_mesh
    else:
        raise CamoError(f"prepare_mesh needs a mesh file path or a trimesh.Trimesh, got {type(path_or_mesh).__name__}")
    v_in = np.asarray(mesh.vertices, dtype=np.float64)
    f_in = np.asarray(mesh.faces, dtype=np.int64)
    if f_in.size == 0:
        raise CamoError(f"mesh {source} has no triangles")
    uopts = {**DEFAULT_UNWRAP_OPTIONS, **dict(unwrap_options or {})}
    unknown = set(uopts) - set(DEFAULT_UNWRAP_OPTIONS) - {"isolate", "timeout"}
    if unknown:
        raise CamoError(f"unknown unwrap option(s): {', '.join(sorted(unknown))}")
    method = _resolve_decimator(decimator)
    target = _check_target(target_vertices, tol)
    if not isinstance(size, (int, float, np.integer, np.floating)) or not np.isfinite(size) or size <= 0:
        raise CamoError(f"object size must be a positive number, got {size!r}")
    params = {
        "target_vertices": target,
        "size": float(size), "tol": float(tol), "decimator": method,
        "unwrap": {k: uopts[k] for k in DEFAULT_UNWRAP_OPTIONS},
    }
    key = _cache_key(v_in, f_in, params)
    cache_path = Path(cache_dir).expanduser() / f"{key}.npz" if cache_dir is not None else default_cache_dir() / f"{key}.npz"
    if use_cache and cache_path.exists():
        hit = _read_cache(cache_path, key)
        if hit is not None:
            hit.report["source"] = source
            return hit

    t0 = time.perf_counter()
    cleaned, report = clean_mesh(mesh)
    t1 = time.perf_counter()
    normed, T1 = normalise(cleaned, size)
    remeshed, info = _remesh(normed, target, tol, method)
    # decimation can create slivers/duplicates; refinement never does
    rv, rf, post = _clean_arrays(remeshed.vertices, remeshed.faces, merge_tol=0.0)
    info["post_clean"] = post
    remeshed = trimesh.Trimesh(rv, rf, process=False)
    final, T2 = normalise(remeshed, size)  # decimation may move the bounds a little
    t2 = time.perf_counter()
    uvm = uv_unwrap(final, **{k: v for k, v in uopts.items()})
    t3 = time.perf_counter()
    report = dict(report)
    report["remesh"] = info
    report["unwrap"] = {**uvm.atlas, "uv_vertices": uvm.n_uv, "welded_vertices": uvm.n_welded,
                        "options": params["unwrap"]}
    report["seconds"] = {"clean": round(t1 - t0, 3), "remesh": round(t2 - t1, 3), "unwrap": round(t3 - t2, 3)}
    report["source"] = source
    prep = PreparedMesh(
        **{k: getattr(uvm, k) for k in _ARRAY_FIELDS}, atlas=uvm.atlas,
        report=report, transform=T2 @ T1, key=key, cache_hit=False,
    )
    if use_cache:
        _write_cache(cache_path, prep)
    return prep
