"""What the gateway's logic answers with: typed actions, and the transports.

:class:`~awaremw.gateway.bridge.GatewayBridge` answers every input with a list
of :data:`Action` (its module docstring says which); the service carries them
out, matching on the union (``case _: assert_never(action)``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from enum import Enum
from typing import TypeAlias

from awaremw.protocol.frames import ItemBody, ItemKind


class Transport(Enum):
    """Where a payload came from, so where its refusal goes."""

    MQTT = "mqtt"  # <prefix>/errors
    HBN = "hbn"  # <prefix>/hbn/errors
    LOCAL = "local"  # the deployment's own definitions, a direct call: no errors topic


@dataclass(frozen=True, slots=True)
class Publish:
    """A message for the IP side; ``topic`` is relative to the prefix."""

    topic: str
    payload: bytes  # b"" with retain=True clears a retained topic
    retain: bool = False
    qos: int = 1


@dataclass(frozen=True, slots=True)
class Inject:
    """A versioned item to inject into gateway mote ``node`` (None: every one)."""

    kind: ItemKind
    item_id: int
    version: int
    body: ItemBody | None
    node: int | None = None


@dataclass(frozen=True, slots=True)
class ErrorReport:
    """A refusal (or, with ``warning``, a note on an accepted payload): the JSON
    document of an errors topic."""

    topic: str  # the full topic / key expression the payload arrived on
    code: str
    error: str
    payload: str
    warning: bool = False  # the payload was accepted; "level": "warning" on the wire

    def to_json(self) -> bytes:
        doc = {"topic": self.topic, "error": self.error, "code": self.code, "payload": self.payload}
        if self.warning:
            doc["level"] = "warning"
        return json.dumps(doc).encode()


@dataclass(frozen=True, slots=True)
class Report:
    """``error`` for the errors topic of the transport ``via``."""

    error: ErrorReport
    via: Transport


@dataclass(frozen=True, slots=True)
class StateChanged:
    """Definitions or groups changed (what the Zenoh queryable answers)."""


Action: TypeAlias = Publish | Inject | Report | StateChanged


@dataclass(frozen=True, slots=True)
class Outcome:
    """What one payload from the IP side led to: the actions, in order."""

    actions: tuple[Action, ...] = ()
    replay: bool = False  # a retained payload already handled: ignored

    @property
    def inject(self) -> Inject | None:
        return next((a for a in self.actions if isinstance(a, Inject)), None)

    @property
    def error(self) -> ErrorReport | None:
        """A refusal, or a warning on what :attr:`inject` carries."""
        return next((a.error for a in self.actions if isinstance(a, Report)), None)

    @property
    def accepted(self) -> bool:
        return self.inject is not None
