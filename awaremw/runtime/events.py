"""The events the runtime itself reports about a mote, beside its core's own
events, through every driver's ``on_event(node_id, event, now)`` hook: the
asyncio driver (:mod:`awaremw.runtime.driver`) and the virtual-clock network
(:mod:`awaremw.runtime.virtual`) emit the same types. Consumers dispatch on the
type (``match event: case MoteDown(reason=r): ...``), never on class names."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class MoteUp:
    """The mote booted and is on the air."""


@dataclass(frozen=True, slots=True)
class MoteDown:
    """The mote was switched off: ``killed`` (by a user or a scenario),
    ``battery`` (its budget ran out), ``stopped`` (its fleet closed) or
    ``fault`` (a contained core bug)."""

    reason: str


MoteEvent = MoteUp | MoteDown
