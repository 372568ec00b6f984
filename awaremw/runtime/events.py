"""The events the runtime itself reports about a mote, beside its core's own
events, through every driver's ``on_event(node_id, event, now)`` hook: the
asyncio driver (:mod:`awaremw.runtime.driver`) and the virtual-clock network
(:mod:`awaremw.runtime.virtual`) emit the same types. Consumers dispatch on the
type (``match event: case MoteDown(reason=r): ...``), never on class names.

:data:`MoteEvent` is everything such a hook is given: a core's events
(:data:`~awaremw.protocol.events.CoreEvent`) and these."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeAlias

from awaremw.protocol.events import CoreEvent


@dataclass(frozen=True, slots=True)
class MoteUp:
    """The mote booted and is on the air."""


@dataclass(frozen=True, slots=True)
class MoteDown:
    """The mote was switched off: ``killed`` (by a user or a scenario),
    ``battery`` (its budget ran out), ``stopped`` (its fleet closed) or
    ``fault`` (a contained core bug)."""

    reason: str


RuntimeEvent: TypeAlias = MoteUp | MoteDown
MoteEvent: TypeAlias = CoreEvent | RuntimeEvent
EventHook: TypeAlias = Callable[[int, MoteEvent, float], None]  # (node id, event, now)
