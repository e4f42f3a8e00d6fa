"""camo_base.tables: parquet by path (no Python file object in pyarrow's threads), same tables as pandas'."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from camo_base.tables import read_parquet, write_parquet

ROOT = Path(__file__).resolve().parents[1]


def _frame() -> pd.DataFrame:
    return pd.DataFrame({
        "run": ["a", "b", "c"], "view": np.array([0, 1, 2], np.int64), "psnr": [31.5, np.nan, np.inf],
        "practice": [True, False, True], "label": pd.Categorical(["Ours", "Mean", "Ours"]),
    })


def test_round_trip_equals_pandas_own(tmp_path):
    df = _frame()
    ours, theirs = tmp_path / "ours.parquet", tmp_path / "theirs.parquet"
    write_parquet(df, ours)
    df.to_parquet(theirs, index=False)
    # either reader on either file gives the frame back, dtypes included (categorical, NaN, inf)
    for p in (ours, theirs):
        pd.testing.assert_frame_equal(read_parquet(p), df)
        pd.testing.assert_frame_equal(read_parquet(p), pd.read_parquet(p))
    assert read_parquet(ours, columns=["psnr", "run"]).columns.tolist() == ["psnr", "run"]


def test_index_is_dropped_unless_asked(tmp_path):
    df = _frame().set_index("run")
    write_parquet(df, tmp_path / "a.parquet")
    write_parquet(df, tmp_path / "b.parquet", index=True)
    assert "run" not in read_parquet(tmp_path / "a.parquet").columns
    assert read_parquet(tmp_path / "b.parquet").index.tolist() == ["a", "b", "c"]


def test_missing_and_corrupt_files_raise(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_parquet(tmp_path / "none.parquet")
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"PAR1 not a table")
    with pytest.raises(Exception, match="(?i)parquet|magic|size"):
        read_parquet(bad)


def test_the_project_reads_and_writes_parquet_only_through_camo_base_tables():
    """pandas' read_parquet / to_parquet pass pyarrow a Python file object: a process could abort at exit."""
    pattern = re.compile(r"pd\.read_parquet\(|\.to_parquet\(|pq\.read_table\(|pq\.write_table\(")
    allowed = {Path("camo_base/tables.py"), Path("tests/test_tables.py"), Path("bench/bench_parquet_exit.py")}
    offenders = []
    for p in sorted(ROOT.glob("**/*.py")) + sorted(ROOT.glob("notebooks/*.ipynb")):
        rel = p.relative_to(ROOT)
        if rel.parts[0].startswith(".") or rel.parts[0] in {"data", "build"} or rel in allowed:
            continue
        text = p.read_text(encoding="utf-8")
        if p.suffix == ".ipynb":
            text = "".join("".join(c["source"]) for c in json.loads(text)["cells"])
        offenders += [f"{rel}: {m.group(0)}" for m in pattern.finditer(text)]
    assert offenders == [], "use camo_base.tables.read_parquet / write_parquet: " + "; ".join(offenders)
