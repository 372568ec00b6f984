"""Hardening of the gateway's IP side (issue 9): hostile MQTT/Zenoh payloads get a
specific refusal and change nothing, every store is bounded, and the embedded
broker has an account, limits, a fixed port and retained definitions that
survive a restart."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import signal
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from awaremw.cli import main
from awaremw.gateway import schema
from awaremw.gateway.bridge import GatewayBridge
from awaremw.gateway.broker import BrokerLimits, EmbeddedBroker, mask_url
from awaremw.gateway.events import Outcome
from awaremw.gateway.store import VersionStore

GROUP = b'{"conditions": [{"attr": "temperature", "op": ">", "value": 45}]}'
CHANNEL = b'{"attr": "temperature", "group_type": 1, "period_s": 2, "agg": "avg"}'
CODES = {
    c.code
    for c in vars(schema).values()
    if isinstance(c, type) and issubclass(c, schema.SchemaError)
}


@pytest.fixture
def bridge() -> Iterator[GatewayBridge]:
    store = VersionStore()
    b = GatewayBridge(store, schema.Limits())
    for rel, p in (("def/group/1", GROUP), ("def/channel/1", CHANNEL)):
        assert b.handle(rel, p, source=f"aware/{rel}").accepted
    yield b
    store.close()


def refused(out: Outcome) -> str:
    assert out.error is not None and out.inject is None, out
    return out.error.code


# --------------------------------------------------------------------------- regressions


def test_deep_nesting_is_refused_not_a_recursion_error(bridge: GatewayBridge) -> None:
    before = bridge.definitions()
    for rel in ("def/group/1", "def/channel/1", "cmd/led"):
        deep = b"[" * 2000 + b"]" * 2000  # within the size limit; used to be RecursionError
        assert refused(bridge.handle(rel, deep, source=f"aware/{rel}")) == "payload_too_deep"
        nested = b'{"args": {"a": ' + b'{"b": ' * 20 + b"1" + b"}" * 21
        assert refused(bridge.handle(rel, nested, source=f"aware/{rel}")) == "payload_too_deep"
    assert bridge.definitions() == before
    assert bridge.stats.refused_by_code["payload_too_deep"] == 6


def test_unicode_digit_node_id_is_an_unknown_attribute(bridge: GatewayBridge) -> None:
    ch = b'{"attr": "rssi:\xc2\xb2", "period_s": 2}'  # rssi:² (used to be a ValueError)
    assert refused(bridge.handle("def/channel/2", ch, source="c")) == "unknown_attribute"
    grp = json.dumps({"conditions": [{"attr": "rssi:١٢", "op": ">", "value": -80}]}).encode()
    assert refused(bridge.handle("def/group/2", grp, source="g")) == "unknown_attribute"
    assert set(bridge.definitions()) == {"def/group/1", "def/channel/1"}


def test_define_verb_refuses_unicode_digits_cleanly(capsys: pytest.CaptureFixture[str]) -> None:
    # Refused locally before any connection (the URL points nowhere).
    url = ["--mqtt", "mqtt://127.0.0.1:1"]
    assert main(["define", "channel", "2", "--attr", "rssi:²", "--period", "2", *url]) == 2
    assert main(["define", "group", "2", "rssi:²>-80", *url]) == 2
    err = capsys.readouterr().err
    assert err.count("rssi:<node id> needs a node id") == 2 and "Traceback" not in err


def test_null_is_refused_only_empty_deletes(bridge: GatewayBridge) -> None:
    for rel in ("def/group/1", "def/channel/1", "cmd/led"):
        assert refused(bridge.handle(rel, b"null", source=f"aware/{rel}")) == "wrong_type"
    assert set(bridge.definitions()) == {"def/group/1", "def/channel/1"}
    out = bridge.handle("def/channel/1", b"", source="aware/def/channel/1")
    assert out.inject is not None and out.inject.body is None
    assert set(bridge.definitions()) == {"def/group/1"}


def test_long_topics_are_refused_and_never_stored(bridge: GatewayBridge) -> None:
    n0 = bridge.store.seen_count()
    for i in range(200):  # 200 topics of 60 KB used to be kept whole
        topic = f"aware/def/group/{i}/" + "x" * 60_000
        out = bridge.handle(topic[6:], GROUP, source=topic)
        assert refused(out) == "topic_too_long"
        assert out.error is not None and len(out.error.topic) < 250  # the echo is truncated
        assert len(out.error.to_json()) < 1500
    assert bridge.store.seen_count() == n0


def test_seen_store_and_error_echo_are_bounded() -> None:
    with VersionStore(max_seen=50) as store:
        b = GatewayBridge(store, schema.Limits())
        for i in range(300):
            b.handle(f"cmd/c{i}", b"{}", source=f"aware/cmd/c{i}")
        assert store.seen_count() <= 50
        out = b.handle("def/channel/1", b"x" * 4000, source="aware/def/channel/1")
        assert out.error is not None and out.error.code == "invalid_json"
        assert len(out.error.payload) < 600 and out.error.payload.endswith("bytes)")


def test_refusals_counted_per_code_and_logged_rate_limited(
    bridge: GatewayBridge, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="awaremw.gateway.bridge"):
        for _ in range(50):
            bridge.handle("def/group/1", b"null", source="aware/def/group/1")
            bridge.handle("def/group/1", b"{", source="aware/def/group/1")
    assert bridge.stats.refused_by_code == {"wrong_type": 50, "invalid_json": 50}
    lines = [r for r in caplog.records if r.name == "awaremw.gateway.bridge"]
    assert len(lines) == 2  # one per code in the interval, not 100


# --------------------------------------------------------------------------- properties

leaf = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats()
    | st.text(max_size=20)
    | st.sampled_from(["temperature", "rssi:3", "rssi:²", ">", "*", "avg", "all"])
)
keys = st.sampled_from(
    ["conditions", "attr", "op", "value", "hysteresis", "group_type", "group_id", "period_s",
     "agg", "target", "args", "node"]
) | st.text(max_size=8)  # fmt: skip
json_docs = st.recursive(
    leaf, lambda kids: st.lists(kids, max_size=5) | st.dictionaries(keys, kids, max_size=6),
    max_leaves=30,
)  # fmt: skip


def _encode(doc: Any) -> bytes:
    return json.dumps(doc, allow_nan=True).encode()


payloads = (
    json_docs.map(_encode)
    | st.integers(1, 4000).map(lambda n: b"[" * n + b"]" * n)
    | st.integers(1, 3000).map(lambda n: b'{"a":' * n + b"1" + b"}" * n)
    | st.integers(4097, 200_000).map(lambda n: b" " * n)
    | st.binary(max_size=200)
)
topics = st.sampled_from(
    ["def/group/1", "def/group/2", "def/group/300", "def/group/²", "def/channel/1",
     "def/channel/3", "def/channel/-1", "cmd/led", "cmd/", "def/widget/1"]
)  # fmt: skip


@settings(
    max_examples=400, deadline=None, derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)  # fmt: skip
@given(rel=topics, payload=payloads)
def test_any_payload_is_applied_whole_or_refused_specifically(
    bridge: GatewayBridge, rel: str, payload: bytes
) -> None:
    before = bridge.definitions()
    out = bridge.handle(rel, payload, source=f"aware/{rel}")
    if out.error is not None:
        assert out.error.code in CODES and out.error.code != "invalid"
        assert out.inject is None and bridge.definitions() == before
        assert len(out.error.payload) < 600
    else:
        assert out.inject is not None or bridge.definitions() == before


# --------------------------------------------------------------------------- real transports


@pytest.mark.zenoh
async def test_hostile_payloads_over_zenoh_and_mqtt_get_specific_errors(tmp_path: Path) -> None:
    """The embedded broker and a real Zenoh session: each hostile payload -> its code."""
    from awaremw.gateway.mqtt import MqttSettings
    from awaremw.gateway.service import GatewayService, GatewaySettings
    from awaremw.runtime.zenoh_session import SessionSettings, free_tcp_endpoint, open_session

    hostile = [
        ("def/group/1", b"[" * 2000 + b"]" * 2000, "payload_too_deep"),
        ("def/channel/1", b'{"attr": "rssi:\xc2\xb2", "period_s": 2}', "unknown_attribute"),
        ("def/channel/1", b"null", "wrong_type"),
        ("def/group/1", b"x" * 50_000, "payload_too_large"),
    ]
    ep = free_tcp_endpoint()
    gw = open_session(SessionSettings(listen=(ep,)))
    dev = open_session(SessionSettings(connect=(ep,)))
    errors: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
    loop = asyncio.get_running_loop()
    sub = dev.declare_subscriber(
        "aware/hbn/errors",
        lambda s: loop.call_soon_threadsafe(errors.put_nowait, json.loads(s.payload.to_bytes())),
    )
    try:
        async with EmbeddedBroker() as broker:
            svc = GatewayService(
                [0],
                settings=GatewaySettings(state_dir=tmp_path),
                mqtt=MqttSettings.from_url(broker.url),
                zenoh_session=gw,
            )
            svc.bind(lambda n, i: None, lambda: 0.0)
            async with svc:
                assert svc.mqtt is not None
                await asyncio.wait_for(svc.mqtt.connected.wait(), 10)
                svc.handle("def/group/1", GROUP)
                before = svc.bridge.definitions()
                # Zenoh: put until routes are up (the first error arrives), then the rest.
                async with asyncio.timeout(15):
                    while errors.empty():
                        dev.put("aware/hbn/" + hostile[0][0], hostile[0][1])
                        await asyncio.sleep(0.1)
                while not errors.empty():
                    errors.get_nowait()
                for rel, p, _ in hostile:
                    dev.put("aware/hbn/" + rel, p)
                got = [await asyncio.wait_for(errors.get(), 10) for _ in hostile]
                assert [e["code"] for e in got] == [c for *_, c in hostile]
                # MQTT: the same payloads, the same codes on aware/errors.
                async with aiomqtt.Client(
                    broker.host, broker.port, username=broker.username,
                    password=broker.password, identifier="hostile",
                ) as c:  # fmt: skip
                    await c.subscribe("aware/errors", qos=1)
                    for rel, p, _ in hostile:
                        await c.publish("aware/" + rel, p, qos=1)
                    codes = []
                    async with asyncio.timeout(10):
                        async for m in c.messages:
                            if m.topic.matches("aware/errors"):
                                codes.append(json.loads(bytes(m.payload))["code"])  # type: ignore[arg-type]
                                if len(codes) == len(hostile):
                                    break
                assert codes == [c for *_, c in hostile]
                assert svc.bridge.definitions() == before
                st_ = svc.stats()["bridge"]["refused_by_code"]
                assert st_["payload_too_deep"] >= 2 and st_["wrong_type"] == 2
    finally:
        sub.undeclare()  # type: ignore[no-untyped-call]
        dev.close()  # type: ignore[no-untyped-call]
        gw.close()  # type: ignore[no-untyped-call]


# --------------------------------------------------------------------------- embedded broker


async def test_broker_refuses_anonymous_unless_asked(tmp_path: Path) -> None:
    async with EmbeddedBroker(state_dir=tmp_path / "b") as b:
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client(b.host, b.port, identifier="anon"):
                pass
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client(b.host, b.port, username=b.username, password="wrong"):
                pass
        async with aiomqtt.Client(b.host, b.port, username=b.username, password=b.password):
            pass
        account = tmp_path / "b" / "mqtt-account"
        assert stat.S_IMODE(account.stat().st_mode) == 0o600
        assert account.read_text().strip() == f"{b.username}:{b.password}"
        assert b.password not in b.public_url and mask_url(b.url) == b.public_url
    async with (
        EmbeddedBroker(anonymous=True) as b,
        aiomqtt.Client(b.host, b.port, identifier="anon"),
    ):
        pass


async def test_broker_refuses_oversize_and_bounds_retained(tmp_path: Path) -> None:
    async with EmbeddedBroker(limits=BrokerLimits(max_retained=3)) as b:
        kw: dict[str, Any] = {"username": b.username, "password": b.password}
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client(b.host, b.port, identifier="big", timeout=1, **kw) as c:
                await c.publish("aware/def/group/1", b"x" * 1_000_000, qos=1, retain=True)
        assert b.stats.oversize == 1 and b.stats.retained == 0
        async with aiomqtt.Client(b.host, b.port, identifier="many", **kw) as c:
            for i in range(10):
                await c.publish(f"t/{i}", b"v", qos=1, retain=True)
        assert b.stats.retained == 3 and b.stats.retained_refused == 7


async def _until(check: Any, timeout: float = 10.0) -> None:
    async with asyncio.timeout(timeout):
        while not check():
            await asyncio.sleep(0.05)  # amqtt gives no event for a queued or expired session


async def test_broker_drops_the_queue_of_a_client_away_past_the_session_expiry() -> None:
    """amqtt has no bound on a persistent client's offline queue: the session expiry
    bounds how long it lives (default one hour)."""
    async with EmbeddedBroker(anonymous=True) as b:
        assert b._broker is not None and b._broker.config.session_expiry_interval == 3600
    # (amqtt drops the sessions of anonymous clients at once: an account here)
    async with EmbeddedBroker(limits=BrokerLimits(session_expiry_s=3)) as b:
        kw: dict[str, Any] = {"username": b.username, "password": b.password}
        async with aiomqtt.Client(
            b.host, b.port, identifier="away", clean_session=False, **kw
        ) as c:
            await c.subscribe("aware/data/#", qos=1)
        assert b.queued_for("away") == 0
        async with aiomqtt.Client(b.host, b.port, identifier="pub", **kw) as p:
            await p.publish("aware/data/1/1/1", b"{}", qos=1)
        await _until(lambda: b.queued_for("away") == 1, timeout=2.5)  # before the expiry
        await _until(lambda: b.queued_for("away") is None)  # expired: the queue is gone
    with pytest.raises(ValueError, match="session_expiry_s >= 1"):
        BrokerLimits(session_expiry_s=0)


def _gateway(state: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "awaremw", "gateway", "grid_small", "--state-dir", str(state),
         "--no-hbn", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _wait_ready(p: subprocess.Popen[str]) -> tuple[int, list[str]]:
    """Lines until the gateway says it is up; the broker port it printed."""
    assert p.stdout is not None
    lines: list[str] = []
    for line in p.stdout:
        lines.append(line)
        if line.startswith("awaremw gateway: motes"):
            m = re.search(r"embedded MQTT broker: mqtt://127\.0\.0\.1:(\d+)", "".join(lines))
            assert m, lines
            return int(m.group(1)), lines
    raise AssertionError(f"gateway did not start: {lines} {p.stderr.read() if p.stderr else ''}")


def _stop(p: subprocess.Popen[str]) -> None:
    p.send_signal(signal.SIGINT)
    assert p.wait(timeout=20) == 0, p.stderr.read() if p.stderr else ""


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


@pytest.mark.slow
async def test_gateway_restart_keeps_port_account_and_retained_definitions(
    tmp_path: Path,
) -> None:
    p = _gateway(tmp_path)
    try:
        port, lines = await asyncio.to_thread(_wait_ready, p)
        assert any("generated password" in ln for ln in lines)
        user, _, password = (
            (tmp_path / "broker" / "mqtt-account").read_text().strip().partition(":")
        )
        assert not any(password in ln for ln in lines if "generated password" not in ln)
        async with aiomqtt.Client("127.0.0.1", port, username=user, password=password) as c:
            await c.publish("aware/def/group/1", GROUP, qos=1, retain=True)
    finally:
        _stop(p)
    p = _gateway(tmp_path)
    try:
        port2, lines = await asyncio.to_thread(_wait_ready, p)
        assert port2 == port
        assert not any(password in ln for ln in lines)  # printed once only
        async with aiomqtt.Client("127.0.0.1", port, username=user, password=password) as c:
            await c.subscribe("aware/def/#", qos=1)
            async with asyncio.timeout(10):
                async for m in c.messages:
                    # Kept, as the gateway holds it: canonical, with its version.
                    assert (m.topic.value, m.retain) == ("aware/def/group/1", True)
                    assert isinstance(m.payload, bytes)
                    assert json.loads(m.payload) == {
                        **json.loads(GROUP),
                        "conditions": [{"attr": "temperature", "op": ">", "value": 45.0}],
                        "hysteresis": 0.0,
                        "version": 1,
                    }
                    break
    finally:
        _stop(p)


@pytest.mark.slow
async def test_gateway_memory_stays_bounded_under_oversize_and_long_topics(
    tmp_path: Path,
) -> None:
    p = _gateway(tmp_path, "--mqtt-port", "0")
    try:
        port, _ = await asyncio.to_thread(_wait_ready, p)
        user, _, password = (
            (tmp_path / "broker" / "mqtt-account").read_text().strip().partition(":")
        )
        kw: dict[str, Any] = {"username": user, "password": password}
        rss0 = _rss_kb(p.pid)
        for i in range(20):  # 20 retained messages of 10 MB: used to take 225 MB
            with pytest.raises(aiomqtt.MqttError):
                async with aiomqtt.Client(
                    "127.0.0.1", port, identifier=f"big{i}", timeout=1, **kw
                ) as c:
                    await c.publish(
                        f"aware/def/group/{i}", os.urandom(10_000_000), qos=1, retain=True
                    )
        async with aiomqtt.Client("127.0.0.1", port, identifier="topics", **kw) as c:
            for i in range(1000):  # 1,000 topics of 60 KB: used to take 126 MB
                await c.publish(f"aware/def/group/{i}/" + "t" * 60_000, b"{}", qos=1)
            await c.subscribe("aware/gateway/stats", qos=1)
        rss1 = _rss_kb(p.pid)
        assert p.poll() is None
        print(f"gateway RSS {rss0} kB -> {rss1} kB")
        assert rss1 - rss0 < 40_000, (rss0, rss1)  # KB
    finally:
        _stop(p)
