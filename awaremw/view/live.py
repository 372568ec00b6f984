"""Views of a running emulation: a rich live map refreshed in place, or plain
log lines (``--plain``, for scripts and CI).

Both take :class:`~awaremw.view.snapshot.Snapshot` updates and free-form log
lines; :func:`describe` turns middleware events into such lines.
"""

from __future__ import annotations

import sys
from collections import deque
from typing import Protocol, TextIO, assert_never

from rich.console import Console, Group
from rich.live import Live
from rich.text import Text

from awaremw.protocol import events as ev
from awaremw.protocol.events import MoteDown, MoteEvent, MoteUp
from awaremw.view.render import render
from awaremw.view.snapshot import RecordLine, Snapshot


class View(Protocol):
    def start(self) -> None: ...

    def update(self, snap: Snapshot) -> None: ...

    def log(self, t: float, line: str) -> None: ...

    def stop(self) -> None: ...


def describe(node: int, event: MoteEvent, t: float) -> str | None:
    """A one-line description of a notable middleware event (None: not notable)."""
    match event:
        case ev.LeaderElected():
            return (
                f"mote {event.node} leads group {event.group_id} (type {event.group_type}, "
                f"{event.cause.value})"
            )
        case ev.GroupJoined():
            return f"mote {event.node} joined group {event.group_id} (type {event.group_type})"
        case ev.GroupLeft():
            return (
                f"mote {event.node} left group {event.group_id} (type {event.group_type}, "
                f"{event.reason.value})"
            )
        case ev.HandoverSent():
            return f"mote {event.node} handed group {event.group_id} over to mote {event.to}"
        case ev.LeaderYielded():
            return (
                f"mote {event.node} yielded group {event.group_id} to heavier group "
                f"{event.successor}"
            )
        case MoteDown(reason="stopped"):
            return None  # the run ended: not news
        case MoteDown(reason=reason):
            return f"mote {node} is down ({reason})"
        case (
            MoteUp() | ev.MalformedFrame() | ev.ItemAdopted() | ev.ItemRefused()
            | ev.InjectSuperseded() | ev.Delivered() | ev.ParentChanged() | ev.DataDropped()
            | ev.GroupTypeRefused() | ev.RecordProduced() | ev.ChannelRefused()
            | ev.CommandExecuted() | ev.NeighbourFound() | ev.NeighbourLost() | ev.PingResult()
        ):  # fmt: skip
            return None
        case _:
            assert_never(event)


def record_line(r: RecordLine) -> str:
    return (
        f"data ch {r.channel} group {r.group_type}/{r.group_id}: {r.agg} = {r.value:.2f}"
        f"{' ' + r.unit if r.unit else ''} over {r.count} reading(s) (leader {r.leader})"
    )


class LiveView:
    """A rich Live display: the map and tables, with the latest log lines below."""

    def __init__(
        self, console: Console | None = None, refresh_per_second: float = 4.0, lines: int = 6
    ) -> None:
        self.console = console or Console()
        self._lines: deque[str] = deque(maxlen=lines)
        self._snap: Snapshot | None = None
        self._live = Live(
            Text("starting..."),
            console=self.console,
            refresh_per_second=refresh_per_second,
            transient=False,
        )

    def start(self) -> None:
        self._live.start()

    def _renderable(self) -> Group:
        parts: list[object] = []
        if self._snap is not None:
            w = max(30, min(80, self.console.width - 48))
            parts.append(render(self._snap, width=w))
        parts.append(Text("\n".join(self._lines), style="grey70"))
        return Group(*parts)  # type: ignore[arg-type]

    def update(self, snap: Snapshot) -> None:
        self._snap = snap
        self._live.update(self._renderable())

    def log(self, t: float, line: str) -> None:
        self._lines.append(f"[{t:7.1f}] {line}")
        self._live.update(self._renderable())

    def stop(self) -> None:
        self._live.stop()


class PlainLog:
    """Plain text lines: every log line, and a status line every ``every`` s of
    emulated time."""

    def __init__(self, out: TextIO | None = None, every: float = 10.0) -> None:
        self.out = out or sys.stdout
        self.every = every
        self._next = 0.0

    def start(self) -> None:
        pass

    def update(self, snap: Snapshot) -> None:
        if snap.t + 1e-9 < self._next:
            return
        self._next = snap.t + self.every
        groups = ", ".join(
            f"{g.group_type}/{g.group_id}:{g.members}"
            + ("" if g.leader is None else f"@{g.leader}")
            for g in snap.groups
        )
        stats = " ".join(
            f"{k}={v:.1f}" if isinstance(v, float) else f"{k}={v}" for k, v in snap.stats.items()
        )
        self._print(snap.t, f"status groups [{groups or 'none'}] {stats}")

    def log(self, t: float, line: str) -> None:
        self._print(t, line)

    def _print(self, t: float, line: str) -> None:
        print(f"[{t:7.1f}] {line}", file=self.out, flush=True)

    def stop(self) -> None:
        pass
