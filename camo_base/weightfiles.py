"""Weight files read and written safely: a restricted unpickler for pickled NumPy dicts, and safetensors bytes.

Downloaded pickles are never given to :func:`pickle.load`: a pickle can name any importable callable and call
it while loading (``os.system`` is one opcode away). :func:`load_numpy_pickle` admits exactly what a pickled dict
of NumPy arrays needs -- ``numpy.ndarray``, ``numpy.dtype`` and NumPy's two array reconstructors
(:data:`ADMITTED_GLOBALS`) -- and refuses every other global in one line before anything is called; the result must be a (nested) dict of str -> numeric
array, else it is refused too.

:func:`safetensors_bytes` writes the `safetensors <https://github.com/huggingface/safetensors>`_ format (an
8-byte little-endian header length, a JSON header of ``{name: {dtype, shape, data_offsets}}``, the raw
little-endian tensors). Written here rather than by the ``safetensors`` package for a stated reason: the bytes
must depend on the tensors alone (keys sorted, no metadata, header padded with spaces to 8 bytes), so the SHA-256
of a converted weight file can be pinned in a data manifest whatever version of the package is installed.
The files are read back with the ``safetensors`` package (:func:`read_safetensors`), which is the reference
reader of the format (and refuses malformed headers).
"""

from __future__ import annotations

import io
import json
import pickle
import struct
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from camo_base.errors import CamoError

#: The only globals a pickled dict of NumPy arrays needs (module, name). NumPy 2 pickles say ``numpy._core``,
#: NumPy 1 pickles ``numpy.core``; both map to the same reconstructor.
ADMITTED_GLOBALS = frozenset({
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.numeric", "_frombuffer"),  # protocol 5 arrays: np.frombuffer(buffer, dtype).reshape(shape)
    ("numpy._core.numeric", "_frombuffer"),
})

#: Array dtypes admitted in a pickle (kinds): float, signed / unsigned int, bool. Object arrays are refused.
ADMITTED_KINDS = "fiub"

_SAFETENSORS_DTYPES = {np.dtype("<f4"): "F32", np.dtype("<f8"): "F64", np.dtype("<f2"): "F16",
                       np.dtype("<i8"): "I64", np.dtype("<i4"): "I32", np.dtype("u1"): "U8", np.dtype("?"): "BOOL"}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    def __init__(self, data: bytes, label: str) -> None:
        super().__init__(io.BytesIO(data))
        self.label = label

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in ADMITTED_GLOBALS:
            raise CamoError(f"{self.label}: refusing pickle global {module}.{name} (only numpy arrays, dtypes and "
                            "dicts are admitted in a weight file)")
        if name == "_reconstruct":
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # NumPy 1
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        if name == "_frombuffer":
            try:
                from numpy._core.numeric import _frombuffer
            except ImportError:  # NumPy 1
                from numpy.core.numeric import _frombuffer
            return _frombuffer
        return getattr(np, name)

    def persistent_load(self, pid: Any) -> Any:
        raise CamoError(f"{self.label}: refusing a pickle persistent id (only numpy arrays, dtypes and dicts are "
                        "admitted in a weight file)")


def _check_tree(obj: Any, label: str, path: str = "") -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, str):
                raise CamoError(f"{label}: refusing the pickle: key {k!r} under {path or '/'} is not a string")
            _check_tree(v, label, f"{path}/{k}")
        return
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in ADMITTED_KINDS or obj.dtype.fields is not None:
            raise CamoError(f"{label}: refusing the pickle: {path} is a {obj.dtype} array (only numeric arrays are "
                            "admitted)")
        return
    raise CamoError(f"{label}: refusing the pickle: {path or 'the top level'} is a {type(obj).__name__} (only dicts "
                    "of numpy arrays are admitted)")


def load_numpy_pickle(data: bytes, label: str = "pickle") -> dict[str, Any]:
    """A pickled (nested) ``dict`` of ``str`` -> numeric NumPy arrays, loaded without running any other code.

    Args:
        data: the pickle's bytes (e.g. an archive member; read the file yourself).
        label: what to call it in error messages (the file or member name).

    Returns:
        The dict, with nested dicts as they were pickled.

    Raises:
        CamoError: one line for any global other than :data:`ADMITTED_GLOBALS` (nothing of it is called), a
        persistent id, a corrupt pickle, or a result that is not a dict tree of numeric arrays.

    >>> import pickle, numpy as np
    >>> load_numpy_pickle(pickle.dumps({"conv": {"kernel": np.ones((1, 1, 3, 2), np.float32)}}))["conv"]["kernel"].shape
    (1, 1, 3, 2)
    """
    try:
        obj = _NumpyOnlyUnpickler(data, label).load()
    except CamoError:
        raise
    except Exception as exc:  # a corrupt or truncated pickle raises many types
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CamoError(f"{label}: not a readable pickle ({msg})") from None
    if not isinstance(obj, dict):
        raise CamoError(f"{label}: refusing the pickle: the top level is a {type(obj).__name__}, not a dict")
    _check_tree(obj, label)
    return obj


def flatten(tree: Mapping[str, Any], sep: str = "/") -> dict[str, np.ndarray]:
    """``{"a": {"b": x}}`` -> ``{"a/b": x}``."""
    out: dict[str, np.ndarray] = {}
    for k, v in tree.items():
        if isinstance(v, Mapping):
            for k2, v2 in flatten(v, sep).items():
                out[f"{k}{sep}{k2}"] = v2
        else:
            out[k] = v
    return out


def safetensors_bytes(tensors: Mapping[str, np.ndarray]) -> bytes:
    """The safetensors file of ``tensors`` (little-endian, C order), byte-for-byte a function of the tensors.

    Keys are sorted, no ``__metadata__`` is written, the JSON header is compact and padded with spaces to a
    multiple of 8 bytes (as the format allows). Supported dtypes: float16/32/64, int32/64, uint8, bool.
    """
    header: dict[str, Any] = {}
    blobs = []
    offset = 0
    for name in sorted(tensors):
        a = np.asarray(tensors[name])
        dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
        if np.dtype(dt) not in _SAFETENSORS_DTYPES:
            raise CamoError(f"safetensors: {name} has unsupported dtype {a.dtype}")
        raw = np.ascontiguousarray(a, dtype=dt).tobytes()
        header[name] = {"dtype": _SAFETENSORS_DTYPES[np.dtype(dt)], "shape": list(a.shape),
                        "data_offsets": [offset, offset + len(raw)]}
        blobs.append(raw)
        offset += len(raw)
    text = json.dumps(header, separators=(",", ":"), sort_keys=True).encode("utf-8")
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text + b"".join(blobs)


def read_safetensors(path: str | Path, what: str = "weights") -> dict[str, np.ndarray]:
    """``{name: array}`` of a safetensors file, read by the ``safetensors`` package (no code is ever run).

    Raises:
        CamoError: one line when the file is missing, truncated or not a safetensors file.
    """
    p = Path(path)
    if not p.is_file():
        raise CamoError(f"{what}: file not found: {p}")
    try:
        from safetensors.numpy import load_file

        return dict(load_file(str(p)))
    except ImportError:
        raise CamoError("reading .safetensors weights needs the 'safetensors' package (pip install safetensors)") \
            from None
    except Exception as exc:  # safetensors raises SafetensorError / OSError for a corrupt file
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CamoError(f"{what} {p}: not a readable safetensors file ({msg})") from None
