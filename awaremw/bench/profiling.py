"""``--profile FILE`` for the benchmarks: cProfile around the measured run.

The statistics go to FILE in :mod:`pstats` format; read them with
``python -m pstats FILE`` (``sort cumulative``, ``stats 10``) or
:func:`top`.
"""

from __future__ import annotations

import cProfile
import io
import pstats
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def profiled(path: str | Path | None) -> Iterator[None]:
    """Profile the body into ``path`` (None: no profiling, no overhead)."""
    if path is None:
        yield
        return
    prof = cProfile.Profile()
    prof.enable()
    try:
        yield
    finally:
        prof.disable()
        prof.dump_stats(str(path))


def top(path: str | Path, sort: str = "cumulative", n: int = 10) -> str:
    """The ``n`` first lines of the profile in ``path`` sorted by ``sort``."""
    out = io.StringIO()
    pstats.Stats(str(path), stream=out).strip_dirs().sort_stats(sort).print_stats(n)
    return out.getvalue()
