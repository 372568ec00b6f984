"""Retained group states a gateway finds on its broker when it starts.

``<prefix>/groups/<type>/<id>`` is retained (docs/gateway.md); a gateway that
stopped, or a run of another network on the same broker, leaves states of
groups this network does not have. At start the gateway reads them (one short
session of its own account) and sorts them with :func:`sort_leftovers`: a state
whose leader is not a mote of this network is cleared at once; the others are
cleared when the network has not reported their group within the bridge's
expiry (cli/gateway.py).

Reading the retained states is synchronised, not timed: after the
subscription to ``groups/+/+``, a second SUBSCRIBE (to a topic that holds no
retained message) is acknowledged only after the broker has sent the retained
messages of the first, and the client handles packets in order; so when its
SUBACK is in, every retained state is in the client's queue.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import secrets
from dataclasses import dataclass

from awaremw.gateway.mqtt import MqttSettings

MAX_LEFTOVERS = 4096  # retained group states read at start (the bridge's MAX_GROUPS)


@dataclass(frozen=True, slots=True)
class Leftovers:
    foreign: tuple[str, ...]  # relative topics whose leader is not in this network
    kept: tuple[str, ...]  # relative topics of groups this network may still have


def sort_leftovers(states: dict[str, bytes], motes: set[int]) -> Leftovers:
    """Sort retained group states (relative topic -> payload) by their leader."""
    foreign: list[str] = []
    kept: list[str] = []
    for rel, payload in sorted(states.items()):
        leader: object = None
        with contextlib.suppress(ValueError, AttributeError):
            leader = json.loads(payload).get("leader")
        # A merge notice has no leader: its group is gone already.
        (kept if isinstance(leader, int) and leader in motes else foreign).append(rel)
    return Leftovers(tuple(foreign), tuple(kept))


async def retained_groups(settings: MqttSettings, timeout_s: float = 5.0) -> dict[str, bytes]:
    """The retained group states on the broker (relative topic -> payload), at most
    :data:`MAX_LEFTOVERS`. Raises :class:`aiomqtt.MqttError` or TimeoutError."""
    s = settings
    nonce = secrets.token_hex(6)
    plen = len(s.prefix) + 1
    out: dict[str, bytes] = {}
    async with (
        asyncio.timeout(timeout_s),
        s.client(
            f"{s.client_id}-leftovers-{nonce}",
            clean_session=True,
            timeout=timeout_s,
            max_queued_incoming_messages=MAX_LEFTOVERS + 16,
        ) as client,
    ):
        await client.subscribe(s.topic("groups/+/+"), qos=0)
        await client.subscribe(s.topic(f"gateway/sync/{nonce}"), qos=0)  # the barrier
        for _ in range(len(client.messages)):
            m = await anext(client.messages)
            payload = m.payload if isinstance(m.payload, bytes) else b""
            if m.retain and payload and len(out) < MAX_LEFTOVERS:
                out[m.topic.value[plen:]] = payload
    return out
