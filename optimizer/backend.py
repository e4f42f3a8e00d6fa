"""Mitsuba / Dr.Jit backend selection.

Order of preference:

1. ``cuda_ad_rgb`` when a CUDA GPU works;
2. ``llvm_ad_rgb`` with a libLLVM >= 16 located automatically (Dr.Jit 1.5
   crashes with ``Cannot select: fminimum`` on LLVM <= 15);
3. otherwise a :class:`CamoError` that says what to install.

The environment variable ``CAMO_VARIANT`` forces a variant, ``CAMO_THREADS``
sets the LLVM thread-pool size (``DRJIT_NUM_THREADS`` does nothing in Dr.Jit
1.5; we call ``dr.set_thread_count``), and ``DRJIT_LIBLLVM_PATH`` names the
LLVM library explicitly.
"""

from __future__ import annotations

import dataclasses
import glob
import os
import re
from typing import Iterable, Mapping, Sequence

from camo_base.errors import CamoError

MIN_LLVM = 16
MAX_LLVM = 22

#: Folders searched for libLLVM, in order (``{v}`` is the major version).
DEFAULT_LLVM_DIRS: tuple[str, ...] = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib/llvm-{v}/lib",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/usr/local/opt/llvm/lib",
    "/opt/homebrew/opt/llvm/lib",
)

INSTALL_HINT = (
    "install libLLVM >= 16 (Debian/Ubuntu: `apt-get install libllvm19`; macOS: `brew install llvm`) "
    "or point DRJIT_LIBLLVM_PATH at an existing libLLVM.so of version 16..22"
)

_VERSION_PATTERNS = (
    re.compile(r"libLLVM-(\d+)(?:\.\d+)*\.(?:so|dylib)"),  # libLLVM-19.so, libLLVM-19.so.1
    re.compile(r"libLLVM\.so\.(\d+)"),  # libLLVM.so.19.1
    re.compile(r"libLLVM\.(\d+)(?:\.\d+)*\.dylib"),  # libLLVM.19.dylib
    re.compile(r"llvm[-@](\d+)/"),  # /usr/lib/llvm-19/lib/libLLVM.so
)


@dataclasses.dataclass(frozen=True)
class LLVMLibrary:
    path: str
    version: int | None  # major version, None when it cannot be told from the name


@dataclasses.dataclass
class BackendInfo:
    variant: str
    llvm: LLVMLibrary | None
    threads: int
    gpu: str | None


def llvm_version_of(path: str) -> int | None:
    """Major LLVM version told by a library path (its name, its folder, or its link target)."""
    candidates = [path]
    try:
        real = os.path.realpath(path)
        if real != path:
            candidates.append(real)
    except OSError:
        pass
    for cand in candidates:
        for pat in _VERSION_PATTERNS:
            m = pat.search(cand)
            if m:
                return int(m.group(1))
    return None


def find_libllvm(
    env: Mapping[str, str] | None = None,
    search_dirs: Sequence[str] = DEFAULT_LLVM_DIRS,
    versions: Iterable[int] = range(MAX_LLVM, MIN_LLVM - 1, -1),
) -> LLVMLibrary:
    """Locate a usable libLLVM (>= 16), newest first.

    ``DRJIT_LIBLLVM_PATH`` in ``env`` wins when it exists; it is refused when
    its name says LLVM <= 15. Raises :class:`CamoError` with the install
    command when nothing usable is found.
    """
    env = os.environ if env is None else env
    explicit = env.get("DRJIT_LIBLLVM_PATH")
    if explicit:
        if not os.path.isfile(explicit):
            raise CamoError(f"DRJIT_LIBLLVM_PATH={explicit} does not exist; {INSTALL_HINT}")
        ver = llvm_version_of(explicit)
        if ver is not None and ver < MIN_LLVM:
            raise CamoError(
                f"DRJIT_LIBLLVM_PATH={explicit} is LLVM {ver}, which crashes Dr.Jit 1.5 "
                f"(`Cannot select: fminimum`); {INSTALL_HINT}"
            )
        return LLVMLibrary(explicit, ver)

    for v in versions:
        for d in search_dirs:
            folder = d.format(v=v)
            names = (
                f"libLLVM-{v}.so",
                f"libLLVM-{v}.so.1",
                f"libLLVM.so.{v}",
                f"libLLVM.so.{v}.*",
                f"libLLVM-{v}.dylib",
                f"libLLVM.{v}.dylib",
            )
            for name in names:
                for hit in sorted(glob.glob(os.path.join(folder, name))):
                    if os.path.isfile(hit):
                        return LLVMLibrary(hit, v)
            if "{v}" in d:  # versioned folder: an unversioned libLLVM.so inside is that version
                for name in ("libLLVM.so", "libLLVM.dylib"):
                    hit = os.path.join(folder, name)
                    if os.path.isfile(hit):
                        return LLVMLibrary(hit, v)
    raise CamoError(f"no libLLVM >= {MIN_LLVM} found (LLVM <= 15 crashes Dr.Jit 1.5); {INSTALL_HINT}")


def cuda_available() -> bool:
    """True when the CUDA driver library loads and reports at least one device."""
    import ctypes

    for name in ("libcuda.so.1", "libcuda.so", "nvcuda.dll"):
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        try:
            if lib.cuInit(0) != 0:
                return False
            count = ctypes.c_int(0)
            return lib.cuDeviceGetCount(ctypes.byref(count)) == 0 and count.value > 0
        except AttributeError:
            return False
    return False


def default_threads() -> int:
    env = os.environ.get("CAMO_THREADS")
    if env:
        try:
            n = int(env)
        except ValueError:
            raise CamoError(f"CAMO_THREADS must be a positive integer, got {env!r}") from None
        if n < 1:
            raise CamoError(f"CAMO_THREADS must be a positive integer, got {env!r}")
        return n
    return os.cpu_count() or 1


_STATE: BackendInfo | None = None
_ON_INIT: list = []


def on_init(hook) -> None:
    """Call ``hook(info)`` once a variant is set (now, if :func:`init` already ran). The rendering stage registers
    its projective integrators this way, so this module imports nothing above it."""
    if hook in _ON_INIT:
        return
    _ON_INIT.append(hook)
    if _STATE is not None:
        hook(_STATE)


def init(variant: str | None = None, threads: int | None = None) -> BackendInfo:
    """Pick and set the Mitsuba variant once per process; later calls return the same info.

    ``variant`` (or ``CAMO_VARIANT``) forces one of ``cuda_ad_rgb``,
    ``llvm_ad_rgb``, ``scalar_rgb``.
    """
    global _STATE
    if _STATE is not None:
        if threads is not None and threads != _STATE.threads:
            set_threads(threads)
        return _STATE
    variant = variant or os.environ.get("CAMO_VARIANT") or None
    threads = threads or default_threads()
    llvm: LLVMLibrary | None = None
    gpu: str | None = None
    if variant is None:
        variant = "cuda_ad_rgb" if cuda_available() else "llvm_ad_rgb"
    if variant.startswith("llvm"):
        llvm = find_libllvm()
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm.path
    import mitsuba as mi

    if variant not in mi.variants():
        raise CamoError(f"Mitsuba variant {variant!r} is not built; available: {', '.join(mi.variants())}")
    try:
        mi.set_variant(variant)
    except Exception as exc:  # driver present but unusable: fall back to LLVM once
        if variant.startswith("cuda") and not os.environ.get("CAMO_VARIANT"):
            llvm = find_libllvm()
            os.environ["DRJIT_LIBLLVM_PATH"] = llvm.path
            variant = "llvm_ad_rgb"
            mi.set_variant(variant)
        else:
            raise CamoError(f"cannot start Mitsuba variant {variant!r}: {exc}") from None
    if variant.startswith("cuda"):
        gpu = _cuda_device_name()
    _STATE = BackendInfo(variant=variant, llvm=llvm, threads=threads, gpu=gpu)
    set_threads(threads)
    for hook in _ON_INIT:
        hook(_STATE)
    return _STATE


def set_threads(n: int) -> None:
    import drjit as dr

    if n < 1:
        raise CamoError(f"thread count must be >= 1, got {n}")
    dr.set_thread_count(n)
    if _STATE is not None:
        _STATE.threads = n


def _cuda_device_name() -> str | None:
    try:
        import torch

        if torch.cuda.is_available():
            return torch.cuda.get_device_name(0)
    except Exception:
        pass
    return "CUDA device"


def info() -> BackendInfo | None:
    """The backend chosen so far in this process, or None before :func:`init`."""
    return _STATE



def load_file(path: str, **kwargs):
    """``mi.load_file`` that also works at one thread.

    Mitsuba 3.9's EXR reader waits on the Dr.Jit thread pool and deadlocks when
    that pool has a single thread (``--threads 1``, the bit-exact mode), so
    loading runs with at least two threads and the count is restored after.
    """
    import drjit as dr
    import mitsuba as mi

    n = dr.thread_count()
    if n < 2:
        dr.set_thread_count(2)
    try:
        return mi.load_file(str(path), **kwargs)
    finally:
        if n < 2:
            dr.set_thread_count(n)
