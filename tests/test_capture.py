"""Radio captures (docs/capture.md): the pcapng writer, the tap in both media,
``--pcap`` on experiment and fleet, ``awaremw sniff`` against a real fleet over
Zenoh, and what Debian's tshark (with the shipped Lua dissector) makes of them."""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import msgpack
import pytest

from awaremw.cli.sniff import dissector_path
from awaremw.experiments import EXPERIMENTS
from awaremw.experiments.scenario import load_scenario
from awaremw.experiments.virtual import VirtualRun
from awaremw.protocol.frames import BROADCAST, FRAME_TYPES
from awaremw.radio.capture import (
    LINKTYPE_IEEE802_15_4_NOFCS,
    Capture,
    PcapngWriter,
    mac_header,
)
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.runtime.deployment import load
from awaremw.runtime.zenoh_session import free_tcp_endpoint

AWAREMW = [sys.executable, "-m", "awaremw"]
TSHARK = shutil.which("tshark")
# CI (.ci/run) installs Debian's tshark and sets AWAREMW_REQUIRE_TSHARK=1: there a
# missing tshark fails these tests instead of skipping them.
if TSHARK is None and os.environ.get("AWAREMW_REQUIRE_TSHARK") == "1":
    raise RuntimeError("AWAREMW_REQUIRE_TSHARK=1 but tshark is not installed")
needs_tshark = pytest.mark.skipif(
    TSHARK is None, reason="tshark is not installed (Debian package tshark; .ci/run installs it)"
)


# --- a pcapng reader


def read_pcapng(path: Path) -> tuple[list[tuple[int, str]], list[tuple[int, int, bytes, str]]]:
    """(interfaces as (linktype, name), packets as (iface, ns, data, comment)): an
    independent reading of the blocks, checking lengths as it goes."""
    raw = path.read_bytes()
    ifaces: list[tuple[int, str]] = []
    packets: list[tuple[int, int, bytes, str]] = []
    off = 0
    while off < len(raw):
        btype, total = struct.unpack_from("<II", raw, off)
        assert total % 4 == 0 and total >= 12
        assert struct.unpack_from("<I", raw, off + total - 4)[0] == total
        body = raw[off + 8 : off + total - 4]
        if off == 0:
            assert btype == 0x0A0D0D0A and struct.unpack_from("<I", body)[0] == 0x1A2B3C4D
        elif btype == 1:
            linktype = struct.unpack_from("<H", body)[0]
            opts = _options(body[8:])
            ifaces.append((linktype, opts.get(2, b"").decode()))
        elif btype == 6:
            iface, hi, lo, cap, orig = struct.unpack_from("<IIIII", body)
            assert cap == orig and iface < len(ifaces)
            data = body[20 : 20 + cap]
            opts = _options(body[20 + cap + (-cap % 4) :])
            packets.append((iface, hi << 32 | lo, data, opts.get(1, b"").decode()))
        off += total
    assert off == len(raw)
    return ifaces, packets


def _options(b: bytes) -> dict[int, bytes]:
    out: dict[int, bytes] = {}
    off = 0
    while off + 4 <= len(b):
        code, n = struct.unpack_from("<HH", b, off)
        if code == 0:
            break
        out[code] = b[off + 4 : off + 4 + n]
        off += 4 + n + (-n % 4)
    return out


def tshark(*args: str) -> list[str]:
    assert TSHARK is not None
    p = subprocess.run([TSHARK, *args], capture_output=True, text=True, timeout=120, check=False)
    assert p.returncode == 0, p.stderr
    return p.stdout.splitlines()


# --- writer and header


def test_mac_header_is_an_802154_data_frame_with_short_addresses() -> None:
    # FCF 0x8841: data, PAN id compression, 16-bit dst and src; DSN; PAN; dst; src.
    assert mac_header(3, BROADCAST, 0x1234, 0x22) == bytes.fromhex("4188342200ffff0300")
    # A unicast asks for the ACK (bit 5): 0x8861.
    assert mac_header(3, 7, 1, 0x22) == bytes.fromhex("6188012200" + "0700" + "0300")


def test_writer_blocks_read_back_and_its_buffer_and_file_are_bounded(tmp_path: Path) -> None:
    path = tmp_path / "x.pcapng"
    w = PcapngWriter(path, max_buffer=1000, max_bytes=20_000)
    air = w.add_interface("air")
    for i in range(1000):
        w.write_packet(air, 1.5 + i, b"\x01\x02\x03", f"n={i}")
        assert w._buffered < 1000 + 200  # never more than one block past the bound
    assert w.dropped > 0 and w.packets + w.dropped == 1000
    w.close()
    assert path.stat().st_size <= 20_000
    ifaces, packets = read_pcapng(path)
    assert ifaces == [(LINKTYPE_IEEE802_15_4_NOFCS, "air")]
    assert len(packets) == w.packets
    assert packets[0] == (0, 1_500_000_000, b"\x01\x02\x03", "n=0")
    assert w.write_packet(air, 1.0, b"x") is False  # closed: dropped, no exception


# --- the tap in the virtual medium


def _virtual(tap: Capture | None) -> VirtualNetwork:
    """romeo4r on the virtual clock for 40 s: static and moving motes, broadcasts
    and unicasts (collection), retries."""
    run = VirtualRun(load_scenario(EXPERIMENTS["romeo4r"][0]))
    run.net.tap = tap
    run.run(40.0)
    return run.net


def test_virtual_tap_sees_every_attempt_and_every_delivery_and_changes_nothing(
    tmp_path: Path,
) -> None:
    cap = Capture.to_file(tmp_path / "v.pcapng")
    net = _virtual(cap)
    cap.close()
    plain = _virtual(None)
    counters = net.counters
    assert counters == plain.counters  # a capture does not change the run
    ifaces, packets = read_pcapng(tmp_path / "v.pcapng")
    air = [p for p in packets if p[0] == 0]
    # One packet per attempt on the air, from exactly the motes that sent.
    assert len(air) == sum(c.frames_tx for c in counters.values())
    senders = {struct.unpack_from("<H", d, 7)[0] for _, _, d, _ in air}
    assert senders == {n for n, c in counters.items() if c.frames_tx}
    # Every delivered frame (refused or duplicate ones included) at every mote.
    rx = Counter()
    lost = Counter()
    collided = Counter()
    for iface, _, _, comment in packets:
        if iface == 0:
            continue
        mote = int(ifaces[iface][1].split()[1])
        m = re.match(r"(rx|lost cause=(\w+))", comment)
        assert m is not None, comment
        if m.group(1) == "rx":
            rx[mote] += 1
            assert "rssi=" in comment
        elif m.group(2) == "collision":
            collided[mote] += 1
        else:
            assert m.group(2) in ("path_loss", "distance")
            lost[mote] += 1
    for mote, c in counters.items():
        assert rx[mote] == c.frames_rx
        assert collided[mote] == c.collisions  # each one recorded with its cause
        # Bulk-counted certain losses are not recorded one by one: at most the count.
        assert lost[mote] <= c.dropped_loss + c.dropped_distance
    assert sum(lost.values()) > 0
    assert sum(collided.values()) > 0  # csma + sinr, the default


# --- tshark and the dissector


def test_dissector_names_every_frame_type() -> None:
    text = dissector_path().read_text(encoding="utf-8")
    named = dict(re.findall(r'\[(\d+)\] = "(\w+)"', text))
    assert {int(k): v for k, v in named.items()} == {
        t: cls.__name__ for t, cls in FRAME_TYPES.items()
    }


def test_dissector_labels_every_body_field_in_order() -> None:
    text = dissector_path().read_text(encoding="utf-8")
    labels = {
        int(t): re.findall(r'"(\w+)"', names)
        for t, names in re.findall(r"\[(\d+)\] = \{([^}]*)\}", text)
    }
    assert labels == {
        t: [f.name for f in dataclasses.fields(cls)][2:]  # after src and dst
        for t, cls in FRAME_TYPES.items()
    }


@needs_tshark
def test_tshark_names_every_frame_type_with_the_dissector(tmp_path: Path) -> None:
    cap = Capture.to_file(tmp_path / "types.pcapng")
    for i, t in enumerate(sorted(FRAME_TYPES)):
        cap.on_air(float(i), 5, BROADCAST, i, 0, msgpack.packb([t, 5, BROADCAST, 1, 2]))
    # A sealed frame: counter and MIC-64 after the msgpack array.
    cap.on_air(99.0, 6, 2, 1, 0, msgpack.packb([1, 6, 2, 9]) + b"\0\0\0\x07" + b"M" * 8)
    cap.close()
    lines = tshark(
        "-X", f"lua_script:{dissector_path()}", "-r", str(tmp_path / "types.pcapng"),
        "-T", "fields", "-e", "awaremw.type_name", "-e", "awaremw.counter",
    )  # fmt: skip
    names = [ln.split("\t") for ln in lines]
    assert [n[0] for n in names] == [FRAME_TYPES[t].__name__ for t in sorted(FRAME_TYPES)] + [
        "Hello"
    ]
    assert names[-1][1] == "7"


@needs_tshark
def test_experiment_romeo4r_virtual_pcap_reads_in_tshark(tmp_path: Path) -> None:
    pcap = tmp_path / "out.pcap"
    p = subprocess.run(
        [*AWAREMW, "experiment", "romeo4r", "--virtual", "--duration", "60",
         "--out", str(tmp_path / "out"), "--pcap", str(pcap)],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    # Plain tshark: 802.15.4 data frames from every mote of the deployment (all of
    # them transmit within 60 s: beacons, Hello, dissemination).
    rows = [ln.split("\t") for ln in tshark(
        "-r", str(pcap), "-Y", 'frame.interface_name == "air"',
        "-T", "fields", "-e", "wpan.frame_type", "-e", "wpan.src16", "-e", "wpan.dst_pan",
    )]  # fmt: skip
    assert rows and all(r[0] == "0x0001" and r[2] == "0x0022" for r in rows)
    ids = {n.id for n in load("romeo4r").nodes}
    assert {int(r[1], 16) for r in rows} == ids
    # With the dissector: every awaremw frame named.
    lines = tshark(
        "-X", f"lua_script:{dissector_path()}", "-r", str(pcap),
        "-T", "fields", "-e", "frame.protocols", "-e", "awaremw.type_name",
    )  # fmt: skip
    types = Counter(ln.split("\t")[1] for ln in lines)
    assert "" not in types  # no packet left undissected
    assert {"Hello", "CtpBeacon", "DripItem", "DripSummary", "LeaderBeacon"} <= set(types)
    # Receptions: RSSI and loss causes in the packet comments.
    comments = tshark("-r", str(pcap), "-T", "fields", "-e", "frame.comment")
    assert any(c.startswith("rx rssi=") for c in comments)
    assert any(c.startswith("lost cause=") for c in comments)


# --- over Zenoh


def _wait_line(proc: subprocess.Popen[str], needle: str, timeout: float) -> str:
    assert proc.stderr is not None
    end = time.monotonic() + timeout
    seen = []
    while time.monotonic() < end:
        line = proc.stderr.readline()
        if not line:
            break
        seen.append(line)
        if needle in line:
            return line
    raise AssertionError(f"no {needle!r} from the process: {''.join(seen)[-2000:]}")


@pytest.mark.zenoh
def test_sniff_captures_a_real_fleet_over_zenoh_and_stops_cleanly_on_sigterm(
    tmp_path: Path,
) -> None:
    ep = free_tcp_endpoint()
    fleet_pcap, sniff_pcap = tmp_path / "fleet.pcapng", tmp_path / "sniff.pcapng"
    fleet = subprocess.Popen(
        [*AWAREMW, "fleet", "grid_small", "--listen", ep, "--duration", "20", "--speed", "2",
         "--plain", "--pcap", str(fleet_pcap)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    sniff = subprocess.Popen(
        [*AWAREMW, "sniff", "--connect", ep, "--pcap", str(sniff_pcap)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        _wait_line(sniff, "aware/radio/**", 30)
        # Wait (bounded) until the capture holds frames: flushed every second.
        end = time.monotonic() + 30
        while time.monotonic() < end:
            if sniff_pcap.exists() and len(read_pcapng(sniff_pcap)[1]) >= 20:
                break
            time.sleep(0.2)
        sniff.send_signal(signal.SIGTERM)
        _, err = sniff.communicate(timeout=20)
        assert sniff.returncode == 0, err
        out, _ = fleet.communicate(timeout=60)
        assert fleet.returncode == 0, out
    finally:
        for p in (sniff, fleet):
            if p.poll() is None:
                p.kill()
                p.wait()
    summary = re.search(r"(\d+) packets to", err)
    assert summary is not None, err
    ifaces, packets = read_pcapng(sniff_pcap)
    assert len(packets) == int(summary.group(1)) >= 20  # everything counted was flushed
    assert [name for _, name in ifaces] == ["air"]
    ids = {n.id for n in load("grid_small").nodes}
    srcs = {struct.unpack_from("<H", d, 7)[0] for _, _, d, _ in packets}
    assert srcs and srcs <= ids
    for _, _, d, comment in packets:
        assert d[:2] == bytes.fromhex("4188") and comment.startswith("tx src=")
        assert msgpack.unpackb(d[9:])[1] == struct.unpack_from("<H", d, 7)[0]  # frame src
    # The fleet's own capture: its motes' frames and their receptions with RSSI.
    f_ifaces, f_packets = read_pcapng(fleet_pcap)
    assert len(f_ifaces) > 1 and any(c.startswith("rx rssi=") for *_, c in f_packets)
    sniffed = {(d, c.split()[1]) for _, _, d, c in packets}
    fleet_air = {(d, c.split()[1]) for i, _, d, c in f_packets if i == 0}
    assert sniffed <= fleet_air  # the sniffer saw frames the fleet put on the air


def test_sniffer_checks_and_strips_the_mic_and_counts_garbage(tmp_path: Path) -> None:
    from awaremw.radio.envelope import Kind, encode_envelope
    from awaremw.radio.security import FrameGuard, RadioSecurity
    from awaremw.radio.sniffer import Sniffer

    sec, _ = RadioSecurity.throwaway()
    sealed = FrameGuard(sec).seal(4, BROADCAST, 9, msgpack.packb([1, 4, BROADCAST, 3]))
    forged = sealed[:-1] + bytes([sealed[-1] ^ 1])
    cap = Capture.to_file(tmp_path / "s.pcapng", receptions=False)
    sn = Sniffer(None, cap, security=sec)  # type: ignore[arg-type]  # handle() needs no session
    for seq, frame in ((9, sealed), (10, forged)):
        sn.handle(encode_envelope(Kind.FRAME, 4, 1.0, 2.0, 0.0, seq, 0, 5.0, BROADCAST, frame), 7.0)
    sn.handle(encode_envelope(Kind.ACK, 2, 1.0, 2.0, 0.0, 10, 0, 5.1, 4, b""), 7.5)
    sn.handle(b"\xc1garbage", 8.0)
    sn.close()
    assert (sn.stats.mic_ok, sn.stats.mic_bad, sn.stats.acks, sn.stats.malformed) == (1, 1, 1, 1)
    _, packets = read_pcapng(tmp_path / "s.pcapng")
    assert len(packets) == 3
    (_, ns, ok, c_ok), (_, _, bad, c_bad), (_, _, ack, c_ack) = packets
    assert ns == 7_000_000_000
    assert ok[9:] == msgpack.packb([1, 4, BROADCAST, 3]) and "mic=ok counter=1" in c_ok
    assert bad[9:] == forged and "mic=bad" in c_bad
    assert ack == bytes.fromhex("02000a") and c_ack.startswith("ack src=2 dst=4 seq=10")


@pytest.mark.zenoh
def test_fleet_with_worker_processes_pcap_sniffs_the_router(tmp_path: Path) -> None:
    pcap = tmp_path / "multi.pcapng"
    p = subprocess.run(
        [*AWAREMW, "fleet", "grid_small", "--processes", "2", "--hello", "--listen",
         free_tcp_endpoint(), "--duration", "6", "--speed", "2", "--pcap", str(pcap)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    tx = int(re.search(r"frames tx=(\d+)", p.stdout).group(1))  # type: ignore[union-attr]
    _, packets = read_pcapng(pcap)
    # HelloMote only broadcasts, and every broadcast goes through Zenoh: the sniffer
    # joined before the shared start, so it sees (nearly) all of them.
    assert tx > 50 and 0.9 * tx <= len(packets) <= tx
    assert f"{len(packets)} packets to {pcap}" in p.stdout
