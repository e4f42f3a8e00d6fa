"""Variant selection and libLLVM location, with fake library folders."""

from __future__ import annotations

import pytest

from optimizer import backend
from camo_base.errors import CamoError


def _touch(p):
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(b"\x7fELF")
    return p


def test_newest_llvm_wins(tmp_path):
    d = tmp_path / "lib"
    _touch(d / "libLLVM-15.so")
    _touch(d / "libLLVM-17.so")
    _touch(d / "libLLVM-19.so.1")
    lib = backend.find_libllvm(env={}, search_dirs=[str(d)])
    assert lib.version == 19 and lib.path.endswith("libLLVM-19.so.1")


def test_llvm_15_and_older_are_never_chosen(tmp_path):
    d = tmp_path / "lib"
    _touch(d / "libLLVM-15.so")
    _touch(d / "libLLVM-14.so.1")
    _touch(d / "libLLVM.so.15.0")
    with pytest.raises(CamoError, match="apt-get install libllvm19"):
        backend.find_libllvm(env={}, search_dirs=[str(d)])


def test_versioned_folder_and_soname_forms(tmp_path):
    _touch(tmp_path / "llvm-18" / "lib" / "libLLVM.so")
    lib = backend.find_libllvm(env={}, search_dirs=[str(tmp_path / "llvm-{v}" / "lib")])
    assert lib.version == 18
    other = tmp_path / "other"
    _touch(other / "libLLVM.so.16.0.6")
    assert backend.find_libllvm(env={}, search_dirs=[str(other)]).version == 16


def test_env_variable_is_honoured_and_checked(tmp_path):
    good = _touch(tmp_path / "custom" / "libLLVM-20.so")
    assert backend.find_libllvm(env={"DRJIT_LIBLLVM_PATH": str(good)}, search_dirs=[]).path == str(good)
    old = _touch(tmp_path / "custom" / "libLLVM-15.so")
    with pytest.raises(CamoError, match="LLVM 15"):
        backend.find_libllvm(env={"DRJIT_LIBLLVM_PATH": str(old)}, search_dirs=[])
    with pytest.raises(CamoError, match="does not exist"):
        backend.find_libllvm(env={"DRJIT_LIBLLVM_PATH": str(tmp_path / "nope.so")}, search_dirs=[])


def test_version_from_symlink_target(tmp_path):
    real = _touch(tmp_path / "libLLVM-19.so.1")
    link = tmp_path / "libLLVM.so"
    link.symlink_to(real)
    assert backend.llvm_version_of(str(link)) == 19


def test_thread_count_from_env(monkeypatch):
    monkeypatch.setenv("CAMO_THREADS", "3")
    assert backend.default_threads() == 3
    monkeypatch.setenv("CAMO_THREADS", "zero")
    with pytest.raises(CamoError):
        backend.default_threads()


def test_init_picks_a_working_variant(mi_backend):
    mi, dr = mi_backend
    info = backend.info()
    assert info.variant in ("llvm_ad_rgb", "cuda_ad_rgb")
    assert mi.variant() == info.variant
    if info.variant.startswith("llvm"):
        assert info.llvm.version >= 16
    backend.set_threads(1)
    assert dr.thread_count() == 1
    backend.set_threads(info.threads)
