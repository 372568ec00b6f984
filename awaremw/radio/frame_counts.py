"""Frames counted by kind and fate, for the metrics (docs/monitoring.md).

:class:`FrameCounts` is a :class:`~awaremw.radio.capture.RadioTap`: a medium
tells it every frame put on the air and every reception, and it counts frames
sent by this process's motes by kind (``ctp_data``, ``drip_item``, ...) and, per
kind, the frames its motes received or lost, by cause (:data:`CAUSES`). A
fleet installs it only when it serves metrics: without it the medium pays
nothing. :class:`Taps` hands one medium's calls to several taps (the metrics
and a pcapng capture).
"""

from __future__ import annotations

import re
from collections.abc import Container, Iterable

from awaremw.protocol.frames import FRAME_TYPES
from awaremw.radio.capture import CAUSES, RadioTap


def _snake(name: str) -> str:
    return re.sub(r"(?<=[a-z])(?=[A-Z])", "_", name).lower()


# Type byte -> kind name; the frames' own classes name them (CtpData -> ctp_data).
KINDS: dict[int, str] = {t: _snake(cls.__name__) for t, cls in FRAME_TYPES.items()}
OTHER = "other"  # not one of ours (a fuzzer's, a foreign mote's)
FATES = ("received", *CAUSES)


def frame_kind(frame: bytes) -> str:
    """The kind of a frame as it goes on the air: a msgpack array whose first
    element is the type (sealed frames keep the payload in clear, MIC after)."""
    if len(frame) >= 2 and 0x90 <= frame[0] <= 0x9F:
        return KINDS.get(frame[1], OTHER)
    return OTHER


class FrameCounts:
    """Counts for the motes ``local`` (their frames sent; the medium reports
    receptions at its own motes only): a live container, motes come and go."""

    def __init__(self, local: Container[int]) -> None:
        self.local = local
        self.sent: dict[str, int] = {}  # kind -> frames (attempts, retries included)
        self.fates: dict[tuple[str, str], int] = {}  # (kind, fate) -> receptions
        self._last: dict[int, str] = {}  # sender -> kind of its last frame (bound: node ids)

    def on_air(self, t: float, src: int, dest: int, seq: int, attempt: int, frame: bytes) -> None:
        kind = frame_kind(frame)
        self._last[src] = kind
        if src in self.local:  # a remote sender's frame is counted by its own process
            self.sent[kind] = self.sent.get(kind, 0) + 1

    def reception(
        self, t: float, src: int, dst: int, rssi: float | None, cause: str | None
    ) -> None:
        key = (self._last.get(src, OTHER), "received" if cause is None else cause)
        self.fates[key] = self.fates.get(key, 0) + 1

    def as_rows(self) -> tuple[tuple[str, str, int], ...]:
        """``(kind, fate, count)`` rows, fate ``sent`` for the frames sent (picklable)."""
        rows = [(k, "sent", n) for k, n in self.sent.items()]
        rows += [(k, fate, n) for (k, fate), n in self.fates.items()]
        return tuple(sorted(rows))


class Taps:
    """Several taps on one medium."""

    def __init__(self, taps: Iterable[RadioTap]) -> None:
        self.taps = tuple(taps)

    def on_air(self, t: float, src: int, dest: int, seq: int, attempt: int, frame: bytes) -> None:
        for tap in self.taps:
            tap.on_air(t, src, dest, seq, attempt, frame)

    def reception(
        self, t: float, src: int, dst: int, rssi: float | None, cause: str | None
    ) -> None:
        for tap in self.taps:
            tap.reception(t, src, dst, rssi, cause)


def with_tap(current: RadioTap | None, tap: RadioTap) -> RadioTap:
    """What a medium's ``tap`` becomes when ``tap`` joins the one it has."""
    return tap if current is None else Taps((current, tap))
