"""What the IP side sent, held until the gateway handles it (sans-IO).

A burst of definitions is mostly a burst of *superseded* definitions: only the
newest value of each ``def/...`` topic matters, so the inbox keeps one entry
per definition topic and a newer payload replaces the pending one in place
(``coalesced``). Commands are not values but events: each is kept, in order.
Entries leave in arrival order (a definition at the place of its first pending
copy), so a command still follows the definition of the group type it targets.

Both are bounded: at most ``max_definitions`` distinct definition topics and
``max_commands`` commands wait at once. What does not fit is refused by
:meth:`Inbox.put`, counted in ``dropped``, and returned to the caller, which
reports it on the errors topic of its transport (:func:`overflow_report`):
nothing is dropped silently. An invalid definition is never replaced (see
:class:`Inbox`): it is refused with its code in its turn, even when a good one
followed it at once. Nor is a client's definition replaced by a *copy* (a
definition with its ``version``, as the gateway republishes it: docs/gateway.md,
One truth): a copy heard after a client's newer definition is the gateway's own
older republication, and taking its place would lose what the client said last.

A transport takes every message it is handed (aiomqtt's own queue would
discard, and log a line per message, when the gateway lags), so a burst costs
one dictionary entry per topic, not a queue slot per message.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from awaremw.gateway.bridge import MAX_ERROR_TOPIC, clip
from awaremw.gateway.events import ErrorReport

MAX_DEFINITIONS = 4096  # distinct definition topics waiting (the contract's ids are u16)
MAX_COMMANDS = 1_000  # commands waiting
MAX_VERDICTS = 4096  # remembered (topic, payload, size) -> valid: a burst repeats payloads
OVERFLOW = "input_overflow"  # error code of a message the gateway could not take


@dataclass(frozen=True, slots=True)
class Incoming:
    """One message from the IP side: ``rel`` relative to the prefix (``def/channel/3``),
    ``topic`` as the sender saw it; ``size`` as sent when the payload was not copied."""

    rel: str
    payload: bytes
    topic: str
    retained: bool = False
    size: int | None = None

    @property
    def is_definition(self) -> bool:
        return self.rel.startswith("def/")


@dataclass(slots=True)
class InboxStats:
    taken: int = 0  # messages accepted into the inbox
    coalesced: int = 0  # definitions replaced by a newer one before they were handled
    copies: int = 0  # copies (with a version) not taken over a client's waiting definition
    dropped: int = 0  # messages refused because the inbox was full (reported)
    handed: int = 0  # entries handed to the gateway
    peak: int = 0  # most entries waiting at once

    def as_dict(self) -> dict[str, int]:
        return {k: getattr(self, k) for k in self.__slots__}


class Inbox:
    """Latest value per definition topic, commands in order; both bounded.

    ``valid(m)`` (pure; optional) says whether a definition is valid on its own. A
    waiting definition that is *invalid* is not replaced by a newer one: it keeps
    its place, to be refused with its code when its turn comes, and the newer one
    waits behind it (counted with the commands: events, not values).
    ``is_copy(m)`` (pure; optional) says whether a definition is a copy with its
    version: one is not taken over a waiting definition that is not (``copies``).
    """

    def __init__(
        self,
        max_definitions: int = MAX_DEFINITIONS,
        max_commands: int = MAX_COMMANDS,
        valid: Callable[[Incoming], bool] | None = None,
        is_copy: Callable[[Incoming], bool] | None = None,
    ) -> None:
        if max_definitions < 1 or max_commands < 1:
            raise ValueError("an inbox holds at least one definition and one command")
        self.max_definitions = max_definitions
        self.max_commands = max_commands
        self.valid = valid
        self.is_copy = is_copy
        self._verdicts: dict[tuple[str, bytes, int | None], bool] = {}  # MAX_VERDICTS
        self.stats = InboxStats()
        # Arrival number -> message, in order; definition topic -> the number of
        # its newest waiting value (which a newer one replaces in place).
        self._entries: OrderedDict[int, Incoming] = OrderedDict()
        self._latest: dict[str, int] = {}
        self._seq = 0

    def __len__(self) -> int:
        return len(self._entries)

    def put(self, m: Incoming) -> Incoming | None:
        """Take ``m``: None; or refuse it (full): ``m`` itself, for the caller to
        count and report."""
        if m.is_definition:
            at = self._latest.get(m.topic)
            if at is not None:
                old = self._entries[at]
                if self.is_copy is not None and self.is_copy(m) and not self.is_copy(old):
                    self.stats.copies += 1  # the client's definition stays
                    self.stats.taken += 1
                    return None
                if self._valid(old):
                    self._entries[at] = m  # the newest wins, at the older one's place
                    self.stats.coalesced += 1
                    self.stats.taken += 1
                    return None
                if self._events() >= self.max_commands:
                    self.stats.dropped += 1
                    return m
                del self._latest[m.topic]  # the invalid one stays, as an event
            elif len(self._latest) >= self.max_definitions:
                self.stats.dropped += 1
                return m
            self._seq += 1
            self._entries[self._seq] = m
            self._latest[m.topic] = self._seq
        else:
            if self._events() >= self.max_commands:
                self.stats.dropped += 1
                return m
            self._seq += 1
            self._entries[self._seq] = m
        self.stats.taken += 1
        self.stats.peak = max(self.stats.peak, len(self._entries))
        return None

    def _valid(self, m: Incoming) -> bool:
        """``valid(m)``, remembered: a burst mostly repeats a few payloads per topic."""
        if self.valid is None:
            return True
        key = (m.topic, m.payload, m.size)  # an oversize put arrives empty, with its size
        verdict = self._verdicts.get(key)
        if verdict is None:
            if len(self._verdicts) >= MAX_VERDICTS:
                self._verdicts.clear()
            verdict = self._verdicts[key] = self.valid(m)
        return verdict

    def _events(self) -> int:
        """Waiting entries that are not a topic's newest value (commands, invalid ones)."""
        return len(self._entries) - len(self._latest)

    def pop(self) -> Incoming | None:
        """The oldest waiting entry, or None."""
        if not self._entries:
            return None
        seq, m = self._entries.popitem(last=False)
        if self._latest.get(m.topic) == seq:
            del self._latest[m.topic]
        self.stats.handed += 1
        return m


def overflow_report(m: Incoming, what: str, *, refetched: bool) -> ErrorReport:
    """The errors-topic report of a message the gateway could not take; ``refetched``:
    a definition the transport will read again (the broker's retained value)."""
    if not m.is_definition:
        hint = "send the command again"
    elif refetched:
        hint = "the broker's retained value is read again after the burst"
    else:
        hint = "put it again"
    text = m.payload[:128].decode("utf-8", errors="replace")
    return ErrorReport(
        clip(m.topic, MAX_ERROR_TOPIC), OVERFLOW, f"not taken: {what} full; {hint}", text
    )
