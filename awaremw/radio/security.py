"""Link-layer frame authentication, as IEEE 802.15.4 security (MIC-64) does it.

One place for both media (the Zenoh medium and the virtual-clock driver):
a frame goes on the air *sealed* and comes off the air *opened* here.

On the air a secured frame is ``payload || counter (4 B, big-endian) || MIC``:
the sender's frame counter (a link-layer retry is the same frame, so the same
counter) and an AES-CCM* authentication-only MIC over the MAC header fields
the envelope carries, the payload and the counter (8 bytes, 802.15.4's
MIC-64; 4 bytes = MIC-32 as TinySec-Auth). Receivers verify the MIC once per
transmission, then each drops a frame whose counter is not above the highest
it accepted from that sender (a replay), in a table bounded at
:data:`MAX_SENDERS` senders. Hardware ACKs are not secured, as in 802.15.4.
The sealed frame must fit the preset's MTU, so the middleware's frames get
``mtu - overhead`` bytes (:meth:`RadioSecurity.payload_mtu`). The nonce, the
order of the checks and the known limitations: docs/security.md,
"Authenticated frames".
"""

from __future__ import annotations

import logging
import os
import struct
from dataclasses import dataclass, field
from typing import NamedTuple

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from cryptography.hazmat.primitives.ciphers.aead import AESCCM
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from awaremw.radio.counters import MoteCounters
from awaremw.radio.faults import FaultLog

log = logging.getLogger(__name__)

KEY_BYTES = 16  # AES-128, as 802.15.4
KEY_SIZES = (16, 32)  # AES-128-CCM* (802.15.4) or AES-256-CCM (`keys init --network-key-bytes 32`)
COUNTER_BYTES = 4
MAX_COUNTER = 0xFFFFFFFF
MAX_SENDERS = 256  # replay-table entries per receiver (neighbours it has heard)
REASONS = ("short", "mic", "replay", "senders")

_HDR = struct.Struct(">HHH")  # src, dest, link seq: the MAC header fields the MIC covers
_CTR = struct.Struct(">I")
_NONCE = struct.Struct(">QIB")  # extended source address, frame counter, security level


@dataclass(frozen=True, slots=True)
class RadioSecurity:
    """The key material a secured radio needs (what ``--secrets DIR`` provides).

    ``network_key``: 16 raw bytes (AES-128, as 802.15.4; 32 for AES-256) shared
    by every mote and gateway of the network (``DIR/radio/network.key``).
    ``gateway_public_key``: the gateway's raw 32-byte Ed25519 public key, with
    which motes verify dissemination items (None: items are not verified).
    ``mic_bytes``: 8 (MIC-64, default) or 4 (MIC-32).
    """

    network_key: bytes = field(repr=False)
    gateway_public_key: bytes | None = None
    mic_bytes: int = 8

    def __post_init__(self) -> None:
        if not isinstance(self.network_key, bytes) or len(self.network_key) not in KEY_SIZES:
            raise ValueError("the network key must be 16 raw bytes (AES-128) or 32 (AES-256)")
        if self.gateway_public_key is not None and len(self.gateway_public_key) != 32:
            raise ValueError("the gateway public key must be 32 raw bytes (Ed25519)")
        if self.mic_bytes not in (4, 8):
            raise ValueError(f"MIC length must be 4 or 8 bytes, not {self.mic_bytes}")

    @property
    def overhead(self) -> int:
        """Bytes a sealed frame adds to the payload (counter + MIC)."""
        return COUNTER_BYTES + self.mic_bytes

    def payload_mtu(self, mtu: int) -> int:
        """The largest payload (middleware frame) a radio of MTU ``mtu`` can carry."""
        return mtu - self.overhead

    @classmethod
    def throwaway(cls, mic_bytes: int = 8) -> tuple[RadioSecurity, Ed25519PrivateKey]:
        """Fresh random keys (benchmarks, tests): the security and the gateway's signing key."""
        sk = Ed25519PrivateKey.generate()
        pk = sk.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
        return cls(os.urandom(KEY_BYTES), pk, mic_bytes), sk


class Opened(NamedTuple):
    """A frame off the air after the MIC check: ``payload`` None if refused (``reason``)."""

    payload: bytes | None
    counter: int
    reason: str


class FrameGuard:
    """Seals and opens frames for the motes of one medium; keeps their counters.

    ``refused`` counts refused receptions per reason (:data:`REASONS`): one
    per receiving mote, as each real mote would drop the frame itself.
    """

    __slots__ = ("_ccm", "_level", "_rx", "_tx", "mic_bytes", "overhead", "refused", "security")

    def __init__(self, security: RadioSecurity) -> None:
        self.security = security
        self.mic_bytes = security.mic_bytes
        self.overhead = security.overhead
        self._ccm = AESCCM(security.network_key, tag_length=security.mic_bytes)
        self._level = 2 if security.mic_bytes == 8 else 1
        self._tx: dict[int, int] = {}  # node id -> last counter used (bound: node ids)
        self._rx: dict[int, dict[int, int]] = {}  # receiver -> sender -> highest counter
        self.refused = FaultLog("refused frame", log, logging.INFO)

    def _mic(self, src: int, dest: int, seq: int, body: bytes, counter: int) -> bytes:
        nonce = _NONCE.pack(src, counter, self._level)
        mic: bytes = self._ccm.encrypt(nonce, b"", _HDR.pack(src, dest, seq) + body)
        return mic

    def seal(self, src: int, dest: int, seq: int, payload: bytes) -> bytes:
        """The frame ``src`` puts on the air: payload, its next counter, the MIC."""
        counter = self._tx.get(src, 0) + 1
        if counter > MAX_COUNTER:  # 2**32 frames: 802.15.4 requires a new key
            raise RuntimeError(f"node {src}: frame counter exhausted; rotate the network key")
        self._tx[src] = counter
        body = payload + _CTR.pack(counter)
        return body + self._mic(src, dest, seq, body, counter)

    def open(self, src: int, dest: int, seq: int, air: bytes) -> Opened:
        """Check the MIC of a frame heard from ``src`` (once per transmission)."""
        cut = len(air) - self.mic_bytes
        if cut < COUNTER_BYTES:
            return Opened(None, 0, "short")
        body = air[:cut]
        (counter,) = _CTR.unpack_from(body, cut - COUNTER_BYTES)
        nonce = _NONCE.pack(src, counter, self._level)
        try:
            self._ccm.decrypt(nonce, air[cut:], _HDR.pack(src, dest, seq) + body)
        except InvalidTag:
            return Opened(None, counter, "mic")
        return Opened(body[: cut - COUNTER_BYTES], counter, "")

    def accept(self, rid: int, counters: MoteCounters, src: int, o: Opened) -> bytes | None:
        """Whether receiver ``rid`` takes the opened frame: the payload, or None
        (refused: counted in ``counters.refused`` and in :attr:`refused`)."""
        if o.payload is None:
            self._refuse(counters, o.reason, src, rid)
            return None
        table = self._rx.get(rid)
        if table is None:
            table = self._rx[rid] = {}
        last = table.get(src)
        if last is None:
            if len(table) >= MAX_SENDERS:
                self._refuse(counters, "senders", src, rid)
                return None
        elif o.counter <= last:
            self._refuse(counters, "replay", src, rid)
            return None
        table[src] = o.counter
        return o.payload

    def _refuse(self, counters: MoteCounters, reason: str, src: int, rid: int) -> None:
        counters.refused += 1
        self.refused.count(reason, f"frame from {src} at node {rid}")

    def resume(self, node_id: int, counter: int) -> None:
        """``node_id`` goes on counting above ``counter`` (a mote restarted in a new
        process: its counter is in flash, not reset)."""
        if not 0 <= counter <= MAX_COUNTER:
            raise ValueError(f"frame counter {counter} outside 0..{MAX_COUNTER}")
        self._tx[node_id] = max(self._tx.get(node_id, 0), counter)

    def counter_of(self, node_id: int) -> int:
        """The last frame counter ``node_id`` used here (0: none yet)."""
        return self._tx.get(node_id, 0)
