"""Supervision of a launcher's worker processes: real subprocesses (not
multiprocessing's spawn, which re-imports the parent's ``__main__``), each
talking to the parent over one end of a socket pair; their messages gathered
into one queue on the parent's loop; a dead one started again in its place
(:meth:`WorkerPool.respawn`); joined (or terminated) on close."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import multiprocessing.connection
import socket
import subprocess
import sys
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

from awaremw.protocol.core import MoteCore
from awaremw.runtime.deployment import Deployment, NodeSpec
from awaremw.runtime.fleet.settings import FleetSettings
from awaremw.runtime.fleet.stats import WorkerResult, lost
from awaremw.runtime.partition import IdModulo, XStripe

log = logging.getLogger(__name__)

WORKER_CMD = "from awaremw.runtime.fleet.worker import main; main()"
MAX_PENDING = 4096  # other messages from workers not yet taken (progress is folded in)
_ESSENTIAL = frozenset({"ready", "result", "gone"})  # at most one each per worker


class LaunchError(RuntimeError):
    """A worker process failed to start, to set up or to run."""


@dataclass(frozen=True)
class Resume:
    """What a restarted worker carries over from the incarnations before it.

    ``restarts``: how many times this worker was started again. ``frame_counters``:
    the radio security frame counter each of its motes goes on from (the last one
    it reported, plus a margin for the frames it may have sent since), so that
    neighbours do not refuse a restarted mote's frames as replays -- a real mote
    keeps that counter in flash across a power cycle. ``base``: the counter
    totals of the dead incarnations (frames, unicasts), added to the new one's
    snapshots so that the fleet's figures go on from where they were.
    """

    restarts: int = 0
    frame_counters: dict[int, int] = field(default_factory=dict)
    base: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class WorkerParams:
    """Everything a worker process needs (pickled to it)."""

    deployment: Deployment
    core_factory: Callable[[NodeSpec, Deployment], MoteCore]
    settings: FleetSettings
    stripe: XStripe | IdModulo
    exclude_kinds: frozenset[str] = frozenset()
    progress_s: float | None = None
    resume: Resume = field(default_factory=Resume)

    @property
    def name(self) -> str:
        return self.settings.name


Message = tuple[int, str, Any]  # (worker index, kind, argument)

# A bound on the frames one mote can put on the air in an emulated second: the
# smallest frame with its ACK and CSMA backoff takes more than 0.5 ms at 250 kb/s.
MAX_FRAMES_PER_S = 2_000


def resume_counters(reported: dict[int, int], since_s: float) -> dict[int, int]:
    """The frame counters a restarted worker's motes go on from: the last ones
    reported, ``since_s`` emulated seconds before the worker died, plus the most
    frames a mote could have sent since (a gap in the counters is harmless, a
    reused counter would be refused as a replay)."""
    margin = math.ceil((max(since_s, 0.0) + 1.0) * MAX_FRAMES_PER_S)
    return {node: c + margin for node, c in reported.items() if c > 0}


class RestartBudget:
    """At most ``limit`` restarts of one worker within ``window_s`` wall seconds:
    a worker that keeps dying at once (a bug in its setup) is not started forever.
    ``limit`` 0: never restart."""

    def __init__(self, limit: int, window_s: float) -> None:
        self.limit = limit
        self.window_s = window_s
        self._times: dict[int, deque[float]] = {}  # bounded: ``limit`` per worker

    @property
    def enabled(self) -> bool:
        return self.limit > 0

    def allow(self, k: int, now: float) -> bool:
        """Whether worker ``k`` may be restarted at ``now`` (and count it if so)."""
        times = self._times.setdefault(k, deque())
        while times and now - times[0] > self.window_s:
            times.popleft()
        if len(times) >= self.limit:
            return False
        times.append(now)
        return True


class WorkerPool:
    """The worker processes of one launcher and the messages they send.

    ``on_message(k, kind, arg)`` sees every message first (on the loop); it
    returns True when it consumed it (progress), else it is queued for
    :meth:`next`. A worker whose pipe closes yields ``(k, "gone", None)``.
    """

    def __init__(self, on_message: Callable[[int, str, Any], bool] | None = None) -> None:
        self.procs: list[subprocess.Popen[bytes]] = []
        self.params: list[WorkerParams] = []  # what each worker was last started with
        self._conns: list[multiprocessing.connection.Connection] = []
        self._msgs: asyncio.Queue[Message] = asyncio.Queue()
        self._others = 0  # queued messages not in _ESSENTIAL: bounded by MAX_PENDING
        self._on_message = on_message

    def __len__(self) -> int:
        return len(self.procs)

    def spawn(self, params: WorkerParams) -> int:
        """Start one worker process and send it ``params``; its index."""
        k = len(self.procs)
        proc, conn = self._start(k, params)
        self.procs.append(proc)
        self.params.append(params)
        self._conns.append(conn)
        return k

    def respawn(self, k: int, resume: Resume) -> subprocess.Popen[bytes]:
        """Start worker ``k`` again (after it died) with its parameters and ``resume``;
        its messages keep the index ``k``. The old process is reaped (or killed, if
        it is somehow still there) so that no zombie is left."""
        old, conn = self.procs[k], self._conns[k]
        with contextlib.suppress(OSError, ValueError):
            asyncio.get_running_loop().remove_reader(conn.fileno())
        conn.close()
        if old.poll() is None:
            old.kill()
            old.wait()
        params = replace(self.params[k], resume=resume)
        proc, conn = self._start(k, params)
        self.procs[k], self._conns[k], self.params[k] = proc, conn, params
        return proc

    def _start(
        self, k: int, params: WorkerParams
    ) -> tuple[subprocess.Popen[bytes], multiprocessing.connection.Connection]:
        psock, csock = socket.socketpair()
        proc = subprocess.Popen(
            [sys.executable, "-c", WORKER_CMD, str(csock.fileno())],
            pass_fds=(csock.fileno(),),
        )
        csock.close()
        conn = multiprocessing.connection.Connection(psock.detach())
        conn.send(params)
        asyncio.get_running_loop().add_reader(conn.fileno(), self._readable, k, conn)
        return proc, conn

    def send(self, k: int, kind: str, arg: object = None) -> None:
        """Send ``(kind, arg)`` to worker ``k`` if it still listens."""
        with contextlib.suppress(OSError):
            self._conns[k].send((kind, arg))

    def send_all(self, kind: str, arg: object = None) -> None:
        """Send ``(kind, arg)`` to every worker still listening."""
        for k in range(len(self._conns)):
            self.send(k, kind, arg)

    async def next(self, timeout: float) -> Message:
        """The next queued message; TimeoutError after ``timeout`` wall seconds."""
        msg = await asyncio.wait_for(self._msgs.get(), timeout)
        if msg[1] not in _ESSENTIAL:
            self._others -= 1
        return msg

    async def results(self, previous: list[WorkerResult], timeout: float) -> list[WorkerResult]:
        """Every worker's result (after ``stop``), one per worker in order;
        :func:`lost` stands in for a worker that went away without one."""
        loop = asyncio.get_running_loop()
        got: dict[str, WorkerResult] = {r.name: r for r in previous}
        deadline = loop.time() + timeout
        while len(got) < len(self.procs) and loop.time() < deadline:
            try:
                k, kind, arg = await self.next(deadline - loop.time())
            except TimeoutError:
                break
            if kind == "result":
                got[arg.name] = arg
            elif kind == "gone":
                got.setdefault(f"w{k}", lost(f"w{k}"))
        return [got.get(f"w{k}") or lost(f"w{k}") for k in range(len(self.procs))]

    async def close(self) -> None:
        """Close the pipes and join the processes (terminate, then kill, a hung one)."""
        loop = asyncio.get_running_loop()
        for c in self._conns:
            with contextlib.suppress(OSError, ValueError):
                loop.remove_reader(c.fileno())
            c.close()
        for k, p in enumerate(self.procs):
            try:
                await asyncio.to_thread(p.wait, 10.0)
            except subprocess.TimeoutExpired:
                log.warning("worker w%d did not stop; terminating it", k)
                p.terminate()
                try:
                    await asyncio.to_thread(p.wait, 5.0)
                except subprocess.TimeoutExpired:
                    p.kill()
                    await asyncio.to_thread(p.wait)

    def _readable(self, k: int, conn: multiprocessing.connection.Connection) -> None:
        try:
            kind, arg = conn.recv()
        except (EOFError, OSError):
            asyncio.get_running_loop().remove_reader(conn.fileno())
            self._put((k, "gone", None))
            return
        if self._on_message is not None and self._on_message(k, kind, arg):
            return
        self._put((k, kind, arg))

    def _put(self, msg: Message) -> None:
        if msg[1] not in _ESSENTIAL:
            if self._others >= MAX_PENDING:  # nobody reads them: drop, say so
                log.warning("worker w%d: message %r dropped (queue full)", msg[0], msg[1])
                return
            self._others += 1
        self._msgs.put_nowait(msg)
