"""Seeded runs decide today what they decided when their trace was written.

Each case is a whole-middleware run on the virtual clock (the aware workload of
``bench virtual``, and the shipped experiments with their own deployment); its
every core event and every mote's radio counters are held against the trace
in ``tests/golden/``. A refactor (issue 31: the groups package) must leave them
as they are; a change of behaviour rewrites them on purpose:

    python tests/test_golden_traces.py          # rewrite every golden trace

and says in its commit why the decisions changed.
"""

from __future__ import annotations

import gzip
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from traces import aware_trace, experiment_trace

GOLDEN = Path(__file__).resolve().parent / "golden"

CASES: dict[str, Callable[[], list[str]]] = {
    "aware-600-seed3": lambda: aware_trace(600, 3, 60.0),
    "romeo4r-seed2": lambda: experiment_trace("romeo4r", 2),
    "romeo4r-seed4": lambda: experiment_trace("romeo4r", 4),
    "fire-seed1": lambda: experiment_trace("fire", 1),
    "fire-seed7": lambda: experiment_trace("fire", 7),
    "failover-seed1": lambda: experiment_trace("failover", 1),
}


def _path(case: str) -> Path:
    return GOLDEN / f"{case}.txt.gz"


def _write(case: str) -> None:
    lines = CASES[case]()
    _path(case).write_bytes(gzip.compress(("\n".join(lines) + "\n").encode(), mtime=0))


@pytest.mark.pure_python
@pytest.mark.parametrize("case", sorted(CASES))
def test_a_seeded_run_decides_what_its_golden_trace_says(case: str) -> None:
    want = gzip.decompress(_path(case).read_bytes()).decode().splitlines()
    got = CASES[case]()
    assert any("|" in line for line in got)
    for i, (w, g) in enumerate(zip(want, got, strict=False)):
        assert g == w, f"{case}: line {i + 1} differs from the golden trace"
    assert len(got) == len(want), f"{case}: {len(got)} lines, the golden trace has {len(want)}"


if __name__ == "__main__":
    GOLDEN.mkdir(exist_ok=True)
    for name in sys.argv[1:] or sorted(CASES):
        _write(name)
        print(f"wrote {_path(name)}")
