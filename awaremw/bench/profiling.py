"""``--profile FILE`` for the benchmarks: cProfile around the measured run.

The statistics go to FILE in :mod:`pstats` format; read them with
``python -m pstats FILE`` (``sort cumulative``, ``stats 10``) or
:func:`top`. A profile sees only the interpreted functions: in the compiled
build (setup.py) the compiled modules' time is charged to their Python caller.
:func:`build_facts` says which build a run measured.
"""

from __future__ import annotations

import cProfile
import io
import pstats
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from awaremw import compiled_modules


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


def build_facts() -> dict[str, Any]:
    """Which build ran: ``build`` is ``"mypyc"`` when this installation runs the
    hot modules compiled (setup.py), else ``"python"``; ``compiled_modules`` counts them."""
    n = len(compiled_modules())
    return {"build": "mypyc" if n else "python", "compiled_modules": n}
