"""Downloading, verifying and unpacking manifest assets (standard library HTTP only).

Layout of a destination folder ``DEST``::

    DEST/<filename>                 verified download (file name from the URL, or the entry's `filename`)
    DEST/<name>/                    an archive entry's unpacked content (+ .camo-extracted.json)
    DEST/.partial/<filename>.part   resumable partial download (HTTP Range)
    DEST/.partial/<name>.extract/   unpacking in progress
    DEST/.rejected/<filename>       a download whose checksum or size did not match (kept for inspection)

A download is streamed into ``.part`` (SHA-256 computed on the fly), checked against the pinned size and
checksum, and only then renamed onto ``DEST/<filename>``: a file at the final path is always complete and
verified. An interrupted download continues from the ``.part`` file's size with a ``Range`` request; a
server that answers ``200`` instead of ``206`` (ignores ranges) restarts it from zero.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import http.client
import json
import os
import shutil
import socket
import sys
import tarfile
import time
import urllib.error
import urllib.request
import zipfile
from pathlib import Path
from typing import Callable, Iterator

from camo_base.errors import CamoError
from optimizer.scenes.data.manifest import Asset, member_selected, safe_relpath

CHUNK = 1 << 18  # 256 KiB
USER_AGENT = "camo-data/0.1 (+https://github.com/; research asset fetcher)"
MARKER = ".camo-extracted.json"
_RETRYABLE_HTTP = {408, 425, 429}  # and every 5xx


@dataclasses.dataclass
class FetchOptions:
    timeout: float = 30.0  # seconds, per connect and per read
    retries: int = 4  # further attempts after the first, per download
    backoff: float = 2.0  # seconds before the first retry; doubled each time, capped at 60 s
    quiet: bool = False
    out: Callable[[str], None] = print


@dataclasses.dataclass
class Download:
    """Result of :func:`ensure_download`."""

    path: Path
    sha256: str
    size: int
    fetched: bool  # False: it was already present and verified
    bytes_transferred: int = 0


class _StreamHash:
    """SHA-256 of a .part file, updated as bytes arrive (so a download is not read twice).

    ``n`` is the number of bytes hashed; :meth:`sync` re-reads the file when it does not match (a .part left
    by an earlier run, or one that was truncated), ``reset`` starts over for a download restarted from zero.
    """

    def __init__(self) -> None:
        self.h = hashlib.sha256()
        self.n = 0
        self.received = 0  # bytes that came over the network in this run

    def reset(self) -> None:
        self.h, self.n = hashlib.sha256(), 0

    def sync(self, part: Path) -> None:
        size = part.stat().st_size if part.exists() else 0
        if size == self.n:
            return
        self.reset()
        if size:
            with open(part, "rb") as f:
                while b := f.read(1 << 20):
                    self.h.update(b)
                    self.n += len(b)

    def update(self, b: bytes) -> None:
        self.h.update(b)
        self.n += len(b)
        self.received += len(b)


class _Interrupted(Exception):
    """A transfer that stopped early; the .part file is kept and the download can resume."""


# ------------------------------------------------------------------------------------------ hashing


def sha256_file(path: Path, progress_label: str | None = None, quiet: bool = True) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f, _bar(path.stat().st_size, 0, progress_label or path.name, quiet or progress_label is None) as bar:
        while True:
            b = f.read(1 << 20)
            if not b:
                break
            h.update(b)
            bar.update(len(b))
    return h.hexdigest()


def check_file(path: Path, sha256: str | None, size: int | None) -> tuple[str, str]:
    """``(status, detail)`` of a file against a pin: ``ok``, ``missing``, ``mismatch`` or ``unpinned``."""
    if not path.is_file():
        return ("unpinned" if sha256 is None or size is None else "missing"), "not downloaded"
    actual_size = path.stat().st_size
    if size is not None and actual_size != size:
        return "mismatch", f"size {actual_size} != {size}"
    digest = sha256_file(path)
    if sha256 is None or size is None:
        return "unpinned", f"present: sha256 {digest}, size {actual_size}"
    if digest != sha256:
        return "mismatch", f"sha256 {digest[:12]}... != {sha256[:12]}..."
    return "ok", f"{actual_size} bytes"


@contextlib.contextmanager
def _bar(total: int | None, initial: int, desc: str, quiet: bool):
    if quiet:
        yield _NoBar()
        return
    from tqdm import tqdm

    # disable=None: no bar when stderr is not a terminal (logs, CI, tests)
    with tqdm(total=total, initial=initial, desc=desc, unit="B", unit_scale=True, unit_divisor=1024,
              disable=None, leave=False, file=sys.stderr) as bar:
        yield bar


class _NoBar:
    def update(self, n: int) -> None:
        pass


# ------------------------------------------------------------------------------------------ locking


@contextlib.contextmanager
def _lock(path: Path) -> Iterator[None]:
    """An exclusive advisory lock (POSIX); two fetches into one DEST must not share a .part file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows: no locking
        yield
        return
    with open(path, "a+b") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise CamoError(f"another camo process is working on {path.stem} in {path.parent.parent}; wait for it") from None
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


# ------------------------------------------------------------------------------------------ HTTP


def _open(url: str, headers: dict[str, str], timeout: float):
    """Open ``url`` (the one place that touches the network; tests guard it)."""
    req = urllib.request.Request(url, headers=headers)
    return urllib.request.urlopen(req, timeout=timeout)


def _parse_content_range(value: str | None) -> tuple[int | None, int | None]:
    """``bytes a-b/total`` -> (a, total); ``bytes */total`` -> (None, total)."""
    if not value or not value.startswith("bytes "):
        return None, None
    rng, _, total = value[6:].partition("/")
    tot = int(total) if total.strip().isdigit() else None
    if rng.strip() == "*":
        return None, tot
    start = rng.split("-", 1)[0].strip()
    return (int(start) if start.isdigit() else None), tot


def _transfer(url: str, part: Path, expected_size: int | None, opts: FetchOptions, label: str,
              hasher: _StreamHash) -> int | None:
    """One attempt: continue ``part`` from its size; returns the total size if the server said it.

    ``hasher`` is brought up to date with the .part file and then fed every byte received.

    Raises :class:`_Interrupted` for a transfer that stopped early (resumable), ``urllib.error.HTTPError``
    for HTTP errors, ``OSError`` / ``http.client.HTTPException`` for network failures.
    """
    offset = part.stat().st_size if part.exists() else 0
    headers = {"User-Agent": USER_AGENT, "Accept-Encoding": "identity"}
    if offset:
        headers["Range"] = f"bytes={offset}-"
    try:
        resp = _open(url, headers, opts.timeout)
    except urllib.error.HTTPError as exc:
        if exc.code == 416 and offset:
            _, total = _parse_content_range(exc.headers.get("Content-Range") if exc.headers else None)
            exc.close()
            if total is not None and total == offset:
                return total  # the .part file is already complete
            part.unlink()  # the .part is longer than the file: start again
            raise _Interrupted(f"server refused the range {offset}- (file is {total} bytes); restarting") from None
        raise
    with resp:
        status = resp.status
        length = resp.headers.get("Content-Length")
        length = int(length) if length and length.strip().isdigit() else None
        total = None
        mode = "ab"
        if status == 206:
            start, total = _parse_content_range(resp.headers.get("Content-Range"))
            if start != offset:  # not the range we asked for: start again from zero
                part.unlink(missing_ok=True)
                raise _Interrupted(f"server sent bytes from {start}, asked for {offset}; restarting")
        elif status == 200:
            if offset:
                opts.out(f"  {label}: server ignored the range request; restarting from 0")
            mode, offset = "wb", 0  # full body: (re)start from zero
            hasher.reset()
            total = length
        else:
            raise _Interrupted(f"unexpected HTTP status {status}")
        if expected_size is not None and total is not None and total != expected_size:
            # the server's file is not the pinned one; do not download it
            part.unlink(missing_ok=True)
            raise CamoError(f"{label}: size mismatch: the server reports {total} bytes, the manifest pins {expected_size} "
                            f"({url}); the file changed upstream or the pin is wrong")
        received = 0
        with open(part, mode) as f, _bar(total, offset, label, opts.quiet) as bar:
            while True:
                try:
                    chunk = resp.read(CHUNK)
                except (http.client.IncompleteRead, ConnectionError, socket.timeout, TimeoutError) as exc:
                    f.flush()
                    raise _Interrupted(f"connection lost after {offset + received} bytes ({type(exc).__name__})") from None
                if not chunk:
                    break
                f.write(chunk)
                hasher.update(chunk)
                received += len(chunk)
                bar.update(len(chunk))
                if expected_size is not None and offset + received > expected_size:
                    break  # longer than pinned: verification below rejects it
            f.flush()
            os.fsync(f.fileno())
        if length is not None and received < length:
            raise _Interrupted(f"connection closed after {offset + received} of {offset + length} bytes")
        return total


def ensure_download(asset: Asset, dest: Path, opts: FetchOptions) -> Download:
    """Make ``DEST/<filename>`` the verified file of ``asset`` (download, resume or skip).

    A pinned asset whose present file matches is skipped. A present file that does not match is moved to
    ``DEST/.rejected/`` and downloaded again. An unpinned asset (``--pin``) is downloaded (or, when the file
    is already there, hashed) and its checksum/size are returned for pinning.
    """
    dest = Path(dest)
    final = asset.download_path(dest)
    partial_dir = dest / ".partial"
    part = partial_dir / (asset.filename + ".part")
    label = asset.name
    with _lock(partial_dir / (asset.filename + ".lock")):
        if final.is_file():
            if asset.pinned:
                status, detail = check_file(final, asset.sha256, asset.size)
                if status == "ok":
                    return Download(final, asset.sha256, asset.size, fetched=False)
                rejected = _reject(final, dest)
                opts.out(f"  {label}: the present {final.name} does not match its pin ({detail}); moved to {rejected}, downloading again")
            else:
                digest = sha256_file(final, f"{label} (hashing)", opts.quiet)
                opts.out(f"  {label}: pinned from the file already present at {final}")
                return Download(final, digest, final.stat().st_size, fetched=False)

        hasher = _StreamHash()
        attempt = 0
        while True:
            if asset.size is not None and part.exists() and part.stat().st_size > asset.size:
                part.unlink()  # longer than the pinned size: cannot be a prefix of the right file
            if asset.size is not None and part.exists() and part.stat().st_size == asset.size:
                break  # complete; verify below
            try:
                hasher.sync(part)
                _transfer(asset.url, part, asset.size, opts, label, hasher)
                break
            except (_Interrupted, OSError, http.client.HTTPException) as exc:
                if isinstance(exc, urllib.error.HTTPError) and exc.code not in _RETRYABLE_HTTP and exc.code < 500:
                    raise CamoError(f"{label}: HTTP {exc.code} {exc.reason} for {asset.url}") from None
                if isinstance(exc, urllib.error.HTTPError):
                    exc.close()
                if attempt >= opts.retries:
                    kept = part.stat().st_size if part.exists() else 0
                    raise CamoError(f"{label}: download failed after {attempt + 1} attempt(s): {_reason(exc)}; "
                                    f"{kept} bytes kept in {part}, run again to resume") from None
                delay = min(60.0, opts.backoff * (2 ** attempt))
                attempt += 1
                opts.out(f"  {label}: {_reason(exc)}; retry {attempt}/{opts.retries} in {delay:.3g} s")
                time.sleep(delay)

        actual_size = part.stat().st_size
        hasher.sync(part)  # no-op unless the file changed behind the stream
        digest = hasher.h.hexdigest()
        bad = None
        if asset.size is not None and actual_size != asset.size:
            bad = f"size mismatch: got {actual_size} bytes, the manifest pins {asset.size}"
        elif asset.sha256 is not None and digest != asset.sha256:
            bad = f"sha256 mismatch: got {digest}, the manifest pins {asset.sha256}"
        if bad:
            rejected = _reject(part, dest, asset.filename)
            raise CamoError(f"{label}: {bad} ({asset.url}); refused, the download was moved to {rejected}")
        os.replace(part, final)
        _fsync_dir(dest)
        return Download(final, digest, actual_size, fetched=True, bytes_transferred=hasher.received)


def _reason(exc: BaseException) -> str:
    if isinstance(exc, urllib.error.HTTPError):
        return f"HTTP {exc.code} {exc.reason}"
    if isinstance(exc, urllib.error.URLError):
        return f"cannot connect ({exc.reason})"
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _reject(path: Path, dest: Path, filename: str | None = None) -> Path:
    target = dest / ".rejected" / (filename or path.name)
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(path, target)
    return target


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


# ------------------------------------------------------------------------------------------ archives


def _member_name(name: str, label: str) -> str:
    """The normalised relative path of an archive member; refuses absolute paths and ``..``."""
    try:
        return safe_relpath("member", name.rstrip("/") or ".")
    except CamoError:
        raise CamoError(f"{label}: unsafe archive member {name!r} (absolute path or '..'); refusing to unpack") from None


def _zip_type(info: zipfile.ZipInfo) -> str:
    mode = (info.external_attr >> 16) & 0o170000
    if mode == 0o120000:
        return "link"
    if info.is_dir():
        return "dir"
    return "file" if mode in (0, 0o100000) else "other"


def _tar_type(m: tarfile.TarInfo) -> str:
    return "file" if m.isreg() else "dir" if m.isdir() else "link" if (m.issym() or m.islnk()) else "other"


def _missing_member(asset: Asset, archive_path: Path, files: list[str]) -> CamoError:
    base = asset.member.rsplit("/", 1)[-1]
    near = [n for n in files if n.rsplit("/", 1)[-1] == base][:3]
    hint = f"; files with that name: {', '.join(near)}" if near else ""
    where = f" under {', '.join(asset.extract)}" if asset.extract and not near else ""
    return CamoError(f"{asset.name}: member {asset.member!r} is not in {archive_path.name}{where}{hint}")


def ensure_extracted(asset: Asset, dest: Path, archive_path: Path, sha256: str, opts: FetchOptions) -> Path:
    """Unpack ``asset``'s archive to ``DEST/<name>/`` (safely, atomically); returns the member's path.

    Safety: any member with an absolute path or a ``..`` component makes the whole archive refused; a
    link or special file among the members to unpack likewise (tar members also pass Python's ``data``
    filter). Only members under ``extract`` (default: all) are unpacked, into a temporary folder that
    replaces ``DEST/<name>/`` when complete. A tar archive is read in one streaming pass.
    """
    dest = Path(dest)
    target = asset.extract_dir(dest)
    marker = target / MARKER
    stamp = {"sha256": sha256, "archive": archive_path.name, "extract": list(asset.extract or []), "member": asset.member}
    if marker.is_file():
        try:
            same = json.loads(marker.read_text(encoding="utf-8")) == stamp
        except (ValueError, OSError):
            same = False
        if same and asset.use_path(dest).is_file():
            return asset.use_path(dest)
    with _lock(dest / ".partial" / f"{asset.name}.extract.lock"):
        return _extract(asset, dest, archive_path, stamp)


def _extract(asset: Asset, dest: Path, archive_path: Path, stamp: dict) -> Path:
    label = asset.name
    target = asset.extract_dir(dest)
    work = dest / ".partial" / f"{asset.name}.extract"
    old = dest / ".partial" / f"{asset.name}.old"
    for p in (work, old):
        if p.exists():
            shutil.rmtree(p)
    work.mkdir(parents=True)
    ok = False
    try:
        seen_files: list[str] = []
        if asset.archive == "zip":
            with zipfile.ZipFile(archive_path) as zf:
                infos = zf.infolist()
                chosen = []
                for info in infos:
                    name = _member_name(info.filename, label)
                    t = _zip_type(info)
                    if not member_selected(name, asset.extract):
                        continue
                    if t in ("link", "other"):
                        raise CamoError(f"{label}: archive member {info.filename!r} is a link or special file; refusing to unpack")
                    if t == "file":
                        seen_files.append(name)
                    chosen.append(info)
                if asset.member not in seen_files:
                    raise _missing_member(asset, archive_path, [_member_name(i.filename, label) for i in infos])
                for info in chosen:
                    zf.extract(info, work)
        else:
            all_files: list[str] = []
            with tarfile.open(archive_path, "r:*") as tf:
                for m in tf:  # one sequential pass (a .tar.gz is decompressed once)
                    name = _member_name(m.name, label)
                    t = _tar_type(m)
                    if t == "file":
                        all_files.append(name)
                    if not member_selected(name, asset.extract):
                        continue
                    if t in ("link", "other"):
                        raise CamoError(f"{label}: archive member {m.name!r} is a link or special file; refusing to unpack")
                    if t == "file":
                        seen_files.append(name)
                    if hasattr(tarfile, "data_filter"):
                        tf.extract(m, work, filter="data")
                    else:  # pragma: no cover - Python < 3.11.4; the member was checked above
                        tf.extract(m, work)
            if asset.member not in seen_files:
                raise _missing_member(asset, archive_path, all_files)
        (work / MARKER).write_text(json.dumps(stamp, indent=1) + "\n", encoding="utf-8")
        ok = True
    except (zipfile.BadZipFile, tarfile.TarError, EOFError, OSError) as exc:
        raise CamoError(f"{label}: cannot unpack {archive_path.name}: {_reason(exc)}") from None
    finally:
        if not ok:
            shutil.rmtree(work, ignore_errors=True)
    if target.exists():
        os.replace(target, old)
    os.replace(work, target)
    shutil.rmtree(old, ignore_errors=True)
    return asset.use_path(dest)
