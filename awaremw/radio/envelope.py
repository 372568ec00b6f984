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
fault: garbage on a radio key), never anything else. Every field is
range-checked against :class:`EnvelopeLimits` (built from the radio preset by
:meth:`EnvelopeLimits.of`), the envelope's size before it is unpacked; each
refusal names a ``reason`` tag (one of :data:`REASONS`) under which the medium
counts it. The table of tags and bounds: docs/runtime.md, "The envelope".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import msgpack

from awaremw.protocol.frames import BROADCAST, MAX_NODE_ID
from awaremw.radio.model import RadioPreset

VERSION = 1


class Kind(IntEnum):
    FRAME = 0
    ACK = 1


# Sane bounds for the emulator's fields (remote input; see docs/radio.md).
MAX_COORD_M = 1.0e6  # 1000 km from the origin: far beyond any deployment area
MAX_TIME_S = 1.0e10  # about 317 years of emulated time
ENVELOPE_OVERHEAD = 64  # bytes of an envelope around its frame, with room to spare

REASONS = (
    "size", "msgpack", "shape", "version", "kind", "src", "dest", "position",
    "tx_power", "seq", "attempt", "time", "frame", "ack",
)  # fmt: skip


class MalformedEnvelope(ValueError):
    """Bytes on a radio key that are not a valid envelope (a remote fault).

    ``reason`` is a short tag (one of :data:`REASONS`) for counting."""

    def __init__(self, message: str, reason: str = "shape") -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True, slots=True)
class EnvelopeLimits:
    """What a valid envelope may carry (from the radio preset)."""

    min_tx_power: float = -math.inf
    max_tx_power: float = math.inf
    mtu: int = 0xFFFF
    max_attempt: int = 255
    max_coord_m: float = MAX_COORD_M
    max_time_s: float = MAX_TIME_S

    @property
    def max_bytes(self) -> int:
        return self.mtu + ENVELOPE_OVERHEAD

    @classmethod
    def of(cls, preset: RadioPreset) -> EnvelopeLimits:
        return cls(preset.min_tx_power_dbm, preset.max_tx_power_dbm, preset.mtu, preset.max_retries)


# Without a preset only the widths and sanity bounds apply (power must still be
# a plausible radio's: within +-100 dBm, so that no range computation overflows).
DEFAULT_LIMITS = EnvelopeLimits(-100.0, 100.0)


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


def _int_in(v: object, lo: int, hi: int) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi


def decode_envelope(data: bytes, limits: EnvelopeLimits = DEFAULT_LIMITS) -> Envelope:
    """Validate and unpack. Raises :class:`MalformedEnvelope` on any defect."""
    if len(data) > limits.max_bytes:
        raise MalformedEnvelope(f"{len(data)} bytes > {limits.max_bytes}", "size")
    try:
        v = msgpack.unpackb(data, use_list=False, raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises several unrelated types on garbage
        raise MalformedEnvelope(f"not msgpack: {type(e).__name__}: {e}", "msgpack") from None
    if not isinstance(v, tuple) or len(v) != 11:
        raise MalformedEnvelope("not an 11-element envelope array", "shape")
    ver, kind, src, x, y, txp, seq, attempt, t, dest, frame = v
    if not _int_in(ver, VERSION, VERSION):
        raise MalformedEnvelope(f"unknown envelope version {_short(ver)}", "version")
    if not _int_in(kind, 0, 1):
        raise MalformedEnvelope(f"unknown envelope kind {_short(kind)}", "kind")
    if not _int_in(src, 0, MAX_NODE_ID):
        raise MalformedEnvelope(f"bad sender id {_short(src)}", "src")
    if not (_int_in(dest, 0, MAX_NODE_ID) or _int_in(dest, BROADCAST, BROADCAST)):
        raise MalformedEnvelope(f"bad destination {_short(dest)}", "dest")
    lim = limits.max_coord_m
    if not (_finite(x) and _finite(y) and -lim <= x <= lim and -lim <= y <= lim):
        raise MalformedEnvelope(f"position ({_short(x)}, {_short(y)}) out of bounds", "position")
    if not (_finite(txp) and limits.min_tx_power <= txp <= limits.max_tx_power):
        raise MalformedEnvelope(f"tx power {_short(txp)} dBm out of range", "tx_power")
    if not _int_in(seq, 0, 0xFFFF):
        raise MalformedEnvelope(f"bad link sequence number {_short(seq)}", "seq")
    if not _int_in(attempt, 0, limits.max_attempt):
        raise MalformedEnvelope(f"bad attempt number {_short(attempt)}", "attempt")
    if not (_finite(t) and -limits.max_time_s <= t <= limits.max_time_s):
        raise MalformedEnvelope(f"time {_short(t)} not finite or out of bounds", "time")
    if not isinstance(frame, bytes) or len(frame) > limits.mtu:
        raise MalformedEnvelope("frame is not bytes within the MTU", "frame")
    if kind == Kind.ACK and (dest == BROADCAST or frame):
        raise MalformedEnvelope("an ACK must be addressed to one node and carry no frame", "ack")
    return Envelope(
        Kind(kind), src, float(x), float(y), float(txp), seq, attempt, float(t), dest, frame
    )


def _short(v: object) -> str:
    """A bounded description of a remote value (never a deep or huge repr)."""
    if isinstance(v, bool | int | float):
        r = repr(v)
        return r if len(r) <= 24 else r[:21] + "..."
    return type(v).__name__
