"""Radio captures Wireshark reads: pcapng, link type IEEE 802.15.4 without FCS.

Two parts (``docs/capture.md``):

* :class:`PcapngWriter` writes pcapng (section header, interface description
  and enhanced packet blocks) with :mod:`struct`; what it buffers is bounded
  (``max_buffer`` bytes, then it writes to the file), and so is the file when
  ``max_bytes`` is given (packets beyond it are dropped and counted).
* :class:`Capture` is the **tap** the media call (:class:`RadioTap`): a frame on
  the air (:meth:`~RadioTap.on_air`) and a reception at one mote, with its RSSI
  and, when it was lost, the cause (:meth:`~RadioTap.reception`). It turns each
  into a packet: the awaremw frame (the bytes on the air, sealed when the radio
  is secured) behind a valid 802.15.4 MAC header -- data frame, PAN id
  compression, 16-bit short destination and source addresses (mote ids,
  broadcast ``0xffff``), the low byte of the sender's link sequence number as
  the DSN, ACK request on unicasts.

Metadata (RSSI, loss cause, attempt, full 16-bit sequence number) goes in each
packet's pcapng comment, so the link type stays the plain
LINKTYPE_IEEE802_15_4_NOFCS (230) every 802.15.4 tool knows. Interfaces:
``air`` (id 0) holds one packet per frame put on the air (every attempt);
``mote N`` what mote N's radio made of each frame it considered. How to read
and filter them in Wireshark and tshark: docs/capture.md.
"""

from __future__ import annotations

import math
import struct
import time
from collections import deque
from pathlib import Path
from typing import BinaryIO, Protocol

from awaremw.protocol.frames import BROADCAST
from awaremw.radio.security import Opened

LINKTYPE_IEEE802_15_4_NOFCS = 230
DEFAULT_PAN_ID = 0x0022  # TinyOS's default AM group (TOS_AM_GROUP)
DEFAULT_MAX_BUFFER = 256 * 1024  # bytes held in memory before a write to the file
RECENT = 8  # attempts per sender remembered to record each once
MAX_COMMENT = 200  # characters of a packet comment (bounded; ours are far shorter)

# Loss causes the media report (``None``: delivered to the mote's core).
CAUSES = (
    "distance",  # beyond the sender's maximum range
    "path_loss",  # below sensitivity or lost by the packet-reception model (path loss, fading)
    "collision",  # overlapped on air without capture (the MAC reports it)
    "mic",  # link security: bad or short MIC
    "replay",  # link security: frame counter not above the last accepted (or sender table full)
    "duplicate",  # a unicast retry of a frame already delivered (the ACK was lost)
)

_SHB = 0x0A0D0D0A
_IDB = 0x00000001
_EPB = 0x00000006
_BOM = 0x1A2B3C4D
_OPT_END = 0
_OPT_COMMENT = 1
_SHB_USERAPPL = 4
_IF_NAME = 2
_IF_TSRESOL = 9

# 802.15.4 frame control: data frame (1), PAN id compression (bit 6), 16-bit
# destination (bits 10-11 = 2) and source (bits 14-15 = 2) addresses; ACK request (bit 5).
FCF_DATA = 0x0001 | 0x0040 | (2 << 10) | (2 << 14)  # 0x8841
FCF_ACK_REQUEST = 0x0020
FCF_ACK = 0x0002  # an ACK frame (no addresses)
_MHR = struct.Struct("<HBHHH")  # FCF, DSN, dst PAN, dst addr, src addr (9 bytes)


def mac_header(src: int, dest: int, seq: int, pan_id: int = DEFAULT_PAN_ID) -> bytes:
    """The 9-byte 802.15.4 MAC header of a data frame from ``src`` to ``dest``."""
    fcf = FCF_DATA if dest == BROADCAST else FCF_DATA | FCF_ACK_REQUEST
    return _MHR.pack(fcf, seq & 0xFF, pan_id, dest, src)


def _pad4(n: int) -> int:
    return (4 - n % 4) % 4


def _option(code: int, value: bytes) -> bytes:
    return struct.pack("<HH", code, len(value)) + value + b"\0" * _pad4(len(value))


def _block(btype: int, body: bytes) -> bytes:
    total = 12 + len(body)
    return struct.pack("<II", btype, total) + body + struct.pack("<I", total)


class PcapngWriter:
    """A pcapng file with interfaces of one link type. Not thread-safe (one loop).

    ``max_buffer``: bytes kept in memory before they are written to the file.
    ``max_bytes``: the file's bound (None: unbounded); packets that would pass
    it are dropped and counted in :attr:`dropped`.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        linktype: int = LINKTYPE_IEEE802_15_4_NOFCS,
        max_buffer: int = DEFAULT_MAX_BUFFER,
        max_bytes: int | None = None,
        application: str = "awaremw",
    ) -> None:
        if max_buffer <= 0:
            raise ValueError(f"max_buffer must be > 0, not {max_buffer}")
        self.path = Path(path)
        self.linktype = linktype
        self.max_buffer = max_buffer
        self.max_bytes = max_bytes
        self.packets = 0
        self.dropped = 0
        self.written = 0  # bytes accepted (in the file or in the buffer)
        self.interfaces: list[str] = []
        self._buf: list[bytes] = []
        self._buffered = 0
        self._file: BinaryIO | None = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        shb = struct.pack("<IHHq", _BOM, 1, 0, -1)
        shb += _option(_SHB_USERAPPL, application.encode()) + _option(_OPT_END, b"")
        self._put(_block(_SHB, shb))

    @property
    def closed(self) -> bool:
        return self._file is None

    def add_interface(self, name: str) -> int:
        """Describe one more interface (before its packets); returns its id."""
        body = struct.pack("<HHI", self.linktype, 0, 0)  # snaplen 0: no limit
        body += _option(_IF_NAME, name.encode()[:128])
        body += _option(_IF_TSRESOL, bytes([9]))  # nanoseconds
        body += _option(_OPT_END, b"")
        self._put(_block(_IDB, body))
        self.interfaces.append(name)
        return len(self.interfaces) - 1

    def write_packet(self, iface: int, ts: float, data: bytes, comment: str = "") -> bool:
        """One enhanced packet block; False if dropped (file bound reached, or closed)."""
        if not 0 <= iface < len(self.interfaces):
            raise ValueError(f"no interface {iface}")
        if self._file is None or not math.isfinite(ts):
            self.dropped += 1
            return False
        ns = max(0, round(ts * 1e9))
        body = struct.pack("<IIIII", iface, ns >> 32, ns & 0xFFFFFFFF, len(data), len(data))
        body += data + b"\0" * _pad4(len(data))
        if comment:
            body += _option(_OPT_COMMENT, comment[:MAX_COMMENT].encode()) + _option(_OPT_END, b"")
        block = _block(_EPB, body)
        if self.max_bytes is not None and self.written + len(block) > self.max_bytes:
            self.dropped += 1
            return False
        self._put(block)
        self.packets += 1
        return True

    def _put(self, block: bytes) -> None:
        if self._file is None:
            raise ValueError(f"capture {self.path} is closed")
        self._buf.append(block)
        self._buffered += len(block)
        self.written += len(block)
        if self._buffered >= self.max_buffer:
            self.flush()

    def flush(self) -> None:
        """Write what is buffered to the file (and the file to the OS)."""
        if self._file is None:
            return
        if self._buf:
            self._file.write(b"".join(self._buf))
            self._buf.clear()
            self._buffered = 0
        self._file.flush()

    def close(self) -> None:
        if self._file is None:
            return
        self.flush()
        self._file.close()
        self._file = None


class RadioTap(Protocol):
    """What a medium tells a capture. Both calls are cheap and never raise on
    remote input (the medium has validated it)."""

    def on_air(self, t: float, src: int, dest: int, seq: int, attempt: int, frame: bytes) -> None:
        """``src`` put ``frame`` (the bytes on the air) on the air at emulated time ``t``."""

    def reception(
        self, t: float, src: int, dst: int, rssi: float | None, cause: str | None
    ) -> None:
        """Mote ``dst`` got (``cause`` None) or lost (``cause``, one of :data:`CAUSES`)
        the frame ``src`` last put on the air; ``rssi`` in dBm when known."""


class Capture:
    """The tap that writes a :class:`PcapngWriter`; see the module docstring.

    ``epoch``: wall time (Unix seconds) of emulated time 0; timestamps are
    ``epoch + t`` (0 for virtual runs: the capture starts at 1970-01-01, so a
    run is the same file for the same seed). ``receptions=False`` keeps only
    the ``air`` interface.
    """

    def __init__(
        self,
        writer: PcapngWriter,
        *,
        pan_id: int = DEFAULT_PAN_ID,
        epoch: float = 0.0,
        receptions: bool = True,
    ) -> None:
        if not 0 <= pan_id <= 0xFFFE:
            raise ValueError(f"PAN id {pan_id:#x} outside 0..0xfffe")
        self.writer = writer
        self.pan_id = pan_id
        self.epoch = epoch
        self.receptions = receptions
        self._air = writer.add_interface("air")
        self._flushed = time.monotonic()
        self._motes: dict[int, int] = {}  # mote id -> interface id (bound: node ids)
        # Per sender, the last frame it put on the air: MAC frame and comment stem
        # (bound: node ids, at most 0x8000).
        self._last: dict[int, tuple[bytes, str]] = {}
        # Per sender, its last RECENT attempts: several media of one process may share
        # this capture, and each reports the frames it hears (recorded once).
        self._recent: dict[int, deque[tuple[bytes, str]]] = {}

    @classmethod
    def to_file(
        cls,
        path: str | Path,
        *,
        epoch: float = 0.0,
        receptions: bool = True,
        max_bytes: int | None = None,
    ) -> Capture:
        """A capture to a new pcapng file at ``path``."""
        return cls(PcapngWriter(path, max_bytes=max_bytes), epoch=epoch, receptions=receptions)

    def on_air(
        self,
        t: float,
        src: int,
        dest: int,
        seq: int,
        attempt: int,
        frame: bytes,
        *,
        note: str = "",
    ) -> None:
        if self.writer.closed:
            return  # a medium still running after the capture closed
        to = "broadcast" if dest == BROADCAST else str(dest)
        stem = f"src={src} dst={to} seq={seq} attempt={attempt}"
        recent = self._recent.get(src)
        if recent is None:
            recent = self._recent[src] = deque(maxlen=RECENT)
        for seen in recent:
            if seen[1] == stem:  # an attempt already recorded (media sharing a capture)
                self._last[src] = seen
                return
        mac = mac_header(src, dest, seq, self.pan_id) + frame
        self._last[src] = (mac, stem)
        recent.append((mac, stem))
        tail = f" {note}" if note else ""
        self.writer.write_packet(self._air, self.epoch + t, mac, f"tx {stem}{tail}")

    def ack(self, t: float, src: int, dest: int, seq: int, note: str = "") -> None:
        """The 802.15.4 ACK ``src`` sent for ``dest``'s frame ``seq`` (its 3 bytes:
        frame control, DSN; an ACK carries no addresses, so they go in the comment)."""
        if self.writer.closed:
            return
        tail = f" {note}" if note else ""
        data = struct.pack("<HB", FCF_ACK, seq & 0xFF)
        self.writer.write_packet(
            self._air, self.epoch + t, data, f"ack src={src} dst={dest} seq={seq}{tail}"
        )

    def reception(
        self, t: float, src: int, dst: int, rssi: float | None, cause: str | None
    ) -> None:
        if not self.receptions or self.writer.closed:
            return
        last = self._last.get(src)
        if last is None:
            return  # a frame this capture never saw go on the air
        iface = self._motes.get(dst)
        if iface is None:
            iface = self._motes[dst] = self.writer.add_interface(f"mote {dst}")
        mac, stem = last
        what = "rx" if cause is None else f"lost cause={cause}"
        level = "" if rssi is None else f" rssi={rssi:.1f}dBm"
        self.writer.write_packet(iface, self.epoch + t, mac, f"{what}{level} at={dst} {stem}")

    def flush(self) -> None:
        self.writer.flush()

    def flush_if_due(self, every_s: float = 1.0) -> None:
        """Flush if the last flush is ``every_s`` wall seconds old (live captures:
        the file stays readable while it grows)."""
        now = time.monotonic()
        if now - self._flushed >= every_s:
            self._flushed = now
            self.writer.flush()

    def close(self) -> None:
        self.writer.close()

    @property
    def packets(self) -> int:
        return self.writer.packets


def refused(data: bytes | None, opened: Opened | None) -> str | None:
    """None if the core got the frame (``data``), else why link security refused it:
    a bad or short MIC, else a replayed counter (or a full sender table)."""
    if data is not None:
        return None
    return "mic" if opened is None or opened.payload is None else "replay"
