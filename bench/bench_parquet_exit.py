"""How often a process aborts at exit after reading a parquet table: pandas' file handle vs camo_base.tables.

    python bench/bench_parquet_exit.py --runs 300 --parallel 2

Each run is a fresh interpreter that imports pandas and pyarrow, reads one small table, prints its length and
exits; the modes are interleaved (run i of every mode before run i + 1) so machine load falls on both alike.
Prints, per mode, the runs that exited non-zero and the stderr line of the first one. The abort is a race at
interpreter finalisation (see camo_base/tables.py), so it shows on a loaded machine: run beside other work.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

MODES = {
    "pandas.read_parquet": "import pandas as pd\ndf = pd.read_parquet(PATH)\n",
    "camo_base.tables.read_parquet": "import pandas as pd\nfrom camo_base.tables import read_parquet\n"
                                     "df = read_parquet(PATH)\n",
}


def _child(mode: str, path: Path) -> tuple[str, int, str]:
    code = f"import sys\nsys.path.insert(0, {str(ROOT)!r})\nPATH = {str(path)!r}\n{MODES[mode]}print(len(df))\n"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    return mode, proc.returncode, proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=300, help="runs per mode (default 300)")
    ap.add_argument("--parallel", type=int, default=2, help="children at a time (default 2)")
    args = ap.parse_args(argv)
    if args.runs < 1 or args.parallel < 1:
        ap.error("--runs and --parallel must be >= 1")
    import pandas as pd

    from camo_base.tables import write_parquet

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "t.parquet"
        write_parquet(pd.DataFrame({"view": range(10), "psnr": [30.0] * 10}), path)
        jobs = [m for _ in range(args.runs) for m in MODES]
        with ThreadPoolExecutor(args.parallel) as pool:
            results = list(pool.map(lambda m: _child(m, path), jobs))
    print(f"{'mode':32s} {'runs':>5s} {'non-zero exits':>15s}  first error")
    for mode in MODES:
        rows = [r for r in results if r[0] == mode]
        bad = [r for r in rows if r[1] != 0]
        print(f"{mode:32s} {len(rows):5d} {len(bad):15d}  {bad[0][2] + ' (exit ' + str(bad[0][1]) + ')' if bad else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
