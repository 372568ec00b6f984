"""The emulator's envelope around a radio frame on Zenoh.

A real radio carries only the frame; the emulator also needs to know where the
sender stood, how loud it transmitted, which link-layer sequence number and
attempt this is and when it went on the air, so that every receiving process
can decide distance, RSSI and loss on its own (and identically). None of this
counts toward the MTU or the energy model.

Wire format: one msgpack array, positional (cheap to pack and unpack)::

    [VERSION, kind, src, x, y, tx_power_dbm, seq, attempt, t, dest, frame]

``kind`` is FRAME (a data frame; ``dest`` is a node id or BROADCAST) or ACK
(the emulated CC2420 auto-ACK; ``dest`` is the original sender, ``seq`` the
acknowledged link sequence number and ``frame`` is empty). ``t`` is the
emulated time the transmission started.

:func:`decode_envelope` raises only :class:`MalformedEnvelope` (a remote
fault: garbage on a radio key), never anything else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import msgpack

from awaremw.protocol.frames import BROADCAST, MAX_NODE_ID

VERSION = 1


class Kind(IntEnum):
    FRAME = 0
    ACK = 1


class MalformedEnvelope(ValueError):
    """Bytes on a radio key that are not a valid envelope (a remote fault)."""


@dataclass(frozen=True, slots=True)
class Envelope:
    kind: Kind
    src: int
    x: float
    y: float
    tx_power: float  # dBm
    seq: int  # link-layer sequence number of the sender (16 bit, wraps)
    attempt: int  # 0 for the first transmission, 1.. for link-layer retries
    t: float  # emulated time the transmission started
    dest: int  # node id, or BROADCAST
    frame: bytes

    @property
    def is_ack(self) -> bool:
        return self.kind is Kind.ACK

    @property
    def is_unicast(self) -> bool:
        return self.dest != BROADCAST

    def encode(self) -> bytes:
        return encode_envelope(
            self.kind,
            self.src,
            self.x,
            self.y,
            self.tx_power,
            self.seq,
            self.attempt,
            self.t,
            self.dest,
            self.frame,
        )


_packb = msgpack.Packer(use_bin_type=True).pack


def encode_envelope(
    kind: Kind,
    src: int,
    x: float,
    y: float,
    tx_power: float,
    seq: int,
    attempt: int,
    t: float,
    dest: int,
    frame: bytes,
) -> bytes:
    """Pack an envelope without building the dataclass (the sender's hot path)."""
    out: bytes = _packb([VERSION, int(kind), src, x, y, tx_power, seq, attempt, t, dest, frame])
    return out


def _finite(v: object) -> bool:
    if isinstance(v, bool) or not isinstance(v, int | float):
        return False
    return math.isfinite(v)


def decode_envelope(data: bytes) -> Envelope:
    """Validate and unpack. Raises :class:`MalformedEnvelope` on any defect."""
    try:
        v = msgpack.unpackb(data, use_list=False, raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises several unrelated types on garbage
        raise MalformedEnvelope(f"not msgpack: {type(e).__name__}: {e}") from None
    if not isinstance(v, tuple) or len(v) != 11:
        raise MalformedEnvelope("not an 11-element envelope array")
    ver, kind, src, x, y, txp, seq, attempt, t, dest, frame = v
    if ver != VERSION:
        raise MalformedEnvelope(f"unknown envelope version {ver!r}")
    if kind not in (0, 1) or isinstance(kind, bool):
        raise MalformedEnvelope(f"unknown envelope kind {kind!r}")
    if not isinstance(src, int) or isinstance(src, bool) or not 0 <= src <= MAX_NODE_ID:
        raise MalformedEnvelope(f"bad sender id {src!r}")
    if not isinstance(dest, int) or isinstance(dest, bool):
        raise MalformedEnvelope(f"bad destination {dest!r}")
    if dest != BROADCAST and not 0 <= dest <= MAX_NODE_ID:
        raise MalformedEnvelope(f"bad destination {dest!r}")
    if not (_finite(x) and _finite(y) and _finite(txp) and _finite(t)):
        raise MalformedEnvelope("position, power or time is not a finite number")
    if not isinstance(seq, int) or isinstance(seq, bool) or not 0 <= seq <= 0xFFFF:
        raise MalformedEnvelope(f"bad link sequence number {seq!r}")
    if not isinstance(attempt, int) or isinstance(attempt, bool) or not 0 <= attempt <= 255:
        raise MalformedEnvelope(f"bad attempt number {attempt!r}")
    if not isinstance(frame, bytes):
        raise MalformedEnvelope("frame is not bytes")
    if kind == Kind.ACK and (dest == BROADCAST or frame):
        raise MalformedEnvelope("an ACK must be addressed to one node and carry no frame")
    return Envelope(
        Kind(kind), src, float(x), float(y), float(txp), seq, attempt, float(t), dest, frame
    )
