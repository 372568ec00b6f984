"""Supervision of a launcher's worker processes: real subprocesses (not
multiprocessing's spawn, which re-imports the parent's ``__main__``), each
talking to the parent over one end of a socket pair; their messages gathered
into one queue on the parent's loop; joined (or terminated) on close."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing.connection
import socket
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from awaremw.protocol.core import MoteCore
from awaremw.runtime.deployment import Deployment, NodeSpec
from awaremw.runtime.fleet_settings import FleetSettings, WorkerPlugin
from awaremw.runtime.partition import IdModulo, XStripe

log = logging.getLogger(__name__)

WORKER_CMD = "from awaremw.runtime.fleet import worker_entry; worker_entry()"
MAX_PENDING = 4096  # other messages from workers not yet taken (progress is folded in)
_ESSENTIAL = frozenset({"ready", "result", "gone"})  # at most one each per worker


class LaunchError(RuntimeError):
    """A worker process failed to start, to set up or to run."""


@dataclass(frozen=True)
class WorkerParams:
    """Everything a worker process needs (pickled to it)."""

    deployment: Deployment
    core_factory: Callable[[NodeSpec, Deployment], MoteCore]
    settings: FleetSettings
    stripe: XStripe | IdModulo
    exclude_kinds: frozenset[str] = frozenset()
    progress_s: float | None = None
    plugin: WorkerPlugin | None = None

    @property
    def name(self) -> str:
        return self.settings.name


@dataclass
class WorkerResult:
    """What a worker sends back when it stops."""

    name: str
    motes: int
    counters: dict[int, dict[str, int]]
    stats: dict[str, int]
    lag_ms: list[float]
    cpu_s: float
    wall_s: float
    error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def lost(name: str) -> WorkerResult:
    return WorkerResult(name, 0, {}, {}, [], 0.0, 0.0, error="no result (process lost)")


Message = tuple[int, str, Any]  # (worker index, kind, argument)


class WorkerPool:
    """The worker processes of one launcher and the messages they send.

    ``on_message(k, kind, arg)`` sees every message first (on the loop); it
    returns True when it consumed it (progress), else it is queued for
    :meth:`next`. A worker whose pipe closes yields ``(k, "gone", None)``.
    """

    def __init__(self, on_message: Callable[[int, str, Any], bool] | None = None) -> None:
        self.procs: list[subprocess.Popen[bytes]] = []
        self._conns: list[multiprocessing.connection.Connection] = []
        self._msgs: asyncio.Queue[Message] = asyncio.Queue()
        self._others = 0  # queued messages not in _ESSENTIAL: bounded by MAX_PENDING
        self._on_message = on_message

    def __len__(self) -> int:
        return len(self.procs)

    def spawn(self, params: WorkerParams) -> int:
        """Start one worker process and send it ``params``; its index."""
        k = len(self.procs)
        psock, csock = socket.socketpair()
        proc = subprocess.Popen(
            [sys.executable, "-c", WORKER_CMD, str(csock.fileno())],
            pass_fds=(csock.fileno(),),
        )
        csock.close()
        conn = multiprocessing.connection.Connection(psock.detach())
        self.procs.append(proc)
        self._conns.append(conn)
        conn.send(params)
        asyncio.get_running_loop().add_reader(conn.fileno(), self._readable, k)
        return k

    def send_all(self, kind: str, arg: object = None) -> None:
        """Send ``(kind, arg)`` to every worker still listening."""
        for c in self._conns:
            with contextlib.suppress(OSError):
                c.send((kind, arg))

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

    def _readable(self, k: int) -> None:
        conn = self._conns[k]
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
