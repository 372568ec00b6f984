"""A live sniffer of the emulated radio over Zenoh (``awaremw sniff``).

It subscribes to the radio's key expressions (``<prefix>/radio/**``) as a mote
would, with one Zenoh FIFO channel drained from the event loop (no Python on
Zenoh's threads), validates each envelope (:func:`decode_envelope`: garbage
is counted, never fatal) and writes what was on the air to a
:class:`~awaremw.radio.capture.Capture`: data frames with their 802.15.4
header, the emulated auto-ACKs as 802.15.4 ACK frames. Timestamps are the wall
time the sniffer got the envelope; the sender's emulated time is in the comment.

With the network key (``--secrets``) it checks each frame's MIC and writes the
payload without counter and MIC, noting ``mic=ok counter=N`` (or
``mic=bad``, the frame written as it was on the air).

Unlike ``--pcap`` on a fleet, a sniffer sees only what goes through Zenoh: every
broadcast and every unicast between processes, but neither the unicasts between
motes of one process nor any reception outcome (docs/capture.md).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass
from typing import Any

import zenoh

from awaremw.radio.capture import Capture
from awaremw.radio.envelope import (
    DEFAULT_LIMITS,
    EnvelopeLimits,
    Kind,
    MalformedEnvelope,
    decode_envelope,
)
from awaremw.radio.faults import FaultLog
from awaremw.radio.security import FrameGuard, RadioSecurity

log = logging.getLogger(__name__)

CHANNEL_CAPACITY = 1 << 14  # envelopes Zenoh holds for us between two polls (then it drops)
POLL_S = 0.005  # wall seconds between polls


@dataclass(slots=True)
class SniffStats:
    envelopes: int = 0
    frames: int = 0
    acks: int = 0
    malformed: int = 0
    mic_ok: int = 0
    mic_bad: int = 0


class Sniffer:
    """Subscribe on ``session`` and write to ``capture``; :meth:`start` in the loop,
    :meth:`close` when done (flushes and closes the capture)."""

    def __init__(
        self,
        session: zenoh.Session,
        capture: Capture,
        *,
        prefix: str = "aware",
        security: RadioSecurity | None = None,
        limits: EnvelopeLimits = DEFAULT_LIMITS,
    ) -> None:
        if "*" in prefix or prefix.endswith("/") or not prefix:
            raise ValueError(f"bad key prefix {prefix!r}")
        self.session = session
        self.capture = capture
        self.key = f"{prefix}/radio/**"
        self.guard = None if security is None else FrameGuard(security)
        self.limits = limits
        self.stats = SniffStats()
        self.rejected = FaultLog("malformed envelope", log, logging.INFO)
        self._sub: zenoh.Subscriber[Any] | None = None
        self._poll: asyncio.TimerHandle | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._sub = self.session.declare_subscriber(
            self.key, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY)
        )
        self._poll = self._loop.call_later(POLL_S, self._drain)

    def _drain(self) -> None:
        sub = self._sub
        if sub is None or self._loop is None:
            return
        while True:
            try:
                s = sub.try_recv()
            except zenoh.ZError as e:  # the channel closed under us
                self.rejected.count("zenoh channel", str(e))
                break
            if s is None:
                break
            self.handle(s.payload.to_bytes(), time.time())
        self.capture.flush_if_due()
        self._poll = self._loop.call_later(POLL_S, self._drain)

    def handle(self, data: bytes, wall: float) -> None:
        """One envelope off Zenoh, received at wall time ``wall``."""
        st = self.stats
        st.envelopes += 1
        try:
            env = decode_envelope(data, self.limits)
        except MalformedEnvelope as e:
            st.malformed += 1
            self.rejected.count(e.reason, str(e))
            return
        if env.kind is Kind.ACK:
            st.acks += 1
            self.capture.ack(wall, env.src, env.dest, env.seq, f"emulated_t={env.t:.6f}")
            return
        st.frames += 1
        frame = env.frame
        note = f"emulated_t={env.t:.6f}"
        g = self.guard
        if g is not None:
            op = g.open(env.src, env.dest, env.seq, frame)
            if op.payload is None:
                st.mic_bad += 1
                note += f" mic=bad ({op.reason})"
            else:
                st.mic_ok += 1
                note += f" mic=ok counter={op.counter}"
                frame = op.payload
        self.capture.on_air(wall, env.src, env.dest, env.seq, env.attempt, frame, note=note)

    def close(self) -> None:
        """Stop listening, then flush and close the capture (idempotent)."""
        if self._poll is not None:
            self._poll.cancel()
            self._poll = None
        if self._sub is not None:
            sub, self._sub = self._sub, None
            # What arrived before the undeclare is still written.
            with contextlib.suppress(zenoh.ZError):
                while (s := sub.try_recv()) is not None:
                    self.handle(s.payload.to_bytes(), time.time())
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()  # type: ignore[no-untyped-call]
        self.capture.close()
