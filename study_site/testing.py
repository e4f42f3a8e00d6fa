"""Fake evaluation directories for tests and benchmarks (random images, rectangular masks)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def make_fake_eval_dir(
    root: str | Path,
    scenes: tuple[str, ...] = ("scene_a", "scene_b"),
    methods: tuple[str, ...] = ("method_x", "method_y"),
    views: int = 2,
    size: tuple[int, int] = (160, 120),
    seed: int = 0,
    ablations: dict[str, tuple[str, str]] | None = None,
) -> list[dict]:
    """Write ``root/renders.json`` and PNGs as `camo evaluate` would; return the entries.

    Each entry gets a random RGB image and a rectangular object mask; the rectangle
    (``x0, y0, x1, y1``, half-open, image pixels) is stored in the entry as ``rect``
    so a test knows where the object is. ``size`` is ``(width, height)``. ``methods`` name runs; ``ablations``
    maps such a name to the ``(method, ablation)`` it stands for (``{"ours-noinp": ("ours", "inpainting")}``).
    """
    from PIL import Image

    rng = np.random.default_rng(seed)
    root = Path(root)
    w, h = size
    entries = []
    for si, scene in enumerate(scenes):
        for name in methods:
            method, ablation = (ablations or {}).get(name, (name, ""))
            run = f"{scene}__{name}"
            d = root / "renders" / run
            d.mkdir(parents=True, exist_ok=True)
            for v in range(views):
                img = _smooth_noise(rng, w, h)
                bw, bh = max(4, w // 4), max(4, h // 4)
                x0 = int(rng.integers(1, w - bw - 1))
                y0 = int(rng.integers(1, h - bh - 1))
                patch = _smooth_noise(rng, bw, bh).astype(np.int16)
                region = img[y0 : y0 + bh, x0 : x0 + bw].astype(np.int16)
                img[y0 : y0 + bh, x0 : x0 + bw] = np.clip((3 * region + patch) // 4, 0, 255).astype(np.uint8)
                mask = np.zeros((h, w), np.uint8)
                mask[y0 : y0 + bh, x0 : x0 + bw] = 255
                stem = f"view_{v:02d}"
                Image.fromarray(img).save(d / f"{stem}_obj.png")
                Image.fromarray(img).save(d / f"{stem}_bg.png")
                Image.fromarray(mask).save(d / f"{stem}_mask.png")
                entries.append(
                    {
                        "run": run,
                        "scene": scene,
                        "object": f"object_{si}",
                        "method": method,
                        "ablation": ablation,
                        "view": v,
                        "image": f"renders/{run}/{stem}_obj.png",
                        "background": f"renders/{run}/{stem}_bg.png",
                        "mask": f"renders/{run}/{stem}_mask.png",
                        "depth": None,
                        "rect": [x0, y0, x0 + bw, y0 + bh],
                    }
                )
    (root / "renders.json").write_text(json.dumps(entries, indent=1))
    return entries


def _smooth_noise(rng, w: int, h: int) -> np.ndarray:
    """Low-frequency random RGB texture (``(h, w, 3)`` uint8) with a little pixel noise."""
    from PIL import Image

    gh, gw = max(2, h // 40), max(2, w // 40)
    lum = rng.uniform(70, 190, (gh, gw, 1))
    tint = rng.normal(0, 1, 3) * 18 + rng.normal(0, 1, (gh, gw, 3)) * 10  # muted, mostly shared hue
    coarse = np.clip(lum + tint, 0, 255).astype(np.uint8)
    smooth = np.asarray(Image.fromarray(coarse).resize((w, h), Image.BICUBIC), dtype=np.int16)
    noise = rng.integers(-10, 11, (h, w, 1), dtype=np.int16)
    return np.clip(smooth + noise, 0, 255).astype(np.uint8)


def mask_rects(stimuli_dir: str | Path) -> dict[str, tuple[int, int, int, int]]:
    """``{stimulus id: (x0, y0, x1, y1)}`` bounding boxes of the masks of a built stimulus set."""
    from study_site.stimuli import StimulusSet

    ss = StimulusSet(stimuli_dir)
    out = {}
    for st in ss.stimuli:
        m = ss.mask(st)
        ys, xs = np.nonzero(m)
        out[st.id] = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
    return out


# ---------------------------------------------------------------------------
# a throw-away PostgreSQL server (tests, bench)
# ---------------------------------------------------------------------------


def find_postgres_bin() -> Path | None:
    """The folder holding initdb/pg_ctl: on PATH, or Debian's /usr/lib/postgresql/<version>/bin (newest)."""
    import shutil

    found = shutil.which("initdb")
    if found and shutil.which("pg_ctl"):
        return Path(found).resolve().parent
    cands = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"), key=lambda p: _version_key(p.parent.parent.name))
    return cands[-1].parent if cands else None


def _version_key(name: str):
    try:
        return tuple(int(x) for x in name.split("."))
    except ValueError:
        return (0,)


class ThrowawayPostgres:
    """A private PostgreSQL cluster in a temporary folder: initdb, pg_ctl start on a unix socket only (no TCP),
    one database; ``stop()`` shuts it down and deletes everything.

    PostgreSQL refuses to run as root: as root the cluster runs as the ``postgres`` user (Debian's package
    creates it), or, without one, as a created system user ``camo-pg``. ``install=True`` runs
    ``.ci/system-deps postgresql`` first when no server binaries are found. ``durable=False`` (tests) turns
    off fsync; the bench keeps PostgreSQL's defaults.
    """

    def __init__(self, dbname: str = "camo_study_test", install: bool = False, durable: bool = False):
        self.dbname, self.install, self.durable = dbname, install, durable
        self.dir: Path | None = None
        self.bin: Path | None = None
        self.user: str | None = None
        self.url: str | None = None

    def _run(self, args: list[str], **kw):
        import subprocess

        cmd = [str(self.bin / args[0]), *args[1:]]
        if self.user is not None:
            cmd = ["runuser", "-u", self.user, "--", *cmd]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=120, **kw)
        if res.returncode != 0:
            raise RuntimeError(f"{args[0]} failed ({res.returncode}): {(res.stderr or res.stdout).strip()[-400:]}")
        return res

    def start(self) -> str:
        import os
        import pwd
        import subprocess
        import tempfile

        self.bin = find_postgres_bin()
        if self.bin is None and self.install:
            script = Path(__file__).resolve().parents[1] / ".ci" / "system-deps"
            subprocess.run(["bash", str(script), "postgresql"], check=False, timeout=900)
            self.bin = find_postgres_bin()
        if self.bin is None:
            raise RuntimeError("PostgreSQL server binaries (initdb, pg_ctl) not found: sudo apt-get install postgresql")
        if os.geteuid() == 0:
            for name in ("postgres", "camo-pg"):
                try:
                    pwd.getpwnam(name)
                    self.user = name
                    break
                except KeyError:
                    continue
            if self.user is None:
                subprocess.run(["useradd", "--system", "--no-create-home", "camo-pg"], check=True, timeout=60)
                self.user = "camo-pg"
        self.dir = Path(tempfile.mkdtemp(prefix="camo_pg_", dir="/tmp"))
        if self.user is not None:
            pw = pwd.getpwnam(self.user)
            os.chown(self.dir, pw.pw_uid, pw.pw_gid)
        data, sock = self.dir / "data", self.dir
        self._run(["initdb", "-D", str(data), "-U", "postgres", "--auth=trust", "-E", "UTF8", "--no-locale",
                   *([] if self.durable else ["--no-sync"])])
        opts = f"-k {sock} -c listen_addresses='' -c max_connections=300"
        if not self.durable:
            opts += " -c fsync=off -c synchronous_commit=off -c full_page_writes=off"
        self._run(["pg_ctl", "-D", str(data), "-l", str(self.dir / "server.log"), "-w", "-t", "60", "-o", opts,
                   "start"])
        self._run(["createdb", "-h", str(sock), "-U", "postgres", self.dbname])
        self.url = f"postgresql+psycopg://postgres@/{self.dbname}?host={sock}"
        return self.url

    def stop(self) -> None:
        import shutil

        if self.dir is None:
            return
        try:
            self._run(["pg_ctl", "-D", str(self.dir / "data"), "-m", "immediate", "-w", "stop"])
        except RuntimeError:
            pass
        shutil.rmtree(self.dir, ignore_errors=True)
        self.dir = None

    def __enter__(self) -> str:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
