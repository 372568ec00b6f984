"""The gateway's own publications on their way back to it (sans-IO).

The gateway retains every definition on MQTT on topics it also subscribes to
(docs/gateway.md, "One truth"), so the broker forwards each of its
publications back to it, live, once. Heard back, a publication is an *echo*:
taken for a client's message it could replace a client's waiting definition
in the inbox, or, as a clearing (an empty payload), delete what a client
defined since. :class:`Echoes` remembers what was sent and not heard back yet
and recognises each once, so that a client's equal payload after it (a
deletion after our clearing) is the client's.

A publication not heard back within ``ttl`` of its sending, and of the last
connect (a persistent session delivers then what was queued), never will be:
lost with a broken link, or refused by the broker. It is forgotten. Bounded:
``per_topic`` records a topic, ``max_topics`` topics (the oldest dropped).
"""

from __future__ import annotations

from collections import deque

from awaremw.gateway.store import payload_hash

ECHOES_KEPT = 4  # publications per topic awaited back at once
MAX_ECHO_TOPICS = 4096  # topics with a publication awaited back
ECHO_TTL_S = 60.0


class Echoes:
    """What was sent on each topic and not heard back yet; the clock comes in as ``now``."""

    def __init__(
        self,
        ttl: float = ECHO_TTL_S,
        per_topic: int = ECHOES_KEPT,
        max_topics: int = MAX_ECHO_TOPICS,
    ) -> None:
        if ttl <= 0 or per_topic < 1 or max_topics < 1:
            raise ValueError("echoes need a positive ttl and room for one")
        self.ttl = ttl
        self.per_topic = per_topic
        self.max_topics = max_topics
        self._sent: dict[str, deque[tuple[str, float]]] = {}  # in send order
        self._connected_at = float("-inf")

    def __len__(self) -> int:
        return sum(len(d) for d in self._sent.values())

    def connected(self, now: float) -> None:
        """A (re)connect: what was sent before may come back from now on."""
        self._connected_at = now

    def sent(self, topic: str, payload: bytes, now: float) -> None:
        """``payload`` goes to the broker on ``topic`` now."""
        seen = self._sent.pop(topic, None)  # re-inserted: the dict stays in send order
        if seen is None:
            if len(self._sent) >= self.max_topics:
                del self._sent[next(iter(self._sent))]
            seen = deque(maxlen=self.per_topic)
        seen.append((payload_hash(payload), now))
        self._sent[topic] = seen

    def heard(self, topic: str, payload: bytes, now: float) -> bool:
        """Whether a live ``payload`` on ``topic`` is one sent and not heard back yet;
        if so it is heard now (once)."""
        seen = self._sent.get(topic)
        if seen is None:
            return False
        stale = now - self.ttl
        if self._connected_at < stale:
            while seen and seen[0][1] < stale:  # the oldest first
                seen.popleft()
        d = payload_hash(payload)
        found = next((e for e in seen if e[0] == d), None)
        if found is not None:
            seen.remove(found)
        if not seen:
            del self._sent[topic]
        return found is not None
