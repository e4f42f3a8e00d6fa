"""``camo data``: manifests, resumable verified downloads, safe unpacking, scene packs.

Everything runs against a local ``ThreadingHTTPServer`` on 127.0.0.1 (ephemeral port) that the fixture starts
and stops; a guard makes any other address fail the test. Fixture files are generated deterministically so
that ``data_manifests/example_local.toml`` can pin their real checksums.
"""

from __future__ import annotations

import hashlib
import http.server
import threading
import tomllib
import urllib.parse
from pathlib import Path

import pytest

from fixture_archives import tar_bytes, zip_bytes
from camo import cli
from optimizer.scenes.data import fetch as fetch_mod
from optimizer.scenes.data.manifest import PLACEHOLDER, load_manifest

REPO = Path(__file__).resolve().parents[1]
MANIFESTS = REPO / "data_manifests"
EXAMPLE = MANIFESTS / "example_local.toml"

CUBE_OBJ = """# unit cube (test fixture, CC0)
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
f 1 3 2
f 1 4 3
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 2 3 7
f 2 7 6
f 3 4 8
f 3 8 7
f 4 1 5
f 4 5 8
"""

ROOM_XML = """<scene version="3.0.0">
    <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
    <shape type="rectangle">
        <transform name="to_world"><scale value="5"/></transform>
        <bsdf type="diffuse"/>
    </shape>
</scene>
"""


def make_fixtures() -> dict[str, bytes]:
    """The files the test server serves (deterministic: their checksums are pinned in example_local.toml)."""
    sky = hashlib.shake_256(b"camo-test-sky").digest(3 * (1 << 20) + 12345)
    return {
        "sky.hdr": sky,
        "chair.zip": zip_bytes({"chair/chair.obj": CUBE_OBJ.encode(), "chair/LICENSE.txt": b"CC0-1.0 test fixture\n"}),
        "room.tar": tar_bytes({"room/scene.xml": ROOM_XML.encode(), "room/LICENSE.txt": b"CC0-1.0 test fixture\n"}),
        # served instead of what its manifest entry pins
        "corrupt.hdr": hashlib.shake_256(b"camo-test-corrupt-served").digest(200_000),
        "loose.hdr": hashlib.shake_256(b"camo-test-unpinned").digest(300_000),
        "evil.zip": zip_bytes({"ok/a.obj": CUBE_OBJ.encode(), "../escaped.obj": CUBE_OBJ.encode()}),
        "abs.tar": tar_bytes({"/tmp/camo-abs-escape.obj": CUBE_OBJ.encode()}),
    }


def sha(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()


# ------------------------------------------------------------------------------------------ server


class _State:
    def __init__(self, files: dict[str, bytes]):
        self.files = files
        self.ignore_range = False
        self.drop_once: set[str] = set()  # paths whose next response stops halfway
        self.fail_once: set[str] = set()  # paths whose next request gets 503
        self.log: list[dict] = []  # one entry per GET: path, range, status, sent
        self.lock = threading.Lock()


def _handler(state: _State):
    class Handler(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):  # keep test output clean
            pass

        def do_GET(self):
            path = urllib.parse.urlsplit(self.path).path.lstrip("/")
            rng = self.headers.get("Range")
            entry = {"path": path, "range": rng, "status": None, "sent": 0}
            with state.lock:
                state.log.append(entry)
                drop = path in state.drop_once
                state.drop_once.discard(path)
                fail = path in state.fail_once
                state.fail_once.discard(path)
            if fail:
                entry["status"] = 503
                self.send_error(503)
                return
            data = state.files.get(path)
            if data is None:
                entry["status"] = 404
                self.send_error(404)
                return
            start = 0
            status = 200
            if rng and not state.ignore_range:
                spec = rng.split("=", 1)[1]
                a, _, b = spec.partition("-")
                start = int(a)
                end = int(b) if b else len(data) - 1
                if start >= len(data):
                    entry["status"] = 416
                    self.send_response(416)
                    self.send_header("Content-Range", f"bytes */{len(data)}")
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                status = 206
                body = data[start:end + 1]
            else:
                body = data
            entry["status"] = status
            self.send_response(status)
            self.send_header("Content-Type", "application/octet-stream")
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Accept-Ranges", "bytes")
            if status == 206:
                self.send_header("Content-Range", f"bytes {start}-{start + len(body) - 1}/{len(data)}")
            self.end_headers()
            if drop:
                half = body[: len(body) // 2]
                self.wfile.write(half)
                self.wfile.flush()
                entry["sent"] = len(half)
                self.close_connection = True
                return
            self.wfile.write(body)
            entry["sent"] = len(body)

    return Handler


@pytest.fixture()
def server(loopback_http):
    state = _State(make_fixtures())
    state.base = loopback_http(_handler(state))
    return state


def fetch(cli, server, manifest, dest, *extra) -> tuple[int, str, str]:
    return cli("data", "fetch", str(manifest), "--dest", str(dest), "--base-url", server.base,
               "--backoff", "0.01", "--timeout", "5", "--quiet", *extra)


EXTRA_ENTRIES = """
[[asset]]
name = "corrupt"
kind = "hdri"
url = "corrupt.hdr"
licence = "CC0-1.0"
sha256 = "{corrupt_sha}"
size = 200000
[asset.source]
dataset = "camo test fixtures"
homepage = "https://example.invalid/camo-tests"

[[asset]]
name = "loose"
kind = "hdri"
url = "loose.hdr"
licence = "CC0-1.0"
sha256 = "TO-BE-PINNED"   # not known yet
size = "TO-BE-PINNED"
[asset.source]
dataset = "camo test fixtures"
homepage = "https://example.invalid/camo-tests"
"""


@pytest.fixture()
def manifest(tmp_path) -> Path:
    """example_local.toml plus a corrupted entry (pinned to other bytes than served) and an unpinned one."""
    wrong = sha(b"the bytes this entry was pinned to")
    p = tmp_path / "m.toml"
    p.write_text(EXAMPLE.read_text(encoding="utf-8") + EXTRA_ENTRIES.format(corrupt_sha=wrong), encoding="utf-8")
    return p


# ------------------------------------------------------------------------------------------ tests


def test_example_manifest_pins_the_fixtures():
    man = load_manifest(EXAMPLE)
    files = make_fixtures()
    assert [a.name for a in man.assets] == ["sky", "chair", "room"]
    for a in man.assets:
        assert a.pinned
        assert a.sha256 == sha(files[a.filename]) and a.size == len(files[a.filename]), a.name


@pytest.mark.parametrize("name", ["polyhaven_hdris.toml", "bitterli_scenes.toml", "navi_objaverse_objects.toml"])
def test_real_manifests_parse_and_are_refused_unpinned(name, cli, tmp_path, monkeypatch):
    def no_network(*a, **k):
        raise AssertionError("no network access expected")

    monkeypatch.setattr(fetch_mod, "_open", no_network)
    man = load_manifest(MANIFESTS / name)
    assert len(man.assets) >= 3
    for a in man.assets:
        assert a.url.startswith("https://")
        assert a.licence and a.source["dataset"] and a.source["homepage"].startswith("https://")
        assert not a.pinned  # nobody could download them here: they must say so
    rc, out, err = cli("data", "fetch", str(MANIFESTS / name), "--dest", str(tmp_path / "d"))
    assert rc == 2 and err.count("\n") == 1 and "not pinned" in err and "--pin" in err
    assert not (tmp_path / "d").exists() or not any((tmp_path / "d").iterdir())


def test_fetch_verifies_unpacks_then_skips(server, cli, tmp_path):
    dest = tmp_path / "d"
    rc, out, err = fetch(cli, server, EXAMPLE, dest)
    assert rc == 0, err
    files = server.files
    assert (dest / "sky.hdr").read_bytes() == files["sky.hdr"]
    assert (dest / "chair.zip").read_bytes() == files["chair.zip"]
    assert (dest / "chair" / "chair" / "chair.obj").read_text() == CUBE_OBJ
    assert (dest / "room" / "room" / "scene.xml").read_text() == ROOM_XML
    assert not list((dest / ".partial").glob("*.part"))
    assert sorted(e["path"] for e in server.log) == ["chair.zip", "room.tar", "sky.hdr"]

    n = len(server.log)
    rc, out, err = fetch(cli, server, EXAMPLE, dest)
    assert rc == 0 and len(server.log) == n  # nothing downloaded again
    assert out.count("present, checksum ok") == 3

    rc, out, err = cli("data", "verify", str(EXAMPLE), "--dest", str(dest))
    assert rc == 0 and "3 ok, 0 missing, 0 mismatch, 0 unpinned" in out


def test_corrupted_download_is_refused(server, cli, tmp_path, manifest):
    dest = tmp_path / "d"
    assert fetch(cli, server, manifest, dest, "--only", "sky")[0] == 0
    sky = dest / "sky.hdr"
    before = (sky.stat().st_ino, sky.stat().st_mtime_ns)

    rc, out, err = fetch(cli, server, manifest, dest, "--only", "sky", "corrupt")
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith("camo: error: corrupt: sha256 mismatch")
    assert not (dest / "corrupt.hdr").exists()
    assert (dest / ".rejected" / "corrupt.hdr").read_bytes() == server.files["corrupt.hdr"]
    assert (sky.stat().st_ino, sky.stat().st_mtime_ns) == before and sky.read_bytes() == server.files["sky.hdr"]


def test_interrupted_download_resumes_from_partial_file(server, cli, tmp_path):
    dest = tmp_path / "d"
    size = len(server.files["sky.hdr"])
    server.drop_once.add("sky.hdr")
    rc, out, err = fetch(cli, server, EXAMPLE, dest, "--only", "sky", "--retries", "0")
    assert rc == 2 and err.count("\n") == 1 and "run again to resume" in err
    part = dest / ".partial" / "sky.hdr.part"
    kept = part.stat().st_size
    assert 0 < kept < size and not (dest / "sky.hdr").exists()
    assert server.log[-1]["sent"] == kept

    rc, out, err = fetch(cli, server, EXAMPLE, dest, "--only", "sky")
    assert rc == 0, err
    second = server.log[-1]
    assert second["range"] == f"bytes={kept}-" and second["status"] == 206
    assert second["sent"] == size - kept < size  # only the rest was transferred
    assert (dest / "sky.hdr").read_bytes() == server.files["sky.hdr"] and not part.exists()


def test_dropped_connection_is_retried_within_one_run(server, cli, tmp_path):
    dest = tmp_path / "d"
    server.drop_once.add("sky.hdr")
    rc, out, err = fetch(cli, server, EXAMPLE, dest, "--only", "sky")
    assert rc == 0, err
    first, second = server.log
    assert first["range"] is None and second["range"] == f"bytes={first['sent']}-"
    assert first["sent"] + second["sent"] == len(server.files["sky.hdr"])
    assert "retry 1/4" in out
    assert (dest / "sky.hdr").read_bytes() == server.files["sky.hdr"]


def test_server_error_is_retried(server, cli, tmp_path):
    server.fail_once.add("sky.hdr")
    rc, out, err = fetch(cli, server, EXAMPLE, tmp_path / "d", "--only", "sky")
    assert rc == 0, err
    assert [e["status"] for e in server.log] == [503, 200] and "HTTP 503" in out
    assert (tmp_path / "d" / "sky.hdr").read_bytes() == server.files["sky.hdr"]


def test_server_ignoring_range_restarts_and_ends_right(server, cli, tmp_path):
    dest = tmp_path / "d"
    server.ignore_range = True
    server.drop_once.add("sky.hdr")
    rc, out, err = fetch(cli, server, EXAMPLE, dest, "--only", "sky")
    assert rc == 0, err
    first, second = server.log
    assert second["range"] is not None and second["status"] == 200  # asked to resume, got the whole file
    assert "ignored the range request" in out
    assert (dest / "sky.hdr").read_bytes() == server.files["sky.hdr"]


def test_unpinned_refused_then_pinned_with_pin(server, cli, tmp_path, manifest):
    dest = tmp_path / "d"
    original = manifest.read_text()
    rc, out, err = fetch(cli, server, manifest, dest, "--only", "sky", "loose")
    assert rc == 2 and err.count("\n") == 1 and "loose" in err and "--pin" in err
    assert server.log == [] and not (dest / "sky.hdr").exists()

    rc, out, err = fetch(cli, server, manifest, dest, "--only", "sky", "loose", "--pin")
    assert rc == 0, err
    assert (dest / "loose.hdr").read_bytes() == server.files["loose.hdr"]
    assert manifest.read_text() == original  # the input manifest is never modified
    pinned = manifest.with_name("m.pinned.toml")
    text = pinned.read_text()
    assert text.startswith("# Pinned by `camo data fetch --pin`")
    assert "# not known yet" not in text  # the placeholder line was replaced, comment and all
    assert original.splitlines()[0] in text and "# the file to use inside the archive" in text  # comments kept
    assert text.count(PLACEHOLDER) == 1  # only in the header comment now
    data = tomllib.loads(text)
    loose = next(a for a in data["asset"] if a["name"] == "loose")
    assert loose["sha256"] == sha(server.files["loose.hdr"]) and loose["size"] == len(server.files["loose.hdr"])
    assert next(a for a in data["asset"] if a["name"] == "corrupt")["size"] == 200000  # others untouched

    # a second --pin from the original refuses to overwrite the pinned file; the pinned manifest fetches as usual
    rc, out, err = fetch(cli, server, manifest, dest, "--only", "loose", "--pin")
    assert rc == 2 and "already exists" in err
    n = len(server.log)
    rc, out, err = fetch(cli, server, pinned, dest, "--only", "sky", "loose")
    assert rc == 0 and len(server.log) == n


def test_verify_reports_ok_missing_mismatch_unpinned(server, cli, tmp_path, manifest):
    dest = tmp_path / "d"
    assert fetch(cli, server, manifest, dest, "--only", "sky", "chair", "room")[0] == 0
    (dest / "chair.zip").unlink()
    sky = dest / "sky.hdr"
    b = bytearray(sky.read_bytes())
    b[1000] ^= 0xFF
    sky.write_bytes(bytes(b))
    rc, out, err = cli("data", "verify", str(manifest), "--dest", str(dest))
    assert rc == 1
    status = {ln.split()[0]: ln.split()[2] for ln in out.splitlines()[2:] if ln and not ln[0].isdigit()}
    assert status == {"sky": "mismatch", "chair": "missing", "room": "ok", "corrupt": "missing", "loose": "unpinned"}
    assert "1 ok, 2 missing, 1 mismatch, 1 unpinned" in out

    # a fetch repairs it: the bad file is moved aside, never kept at the final path
    assert fetch(cli, server, EXAMPLE, dest)[0] == 0
    assert (dest / ".rejected" / "sky.hdr").read_bytes() == bytes(b)
    assert cli("data", "verify", str(EXAMPLE), "--dest", str(dest))[0] == 0


def test_pack_from_zip_obj_is_a_valid_scene_pack(server, cli, tmp_path):
    from optimizer.scenes.mesh import load_mesh
    from optimizer.scenes.scenepack import load_pack

    dest = tmp_path / "d"
    assert fetch(cli, server, EXAMPLE, dest)[0] == 0
    out = tmp_path / "packs" / "chair.toml"
    rc, o, err = cli("data", "pack", str(EXAMPLE), "chair", "--dest", str(dest), "--out", str(out))
    assert rc == 0, err
    pack = load_pack(out)
    assert Path(pack.object.mesh) == (dest / "chair" / "chair" / "chair.obj").resolve()
    assert pack.object.rotation == (0.0, 0.0, 15.0) and pack.environment.builtin == "meadow"
    assert "CC0-1.0" in out.read_text()  # the licence is credited in the pack
    mesh = load_mesh(pack.object.mesh)
    assert mesh.vertices.shape == (8, 3) and mesh.faces.shape == (12, 3)

    # combined with the HDRI of the same manifest, and refusing to overwrite without --overwrite
    rc, o, err = cli("data", "pack", str(EXAMPLE), "chair", "--dest", str(dest), "--out", str(out), "--with", "sky")
    assert rc == 2 and "--overwrite" in err
    rc, o, err = cli("data", "pack", str(EXAMPLE), "chair", "--dest", str(dest), "--out", str(out),
                     "--with", f"{EXAMPLE}:sky", "--overwrite")
    assert rc == 0, err
    pack = load_pack(out)
    assert Path(pack.environment.panorama) == (dest / "sky.hdr").resolve() and pack.environment.ground_extent == 20.0

    # the --with asset fetched into another folder (and named through another manifest file)
    other = tmp_path / "other.toml"
    other.write_text(EXAMPLE.read_text())
    rc, o, err = cli("data", "pack", str(EXAMPLE), "chair", "--dest", str(dest), "--out", str(out),
                     "--with", f"{other}:sky", "--with-dest", str(tmp_path / "elsewhere"), "--overwrite")
    assert rc == 2 and "not fetched into" in err and "elsewhere" in err

    # a Mitsuba scene from a tar archive, with a built-in object
    out2 = tmp_path / "packs" / "room.toml"
    rc, o, err = cli("data", "pack", str(EXAMPLE), "room", "--dest", str(dest), "--out", str(out2))
    assert rc == 0, err
    pack = load_pack(out2)
    assert Path(pack.environment.xml).name == "scene.xml" and pack.object.primitive == "utility_box"


def test_pack_needs_a_fetched_asset(cli, tmp_path):
    rc, out, err = cli("data", "pack", str(EXAMPLE), "chair", "--dest", str(tmp_path), "--out",
                       str(tmp_path / "p.toml"))
    assert rc == 2 and "not fetched" in err and not (tmp_path / "p.toml").exists()


@pytest.mark.parametrize("fname,archive,member", [("evil.zip", "zip", "ok/a.obj"), ("abs.tar", "tar", "tmp/x.obj")])
def test_unsafe_archives_are_refused(server, cli, tmp_path, fname, archive, member):
    data = server.files[fname]
    p = tmp_path / "evil.toml"
    p.write_text(f"""
[[asset]]
name = "evil"
kind = "mesh"
url = "{fname}"
licence = "CC0-1.0"
sha256 = "{sha(data)}"
size = {len(data)}
archive = "{archive}"
member = "{member}"
[asset.source]
dataset = "camo test fixtures"
homepage = "https://example.invalid/camo-tests"
""")
    dest = tmp_path / "inner" / "d"
    rc, out, err = fetch(cli, server, p, dest)
    assert rc == 2 and err.count("\n") == 1 and "unsafe archive member" in err
    assert not (dest / "evil").exists() and not (tmp_path / "inner" / "escaped.obj").exists()
    assert not Path("/tmp/camo-abs-escape.obj").exists()


@pytest.mark.parametrize("edit,message", [
    (lambda t: t.replace('kind = "hdri"', 'kind = "texture"', 1), "kind must be one of"),
    (lambda t: t.replace('licence = "CC0-1.0"', 'licence = "CC0-1.0"\ncolour = 1', 1), "unknown key(s) colour"),
    (lambda t: t.replace('name = "chair"', 'name = "sky"', 1), "duplicate asset name"),
    (lambda t: t.replace('member = "chair/chair.obj"', 'member = "../chair.obj"', 1), "relative path inside"),
    (lambda t: t.replace('sha256 = "', 'sha256 = "XYZ', 1), "64 lowercase hex"),
    (lambda t: t + "\n[[asset]\n", "not valid TOML"),
])
def test_bad_manifests_get_one_line_errors(cli, tmp_path, edit, message):
    p = tmp_path / "bad.toml"
    p.write_text(edit(EXAMPLE.read_text()))
    rc, out, err = cli("data", "verify", str(p), "--dest", str(tmp_path))
    assert rc == 2 and err.count("\n") == 1 and message in err, err


def test_http_404_is_one_line(server, cli, tmp_path):
    p = tmp_path / "m.toml"
    p.write_text(EXAMPLE.read_text().replace('url = "sky.hdr"', 'url = "nope.hdr"'))
    rc, out, err = fetch(cli, server, p, tmp_path / "d", "--only", "sky")
    assert rc == 2 and err.count("\n") == 1 and "HTTP 404" in err
    assert len(server.log) == 1  # 404 is not retried


def test_data_list(cli):
    rc, out, err = cli("data", "list", str(MANIFESTS / "polyhaven_hdris.toml"))
    assert rc == 0 and "CC0-1.0" in out and "dl.polyhaven.org" in out


def test_entries_sharing_one_archive_download_it_once(server, cli, tmp_path):
    data = server.files["chair.zip"]
    entry = """
[[asset]]
name = "{name}"
kind = "mesh"
url = "chair.zip"
licence = "CC0-1.0"
sha256 = "{sha}"
size = {size}
archive = "zip"
member = "chair/chair.obj"
extract = ["chair/"]
[asset.source]
dataset = "camo test fixtures"
homepage = "https://example.invalid/camo-tests"
"""
    p = tmp_path / "shared.toml"
    p.write_text("".join(entry.format(name=n, sha=sha(data), size=len(data)) for n in ("one", "two")))
    rc, out, err = fetch(cli, server, p, tmp_path / "d")
    assert rc == 0, err
    assert [e["path"] for e in server.log] == ["chair.zip"]
    for n in ("one", "two"):
        assert (tmp_path / "d" / n / "chair" / "chair.obj").read_text() == CUBE_OBJ
    assert "shares chair.zip" in out


def test_pin_text_edits_lines_or_rewrites():
    from optimizer.scenes.data.manifest import pin_text

    block = ('[[asset]]\nname = "a"  # keep me\nkind = "hdri"\nurl = "https://x.invalid/a.hdr"\nlicence = "CC0-1.0"\n'
             'sha256 = "TO-BE-PINNED"  # placeholder\nsize = "TO-BE-PINNED"\n'
             '[asset.source]\ndataset = "d"\nhomepage = "https://x.invalid"\n')
    out = pin_text(block, {"a": ("1" * 64, 7)}, Path("m.toml"))
    assert "# keep me" in out and "# placeholder" not in out
    assert tomllib.loads(out)["asset"][0]["sha256"] == "1" * 64 and tomllib.loads(out)["asset"][0]["size"] == 7
    again = pin_text(out, {"a": ("2" * 64, 8)}, Path("m.toml"))  # one header, not two
    assert again.count("# Pinned by") == 1 and tomllib.loads(again)["asset"][0]["size"] == 8

    inline = ('asset = [{ name = "a", kind = "hdri", url = "https://x.invalid/a.hdr", licence = "CC0-1.0", '
              'sha256 = "TO-BE-PINNED", size = "TO-BE-PINNED", source = { dataset = "d", homepage = "https://x.invalid" } }]\n')
    out = pin_text(inline, {"a": ("3" * 64, 9)}, Path("m.toml"))  # layout the line editor does not handle
    assert tomllib.loads(out)["asset"][0] | {"source": None} == {
        "name": "a", "kind": "hdri", "url": "https://x.invalid/a.hdr", "licence": "CC0-1.0",
        "sha256": "3" * 64, "size": 9, "source": None}
