"""The resume contract every start search of a run keeps (the roughness start search and the clear-glass candidate,
optimizer/optimise/startsearch.py): its choice travels in the checkpoint, a resumed run does not search again and
ends with the uninterrupted run's maps, and a corrupt record is a one-line error. Imported by
tests/test_startsearch.py and tests/test_clear_candidate.py.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np


def assert_search_resumes(run: Callable[..., int], full: Path, out: Path, name: str, label: str, capfd) -> None:
    """``run(out, *flags, quiet=True)`` runs the test's tiny optimisation into ``out`` and returns its exit code;
    ``full``: the same run uninterrupted (3 iterations); ``name``: the search's key in ``summary.json`` and the
    checkpoint (``start_search``); ``label``: the line it prints when it searches (``start search``)."""
    chosen = json.loads((full / "summary.json").read_text())[name]
    capfd.readouterr()
    assert run(out, "--iterations", "2") == 0
    ck = dict(np.load(out / "checkpoint.npz"))
    assert json.loads(str(ck[f"{name}/info"]))["chosen"] == chosen["chosen"]
    capfd.readouterr()
    assert run(out, "--iterations", "3", "--resume", quiet=False) == 0
    assert f"{label}:" not in capfd.readouterr().err  # nothing was searched again
    again = json.loads((out / "summary.json").read_text())[name]
    assert again["chosen"] == chosen["chosen"] and again["scores"] == chosen["scores"]
    np.testing.assert_array_equal(np.load(out / "maps" / "roughness.npy"), np.load(full / "maps" / "roughness.npy"))
    ck[f"{name}/info"] = np.array("{not json")
    with open(out / "checkpoint.npz", "wb") as f:
        np.savez(f, **ck)
    capfd.readouterr()
    assert run(out, "--iterations", "4", "--resume") == 2
    err = capfd.readouterr().err.strip()
    assert f"bad {name}/info" in err and len(err.splitlines()) == 1
