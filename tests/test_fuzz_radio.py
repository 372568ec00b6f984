"""Fuzzing the radio of a running system: ``awaremw fleet`` + ``awaremw gateway``
(as separate processes) + Mosquitto.

A Zenoh client session captures real envelopes from the radio keys and puts
thousands of mutated copies back (extreme field values, wrong types,
truncations, deep nesting, mutated frames, Drip items at extreme versions for
the channel in use; :mod:`awaremw.radio.fuzz`). Then every process must be
alive, records keep arriving on MQTT, and a channel definition changed after
the attack reaches the motes (records show its period), the attacked channel
included. The rejections are visible in ``fleet-ctl stats``.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import pytest
import zenoh
from mosquitto import Mosquitto, MosquittoSub, mosquitto_fixture, pub, require  # noqa: F401
from test_gateway_e2e import channel, is_period, records

from awaremw.cli.fleet import control_query
from awaremw.radio.fuzz import mutants
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)

pytestmark = [pytest.mark.zenoh, pytest.mark.mosquitto, pytest.mark.slow]

SPEED = 4.0
N_MUTANTS = 3000
# A record may come this many emulated seconds after its epoch ended: at 4x on a
# loaded 2-core machine a second of wall time is 4 emulated seconds (epoch numbers
# of the two periods differ by far more: 1.0 s epochs at t = 250 s are near 250).
LATE = 4.0
GROUP = json.dumps({"conditions": [{"attr": "x", "op": ">", "value": 3}]})


@asynccontextmanager
async def process(*args: str) -> AsyncIterator[asyncio.subprocess.Process]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    p = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "awaremw", *args,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL, env=env,
    )  # fmt: skip
    try:
        yield p
    finally:
        if p.returncode is None:
            p.terminate()
            await p.wait()


class Capture:
    """Envelopes heard on the radio keys (bounded), copied on Zenoh's thread."""

    def __init__(self, limit: int = 400) -> None:
        self.limit = limit
        self.got: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            if len(self.got) < self.limit:
                self.got.append((str(sample.key_expr), sample.payload.to_bytes()))


async def until(cond: Any, timeout: float) -> None:
    async def poll() -> None:
        while not cond():
            await asyncio.sleep(0.05)

    await asyncio.wait_for(poll(), timeout)


@pytest.mark.parametrize("seed", [9, 1, 2])  # three different attacks
async def test_fuzzed_radio_leaves_fleet_and_gateway_alive(mosquitto: Mosquitto, seed: int) -> None:
    require("mosquitto_sub")
    ep = free_tcp_endpoint()
    common = ["--speed", str(SPEED)]
    async with (
        process("fleet", "grid_small", "--listen", ep, "--without-kind", "gateway", "--plain",
                *common) as fleet,
        MosquittoSub(mosquitto, "viewer", "aware/#") as sub,
        process("gateway", "grid_small", "--connect", ep, "--mqtt", mosquitto.url("gateway"),
                *common) as gw,
    ):  # fmt: skip
        await sub.wait_for(lambda ls: ("aware/gateway/status", "online") in ls, 40)
        pub(mosquitto, "operator", "aware/def/group/1", GROUP)
        pub(mosquitto, "operator", "aware/def/channel/1", channel(1.0))
        await sub.wait_for(lambda ls: len(records(ls, 1)) >= 2, 40)

        session = open_session(SessionSettings("client", (ep,)))
        try:
            cap = Capture()
            subscriber = session.declare_subscriber("aware/radio/**", cap)
            await until(lambda: len(cap.got) >= cap.limit, 30)
            subscriber.undeclare()  # type: ignore[no-untyped-call]
            kinds: dict[str, int] = {}
            gen = mutants(cap.got, seed=seed)
            for i in range(N_MUTANTS):
                key, payload, what = next(gen)
                kinds[what] = kinds.get(what, 0) + 1
                session.put(key, payload)
                if i % 200 == 199:
                    await asyncio.sleep(0.05)  # pacing: let the loops breathe, not a sync
            assert len(kinds) >= 8, kinds
            stats = await asyncio.to_thread(control_query, [ep], "aware", {"op": "stats"}, 5.0)
        finally:
            close_quietly(session)

        assert fleet.returncode is None and gw.returncode is None
        # Both processes answer fleet-ctl stats: garbage counted per reason, no fault.
        snaps = {d["fleet"]: d["snapshot"] for d in stats}
        assert len(snaps) == 2, snaps.keys()
        for name, snap in snaps.items():
            rejected = snap["rejected"]
            assert sum(rejected.values()) >= N_MUTANTS // 4, (name, rejected)
            assert {"tx_power", "position", "time", "size", "msgpack"} <= rejected.keys()
            assert snap["faults"] == {}, (name, snap["faults"])

        # Records keep arriving after the attack ...
        n = len(sub.lines)
        await sub.wait_for(lambda ls: len(records(ls[n:], 1)) >= 2, 40)
        # ... and a changed definition of the attacked channel reaches the motes
        # (forged versions far from the held one are refused as jumps, near ones
        # are superseded by the gateway: docs/protocol-dissemination.md).
        pub(mosquitto, "operator", "aware/def/channel/1", channel(2.5))
        n = len(sub.lines)

        def changed(r: dict[str, Any]) -> bool:
            return is_period(r, 2.5, LATE) and not is_period(r, 1.0)

        await sub.wait_for(
            lambda ls: sum(1 for r in records(ls[n:], 1) if changed(r)) >= 3,
            60,
        )
