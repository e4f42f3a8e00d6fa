"""Serving the stimulus images: static, immutable, and with headers that say nothing about the build.

Every stimulus image is written twice by ``camo study build-stimuli`` (:class:`study_site.stimuli.StimulusWriter`):
``images/<id>.webp`` (lossless WebP, checked pixel-identical to the PNG when written; 25-45 % fewer bytes) and
``images/<id>.png`` (the fallback for a browser without WebP). The task page gets both URLs, ``/i/<id>.webp`` and
``/i/<id>.png``. ``<id>`` is a random token drawn anew for every image of every build, so a URL never names other
bytes: the responses are cached for a year as ``immutable``.

:class:`StaticStimuli` serves them as WSGI middleware in front of the Flask app -- no session, no database, no
Flask request: a dictionary look-up and the file handed to the server's ``wsgi.file_wrapper`` (sendfile under
gunicorn and waitress). The stimulus id is unguessable (96 random bits) and reaches a participant only in their own
plan (``/api/state``), so the URL is the permission, as for any capability URL.

Headers: ``Content-Type``, ``Content-Length``, ``Cache-Control: public, max-age=31536000, immutable``, ``ETag`` =
the first 32 hex digits of the SHA-256 of the bytes (``If-None-Match`` answers 304), ``X-Content-Type-Options``,
``Cross-Origin-Resource-Policy: same-origin``. No ``Last-Modified`` and no time-derived ``ETag``: files written
one run after the other would otherwise sort the stimuli of one build by run (and so by method).

Why not WhiteNoise (the usual WSGI static server): it sends ``Last-Modified`` and an ETag made of the file's
modification time and size -- exactly the build times this module must not reveal -- and does not serve one
image under two formats chosen by the page.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

#: Cache-Control of a stimulus image: its URL never names other bytes.
IMMUTABLE = "public, max-age=31536000, immutable"
MIMETYPES = {".png": "image/png", ".webp": "image/webp"}


@dataclass(frozen=True)
class StaticFile:
    path: Path
    mimetype: str
    size: int
    etag: str  # quoted strong ETag: the content hash

    def headers(self, cache_control: str = IMMUTABLE) -> list[tuple[str, str]]:
        return [("Content-Type", self.mimetype), ("Content-Length", str(self.size)), ("Cache-Control", cache_control),
                ("ETag", self.etag), ("X-Content-Type-Options", "nosniff"),
                ("Cross-Origin-Resource-Policy", "same-origin")]


def static_file(path: Path) -> StaticFile:
    """A file with its content-hash ETag (reads it once)."""
    data = path.read_bytes()
    return StaticFile(path, MIMETYPES.get(path.suffix, "application/octet-stream"), len(data),
                      '"' + hashlib.sha256(data).hexdigest()[:32] + '"')


def etag_matches(environ, etag: str) -> bool:
    """Whether the request's ``If-None-Match`` names ``etag`` (or ``*``)."""
    inm = environ.get("HTTP_IF_NONE_MATCH", "")
    if not inm:
        return False
    tags = {t.strip().removeprefix("W/") for t in inm.split(",")}
    return "*" in tags or etag in tags


class StaticStimuli:
    """WSGI middleware: ``GET``/``HEAD /i/<name>`` from ``files`` (``{"<id>.webp": StaticFile, ...}``), anything
    else to ``app``. An unknown name is a plain 404."""

    prefix = "/i/"

    def __init__(self, app, files: dict[str, StaticFile]):
        self.app = app
        self.files = files

    def __call__(self, environ, start_response):
        path = environ.get("PATH_INFO", "")
        if not path.startswith(self.prefix):
            return self.app(environ, start_response)
        method = environ.get("REQUEST_METHOD", "GET")
        f = self.files.get(path[len(self.prefix):])
        if f is None or method not in ("GET", "HEAD"):
            code = "404 Not Found" if f is None else "405 Method Not Allowed"
            body = code.encode()
            start_response(code, [("Content-Type", "text/plain; charset=utf-8"), ("Content-Length", str(len(body))),
                                  ("Cache-Control", "no-store"), ("X-Content-Type-Options", "nosniff")])
            return [body]
        if etag_matches(environ, f.etag):
            start_response("304 Not Modified", [h for h in f.headers() if h[0] in ("Cache-Control", "ETag")])
            return []
        start_response("200 OK", f.headers())
        if method == "HEAD":
            return []
        fh = open(f.path, "rb")  # noqa: SIM115 - closed by the server through the file wrapper
        wrapper = environ.get("wsgi.file_wrapper")
        if wrapper is not None:
            return wrapper(fh, 256 * 1024)
        try:
            return [fh.read()]
        finally:
            fh.close()
