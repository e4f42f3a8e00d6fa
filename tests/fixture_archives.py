"""Archives for the ``camo data`` tests, byte for byte reproducible (fixed dates, modes and member order): the
checksums of ``data_manifests/example_local.toml`` pin what these write. Imported by tests/test_data.py and
tests/test_data_registry.py, tests/test_lpips_weights.py (pytest puts tests/ on the path); ``files_handler`` serves
them from a loopback HTTP server."""

from __future__ import annotations

import http.server
import io
import tarfile
import urllib.parse
import zipfile


def zip_bytes(entries: dict[str, bytes], compression: int = zipfile.ZIP_STORED) -> bytes:
    """A zip (a wheel is one) of ``{member: data}``, members dated 1980-01-01 with mode 0644 (Unix)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as zf:
        for name, data in entries.items():
            info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
            info.create_system = 3
            info.external_attr = 0o100644 << 16
            zf.writestr(info, data)
    return buf.getvalue()


def tar_bytes(entries: dict[str, bytes], links: dict[str, str] | None = None, gzip: bool = False) -> bytes:
    """A USTAR tar of ``{member: data}`` (mode 0644, mtime 0) and symbolic ``links`` ``{member: target}``;
    ``gzip``: compressed (a .tgz; the gzip header's own time is not fixed)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz" if gzip else "w", format=tarfile.USTAR_FORMAT) as tf:
        for name, data in entries.items():
            info = tarfile.TarInfo(name)
            info.size, info.mode, info.mtime = len(data), 0o644, 0
            tf.addfile(info, io.BytesIO(data))
        for name, target in (links or {}).items():
            info = tarfile.TarInfo(name)
            info.type, info.linkname = tarfile.SYMTYPE, target
            tf.addfile(info)
    return buf.getvalue()


def files_handler(files: dict[str, bytes], log: list[str]) -> type:
    """An HTTP handler class serving ``files`` (``{url path without the leading '/': bytes}``, looked up at request
    time) and appending every requested path to ``log``; 404 for anything else. For ``loopback_http``."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            path = urllib.parse.unquote(urllib.parse.urlsplit(self.path).path.lstrip("/"))
            log.append(path)
            data = files.get(path)
            if data is None:
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

    return Handler
