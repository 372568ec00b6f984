"""Hardening of the radio and protocol side (issue 9): bounded decoding, last
guards, version arithmetic that cannot overflow, bounded state.

Property tests (hypothesis, derandomized) check that decoding envelopes,
frames and Drip items never raises anything but the documented error; the
regression tests replay the two crashes of the issue on real Zenoh sessions:
an envelope with ``tx_power`` 1e5 (OverflowError in ``max_range_m``) and a Drip
item at version 0xFFFFFFFF heard by the gateway (version overflow).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from awaremw.gateway.service import GatewayService, GatewaySettings, attach_to_fleet
from awaremw.gateway.store import unwrap, wire_version
from awaremw.nodes import KindsFactory, kind_names
from awaremw.protocol.dissemination import newer, next_version
from awaremw.protocol.events import ItemAdopted
from awaremw.protocol.frames import (
    BROADCAST,
    ChannelDef,
    DripItem,
    FrameError,
    ItemKind,
    decode,
    encode,
)
from awaremw.radio.envelope import (
    REASONS,
    EnvelopeLimits,
    Kind,
    MalformedEnvelope,
    decode_envelope,
    encode_envelope,
)
from awaremw.radio.faults import MAX_REASONS, FaultLog
from awaremw.radio.model import RadioModel, cell_of, preset
from awaremw.runtime.deployment import Deployment, load
from awaremw.runtime.driver import LagStats
from awaremw.runtime.fleet import Fleet, FleetSettings
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)

PROPS = settings(
    derandomize=True, max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
CC2420 = preset("cc2420")
LIMITS = EnvelopeLimits.of(CC2420)

# --------------------------------------------------------------------------- values

extreme_ints = st.sampled_from(
    [0, -1, 1, 255, 256, 0x7FFF, 0x8000, 0xFFFF, 0x10000, 0xFFFFFFFF, 2**32, 2**63 - 1, -(2**63),
     2**64 - 1]
)  # fmt: skip
extreme_floats = st.sampled_from(
    [0.0, -0.0, 1e5, -1e5, 1e308, -1e308, math.inf, -math.inf, math.nan, 5e-324, 1e6, 1e10]
)
scalars = st.one_of(
    extreme_ints,
    extreme_floats,
    st.integers(),
    st.floats(),
    st.booleans(),
    st.none(),
    st.text(max_size=8),
    st.binary(max_size=200),
)
values = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=3), inner, max_size=3)
    ),
    max_leaves=12,
)


def _pack(obj: Any) -> bytes:
    try:
        return bytes(msgpack.packb(obj, use_bin_type=True))
    except (OverflowError, ValueError, TypeError):
        return b"\xc1"  # never-used msgpack byte


def valid_envelope(**over: Any) -> list[Any]:
    f = {
        "ver": 1, "kind": 0, "src": 7, "x": 10.0, "y": 10.0, "txp": 0.0, "seq": 1,
        "attempt": 0, "t": 12.5, "dest": BROADCAST, "frame": encode(DripItem(7, BROADCAST)),
    }  # fmt: skip
    f.update(over)
    return list(f.values())


# --------------------------------------------------------------------------- envelopes


@PROPS
@given(st.binary(max_size=400))
def test_envelope_decode_of_any_bytes_raises_only_malformed(data: bytes) -> None:
    try:
        decode_envelope(data, LIMITS)
    except MalformedEnvelope as e:
        assert e.reason in REASONS


@PROPS
@given(st.integers(0, 10), values)
def test_envelope_with_any_field_mutated_is_valid_or_rejected(i: int, v: Any) -> None:
    env = valid_envelope()
    env[i] = v
    try:
        got = decode_envelope(_pack(env), LIMITS)
    except MalformedEnvelope as e:
        assert e.reason in REASONS
        return
    # Accepted: then every field is within its documented bound.
    assert all(math.isfinite(z) for z in (got.x, got.y, got.tx_power, got.t))
    assert CC2420.min_tx_power_dbm <= got.tx_power <= CC2420.max_tx_power_dbm
    assert len(got.frame) <= CC2420.mtu and 0 <= got.seq <= 0xFFFF


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("txp", 1e5, "tx_power"),
        ("txp", math.nan, "tx_power"),
        ("x", 1e300, "position"),
        ("y", -math.inf, "position"),
        ("t", math.inf, "time"),
        ("t", 1e12, "time"),
        ("seq", 0x10000, "seq"),
        ("attempt", 200, "attempt"),
        ("dest", 0xFFFE, "dest"),
        ("src", -1, "src"),
        ("frame", b"\x00" * (CC2420.mtu + 1), "frame"),
        ("kind", True, "kind"),
        ("ver", 2**64 - 1, "version"),
    ],
)
def test_envelope_field_out_of_bounds_is_rejected_with_its_reason(
    field: str, value: Any, reason: str
) -> None:
    with pytest.raises(MalformedEnvelope) as ei:
        decode_envelope(_pack(valid_envelope(**{field: value})), LIMITS)
    assert ei.value.reason == reason


def test_envelope_size_and_nesting_limits() -> None:
    with pytest.raises(MalformedEnvelope) as ei:
        decode_envelope(b"\x91" * 100_000, LIMITS)
    assert ei.value.reason == "size"
    deep = b"\x91" * 150 + b"\x00"  # 150 nested arrays, within the size limit
    with pytest.raises(MalformedEnvelope):
        decode_envelope(deep, LIMITS)
    ok = encode_envelope(Kind.FRAME, 3, 1.0, 2.0, 0.0, 9, 0, 1.0, BROADCAST, b"\x93\x01\x02\x03")
    assert decode_envelope(ok, LIMITS).src == 3


# --------------------------------------------------------------------------- frames, Drip items


@PROPS
@given(st.binary(max_size=CC2420.mtu))
def test_frame_decode_of_any_bytes_raises_only_frame_error(data: bytes) -> None:
    with contextlib.suppress(FrameError):
        decode(data)


@PROPS
@given(values, values, values, values)
def test_drip_item_decode_with_any_fields_raises_only_frame_error(
    kind: Any, item_id: Any, version: Any, body: Any
) -> None:
    data = _pack([DripItem.TYPE, 5, BROADCAST, kind, item_id, version, body])
    try:
        f = decode(data)
    except FrameError:
        return
    assert isinstance(f, DripItem) and 0 <= f.version <= 0xFFFFFFFF


@PROPS
@given(st.sampled_from([0, 1, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF]), extreme_ints)
def test_drip_item_at_extreme_versions(version: int, period: int) -> None:
    data = _pack([DripItem.TYPE, 5, BROADCAST, int(ItemKind.CHANNEL), 1, version,
                  [1, 1, 0xFFFF, period, 0]])  # fmt: skip
    try:
        f = decode(data)
    except FrameError:
        assert not 1 <= period <= 0xFFFFFFFF
        return
    assert isinstance(f, DripItem) and f.version == version


# --------------------------------------------------------------------------- versions


u32 = st.integers(0, 0xFFFFFFFF)


@PROPS
@given(u32, u32)
def test_serial_order_is_total_and_antisymmetric(a: int, b: int) -> None:
    if a == b:
        assert not newer(a, b)
    else:
        assert newer(a, b) != newer(b, a)


@PROPS
@given(u32)
def test_next_version_is_always_newer(v: int) -> None:
    assert newer(next_version(v), v)
    assert next_version(0xFFFFFFFF) == 0 and newer(0, 0xFFFFFFFF)


@PROPS
@given(u32, st.integers(0, 2**40))
def test_unwrap_agrees_with_serial_order(wire: int, ref: int) -> None:
    v = unwrap(wire, ref)
    assert wire_version(v) == wire
    assert (v > ref) == newer(wire, wire_version(ref))
    assert abs(v - ref) <= 2**31


# --------------------------------------------------------------------------- bounded state


def test_lag_stats_is_a_bounded_ring_with_meaningful_percentiles() -> None:
    lag = LagStats(window=1000)
    for i in range(5000):
        lag.add(float(i % 100))
    assert len(lag.samples) == 1000 and lag.count == 5000
    assert lag.percentile(50) == pytest.approx(49.0, abs=1)
    assert lag.percentile(99) == pytest.approx(98.0, abs=1)
    mark = lag.count
    for _ in range(10):
        lag.add(500.0)
    assert lag.since(mark) == [500.0] * 10
    assert len(lag.since(0)) == 1000  # only the window survives


def test_range_cache_is_bounded_and_refuses_impossible_powers() -> None:
    m = RadioModel(CC2420, seed=1)
    for i in range(10_000):
        m.max_range_m(CC2420.min_tx_power_dbm + i * 1e-4)
    assert len(m._range_cache) <= 64
    with pytest.raises(ValueError, match="outside"):
        m.max_range_m(1e5)  # was OverflowError


def test_fault_log_counts_per_reason_bounded_and_rate_limited(
    caplog: pytest.LogCaptureFixture,
) -> None:
    t = [0.0]
    import logging

    f = FaultLog("rejected envelope", logging.getLogger("t"), clock=lambda: t[0])
    with caplog.at_level(logging.WARNING, "t"):
        for _ in range(1000):
            f.count("tx_power", "x")
        t[0] = 11.0
        f.count("tx_power", "x")
    assert f.get("tx_power") == 1001
    assert len(caplog.records) == 2 and "1000 more" in caplog.records[1].getMessage()
    for i in range(200):
        f.count(f"r{i}")
    assert len(f.as_dict()) <= MAX_REASONS + 1


# ----------------------------------------------------------------- real Zenoh: regressions

SPEED = 4.0
Fleets = tuple[Deployment, Fleet, Fleet, GatewayService, str]


@asynccontextmanager
async def fleet_and_gateway() -> AsyncIterator[
    tuple[Deployment, Fleet, Fleet, GatewayService, str]
]:
    """The sensor motes of grid_small in one Fleet, the gateway mote with its
    service (no MQTT) in another, as in two processes."""
    dep = load("grid_small", kind_names())
    ep = free_tcp_endpoint()
    async with Fleet(
        dep,
        KindsFactory(),
        FleetSettings(name="sensors", speed=SPEED, listen=(ep,)),
        node_filter=lambda s: s.kind != "gateway",
    ) as sensors:
        gw = Fleet(
            dep,
            KindsFactory(),
            FleetSettings(
                name="gateway",
                speed=SPEED,
                connect=(ep,),
                start_wall=sensors.clock.start_wall,
                control=False,
            ),
            node_filter=lambda s: s.kind == "gateway",
        )
        async with gw:
            svc = attach_to_fleet(gw, settings=GatewaySettings())
            async with svc:
                yield dep, sensors, gw, svc, ep


async def until(cond: Any, timeout: float = 30.0) -> None:
    async def poll() -> None:
        while not cond():
            await asyncio.sleep(0.02)

    await asyncio.wait_for(poll(), timeout)


def radio_key(model: RadioModel, x: float, y: float, src: int) -> str:
    cx, cy = cell_of(x, y, model.cell_size_m)
    return f"aware/radio/{cx}/{cy}/{src}"


@pytest.mark.zenoh
async def test_tx_power_1e5_on_a_radio_key_is_rejected_and_counted() -> None:
    async with fleet_and_gateway() as (dep, sensors, gw, _svc, ep):
        model = sensors.medium.model
        gx, gy = next(s.position for s in dep.nodes if s.kind == "gateway")
        client = open_session(SessionSettings("client", (ep,)))
        try:
            for txp in (1e5, math.inf, -1e5):
                env = msgpack.packb(
                    [1, 0, 900, gx + 1.0, gy, txp, 1, 0, sensors.now(), BROADCAST, b"\x93\x00\x00"]
                )
                client.put(radio_key(model, gx + 1.0, gy, 900), env)
            await until(
                lambda: (
                    sensors.medium.rejected.get("tx_power") >= 3
                    and gw.medium.rejected.get("tx_power") >= 3
                )
            )
        finally:
            close_quietly(client)
        assert not sensors.failed and not gw.failed  # both processes still run
        assert sensors.medium.faults.total == 0 and gw.medium.faults.total == 0
        stats = sensors.control.request(json.dumps({"op": "stats"}).encode())["snapshot"]
        assert stats["rejected"]["tx_power"] >= 3


@pytest.mark.zenoh
async def test_drip_item_at_max_version_heard_by_the_gateway_cannot_lock_a_definition() -> None:
    """A foreign channel item at version 0xFFFFFFFF spreads and the gateway
    learns it (it used to crash on the next version); a new definition from the
    gateway then takes effect everywhere, at version 2**32 (0 on the radio)."""
    async with fleet_and_gateway() as (dep, sensors, gw, svc, ep):
        adopted: dict[int, set[int]] = {}  # version -> sensor motes holding it

        def on_event(node: int, ev: object, now: float) -> None:
            if isinstance(ev, ItemAdopted) and ev.kind is ItemKind.CHANNEL:
                adopted.setdefault(ev.version, set()).add(node)

        sensors.on_event(on_event)
        n = sum(1 for s in dep.nodes if s.kind != "gateway")
        group = {"conditions": [{"attr": "x", "op": ">", "value": 3}]}
        assert svc.handle("def/group/1", json.dumps(group).encode()).accepted

        # A foreign Drip item at the last u32 version, next to the gateway mote.
        gx, gy = next(s.position for s in dep.nodes if s.kind == "gateway")
        forged = DripItem(900, BROADCAST, ItemKind.CHANNEL, 1, 0xFFFFFFFF,
                          ChannelDef(1, 1, 0xFFFF, 9000, 0))  # fmt: skip
        client = open_session(SessionSettings("client", (ep,)))
        try:
            for seq in range(3):
                # One after another (10 ms apart), as one radio would send them: frames
                # on the air at once collide (docs/radio.md, "Medium access and collisions").
                env = encode_envelope(
                    Kind.FRAME, 900, gx + 0.5, gy, 0.0, seq, 0, sensors.now() + 0.01 * seq,
                    BROADCAST, encode(forged),
                )  # fmt: skip
                client.put(radio_key(sensors.medium.model, gx + 0.5, gy, 900), env)
        finally:
            close_quietly(client)
        await until(lambda: svc.bridge.stats.learned >= 1)  # the forged item
        await until(lambda: len(adopted.get(0xFFFFFFFF, ())) == n)
        assert svc.bridge.definitions()["def/channel/1"]["version"] == 0xFFFFFFFF

        # A new definition from the gateway takes effect everywhere, twice.
        ch = {"attr": "temperature", "group_type": 1, "group_id": "*", "agg": "avg"}
        for k, period in enumerate((2.0, 3.0)):
            out = svc.handle("def/channel/1", json.dumps({**ch, "period_s": period}).encode())
            assert out.inject is not None and out.inject.version == 2**32 + k
            await until(lambda k=k: len(adopted.get(k, ())) == n)  # type: ignore[misc]
            for node in range(1, n + 1):
                item = sensors.cores[node].dissemination.items[(ItemKind.CHANNEL, 1)]  # type: ignore[attr-defined]
                assert item.version == k and item.body.period_ms == int(period * 1000)
        assert not sensors.failed and not gw.failed
        assert sensors.medium.faults.total == 0 and gw.medium.faults.total == 0
