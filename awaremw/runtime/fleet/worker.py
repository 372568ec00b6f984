"""A launcher's worker process: ``python -c "from awaremw.runtime.fleet.worker
import main; main()" FD``, one :class:`~awaremw.runtime.fleet.local.Fleet` on
the stripe the launcher gave it.

Real processes started with ``subprocess`` (not multiprocessing's spawn, which
re-imports the parent's ``__main__``): the launcher passes one end of a socket
pair as FD and sends the pickled :class:`WorkerParams` over it. The worker sets
up, reports ready, starts at the shared start time it is sent, and answers
``freeze`` and ``stop``; its :class:`WorkerResult` is its last message.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import multiprocessing.connection
import os
import sys
from typing import Any

from awaremw.runtime import logs
from awaremw.runtime.fleet.local import Fleet
from awaremw.runtime.fleet.pool import Resume, WorkerParams
from awaremw.runtime.fleet.stats import WorkerResult, lost
from awaremw.runtime.partition import WorkerFilter

log = logging.getLogger(__name__)

COUNTERS_EVERY_S = 1.0  # a secured worker without progress reports its frame counters this often
Conn = multiprocessing.connection.Connection


def main() -> None:
    """The entry point of a worker process (see the module)."""
    conn = Conn(int(sys.argv[1]))
    params = conn.recv()
    if not isinstance(params, WorkerParams):
        raise SystemExit("awaremw worker: bad parameters from the launcher")
    if os.environ.get(logs.ENV) == "json":  # as the launcher's process logs
        logs.use_json_logs(f"awaremw worker {params.name}", logging.WARNING)
    else:
        logging.basicConfig(level=logging.WARNING, format=f"%(asctime)s {params.name} %(message)s")
    try:
        asyncio.run(_worker(params, conn))
    except KeyboardInterrupt:
        pass
    finally:
        conn.close()


async def _worker(p: WorkerParams, conn: Conn) -> None:
    loop = asyncio.get_running_loop()
    inbox: asyncio.Queue[tuple[str, Any]] = asyncio.Queue()

    def readable() -> None:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            loop.remove_reader(conn.fileno())
            inbox.put_nowait(("stop", None))  # the parent is gone
            return
        inbox.put_nowait(msg)

    loop.add_reader(conn.fileno(), readable)
    fleet = Fleet(
        p.deployment,
        p.core_factory,
        p.settings,
        node_filter=WorkerFilter(p.stripe, p.exclude_kinds),
    )
    error: str | None = None
    progress: asyncio.Task[None] | None = None
    try:
        async with fleet:  # settings.autostart is off: set up, not started
            _resume(fleet, p.resume)
            conn.send(("ready", len(fleet.runners)))
            while True:
                kind, arg = await inbox.get()
                match kind:
                    case "start":
                        fleet.start(float(arg))
                        secured = fleet.medium.guard is not None
                        if p.progress_s or secured:
                            every = p.progress_s or COUNTERS_EVERY_S
                            progress = asyncio.create_task(
                                _report(fleet, conn, every, bool(p.progress_s), secured)
                            )
                    case "freeze":
                        fleet.medium.freeze()
                        conn.send(("frozen", fleet.now()))
                    case "stop":
                        break
                fleet.raise_errors()
    except Exception as e:  # reported to the parent, which fails the run
        log.exception("worker %s failed", p.name)
        error = f"{type(e).__name__}: {e}"
    finally:
        if progress is not None:
            progress.cancel()
        with contextlib.suppress(OSError):
            loop.remove_reader(conn.fileno())
    result: WorkerResult = fleet.results[0] if fleet.results else lost(p.name)
    result = dataclasses.replace(result, error=error or result.error)
    with contextlib.suppress(OSError, BrokenPipeError):
        conn.send(("result", result))


def _resume(fleet: Fleet, r: Resume) -> None:
    """A restarted worker goes on from its dead incarnations (see :class:`Resume`)."""
    fleet.control.restarts = r.restarts
    fleet.stats.base = dict(r.base)
    guard = fleet.medium.guard
    if guard is not None:
        for node, counter in r.frame_counters.items():
            guard.resume(node, counter)


async def _report(fleet: Fleet, conn: Conn, every: float, progress: bool, counters: bool) -> None:
    """Every ``every`` wall seconds: a progress snapshot, and the motes' frame
    counters on a secured radio (what a restart goes on from)."""
    guard = fleet.medium.guard
    while True:
        await asyncio.sleep(every)
        with contextlib.suppress(OSError, BrokenPipeError):
            if progress:
                conn.send(("progress", fleet.stats.snapshot()))
            if counters and guard is not None:
                ids = list(fleet.runners)
                conn.send(("counters", (fleet.now(), {i: guard.counter_of(i) for i in ids})))
