"""The Zenoh HBN API on real Zenoh sessions over loopback (no multicast scouting)."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator

import pytest
import zenoh
from inbox import Inbox

from awaremw.gateway.events import ErrorReport, Publish
from awaremw.gateway.hbn import HbnApi
from awaremw.runtime.zenoh_session import SessionSettings, free_tcp_endpoint, open_session

pytestmark = pytest.mark.zenoh


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """The gateway's session (listening on loopback) and an IP device's, linked directly."""
    ep = free_tcp_endpoint()
    gw = open_session(SessionSettings(listen=(ep,)))
    dev = open_session(SessionSettings(connect=(ep,)))
    try:
        yield gw, dev
    finally:
        dev.close()  # type: ignore[no-untyped-call]
        gw.close()  # type: ignore[no-untyped-call]


class ThreadSafeSamples:
    """Samples received on a Zenoh thread, waited for from the test thread."""

    def __init__(self) -> None:
        self.items: list[tuple[str, str, bytes]] = []
        self.cond = threading.Condition()

    def __call__(self, s: zenoh.Sample) -> None:
        if str(s.key_expr).startswith(("aware/hbn/def/", "aware/hbn/cmd/")):
            return  # the device's own puts
        with self.cond:
            self.items.append((str(s.key_expr), str(s.kind), s.payload.to_bytes()))
            self.cond.notify_all()

    async def wait(self, n: int, timeout: float = 10.0) -> list[tuple[str, str, bytes]]:
        def block() -> bool:
            with self.cond:
                return self.cond.wait_for(lambda: len(self.items) >= n, timeout)

        assert await asyncio.to_thread(block), self.items
        return self.items


async def got_all(got: ThreadSafeSamples) -> None:
    while sum(1 for i in got.items if i[2] != b"probe") < 4:
        await got.wait(len(got.items) + 1)


async def wait_routed(dev: zenoh.Session, key: str, timeout: float = 10.0) -> None:
    """Wait until a get on ``key`` reaches the gateway's queryable (routes are up)."""
    deadline = asyncio.get_running_loop().time() + timeout
    while asyncio.get_running_loop().time() < deadline:
        replies = await asyncio.to_thread(lambda: list(dev.get(key, timeout=1.0)))
        if any(r.ok is not None for r in replies):
            return
    raise AssertionError(f"no queryable answered on {key}")


async def test_definitions_in_state_out(sessions: tuple[zenoh.Session, zenoh.Session]) -> None:
    gw, dev = sessions
    inbox = Inbox()
    api = HbnApi(gw, inbox)
    api.start()
    try:
        api.set_state({"gateway/status": b"online"})
        await wait_routed(dev, "aware/hbn/gateway/status")
        got = ThreadSafeSamples()
        sub = dev.declare_subscriber("aware/hbn/**", got)
        dev.put("aware/hbn/def/group/1", b'{"conditions": []}')
        dev.delete("aware/hbn/def/channel/2")
        dev.put("aware/hbn/cmd/blink", b"{}")
        await inbox.wait(3)
        assert inbox.items == [
            ("def/group/1", b'{"conditions": []}', False, "aware/hbn/def/group/1"),
            ("def/channel/2", b"", False, "aware/hbn/def/channel/2"),
            ("cmd/blink", b"{}", False, "aware/hbn/cmd/blink"),
        ]
        # Wait until the device's subscription is known to the gateway: publish a
        # probe until it arrives, then the real messages.
        for _ in range(200):
            api.publish(Publish("data/0/0/1", b"probe"))
            try:
                await got.wait(1, timeout=0.05)
                break
            except AssertionError:
                continue
        api.publish(Publish("data/1/1/513", b'{"value": 2}'))
        api.publish(Publish("groups/1/513", b'{"leader": 3}', retain=True))
        api.publish(Publish("groups/1/513", b"", retain=True))
        api.publish_error(ErrorReport("aware/hbn/def/group/x", "bad", "why", "x"))
        await got.wait(4 + 1)
        await asyncio.wait_for(got_all(got), 10)
        items = [i for i in got.items if i[2] != b"probe"]
        assert [(k, kind) for k, kind, _ in items] == [
            ("aware/hbn/data/1/1/513", "SampleKind.PUT"),
            ("aware/hbn/groups/1/513", "SampleKind.PUT"),
            ("aware/hbn/groups/1/513", "SampleKind.DELETE"),
            ("aware/hbn/errors", "SampleKind.PUT"),
        ]
        sub.undeclare()  # type: ignore[no-untyped-call]

        api.set_state(
            {
                "def/group/1": b"{}",
                "def/channel/2": b"{}",
                "groups/1/513": b"{}",
                "gateway/status": b"online",
            }
        )

        def keys(sel: str) -> set[str]:
            return {str(r.ok.key_expr) for r in dev.get(sel, timeout=5.0) if r.ok is not None}

        assert await asyncio.to_thread(keys, "aware/hbn/def/**") == {
            "aware/hbn/def/group/1",
            "aware/hbn/def/channel/2",
        }
        assert await asyncio.to_thread(keys, "aware/hbn/groups/**") == {"aware/hbn/groups/1/513"}
        assert len(await asyncio.to_thread(keys, "aware/hbn/**")) == 4
    finally:
        api.close()
