"""Parquet tables read and written by path, never through a Python file object.

Every ``metrics.parquet``, ``predicted*.parquet`` and ``trials.parquet`` of the project goes through these two
functions. ``pandas.read_parquet(path)`` / ``DataFrame.to_parquet(path)`` open a local path as a *Python* file
object and hand it to pyarrow, whose worker threads then read through Python and need the GIL. A worker still
holding such a task when the interpreter finalises is stopped by ``pthread_exit`` inside a C++ frame, and the process
aborts *after* its work is done: ``terminate called without an active exception``, exit status -6 (apache/arrow
#34314, #50482; pyarrow 26.0.1, pandas 2.3.3). It is rare and needs a loaded machine: on the 2-core reference
machine at load 10-13 a script that only does ``pd.read_parquet`` of a 10-row file aborted at exit in 2 of 300 runs,
and CI lost a run to it (the metric worked example of ``tests/test_registries.py``, at two test processes). Handing
pyarrow the path string lets Arrow open and read the file itself, with no Python in its threads (the upstream
reports' workaround). Side by side, interleaved, two at a time (``python bench/bench_parquet_exit.py --runs 300``,
load 4-13): ``pd.read_parquet`` aborted at exit in 5 of 300 runs, :func:`read_parquet` in 0 of 300.

>>> import tempfile, pandas as pd
>>> from pathlib import Path
>>> p = Path(tempfile.mkdtemp()) / "t.parquet"
>>> write_parquet(pd.DataFrame({"view": [0, 1], "psnr": [31.5, 29.0]}), p)
>>> read_parquet(p, columns=["psnr"])["psnr"].tolist()
[31.5, 29.0]
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Sequence

if TYPE_CHECKING:  # pandas is imported by the callers; importing this module stays cheap
    import pandas as pd


def read_parquet(path: str | os.PathLike, columns: Sequence[str] | None = None) -> pd.DataFrame:
    """The table at ``path`` (a local file) as a DataFrame, as ``pandas.read_parquet`` returns it.

    ``columns``: read only these (``None``: all). Raises what pyarrow raises for a missing or corrupt file
    (``FileNotFoundError``, ``pyarrow.ArrowInvalid``, ...); callers turn that into their one-line error.
    """
    import pyarrow.parquet as pq

    return pq.read_table(os.fspath(path), columns=list(columns) if columns is not None else None).to_pandas()


def write_parquet(table: pd.DataFrame, path: str | os.PathLike, index: bool = False) -> None:
    """Write ``table`` to ``path`` (a local file; overwritten), as ``DataFrame.to_parquet(path, index=index)``.

    Not atomic by itself: write to ``camo_base.atomic.atomic_path(target)``'s temporary path to keep earlier
    results when a write fails.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.Table.from_pandas(table, preserve_index=index), os.fspath(path))
