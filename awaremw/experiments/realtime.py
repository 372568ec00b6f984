"""Run a scenario in real time: the fleet over Zenoh, the gateway, MQTT.

Placeholder until the fleet runtime lands; see :func:`run_realtime`.
"""

from __future__ import annotations

from awaremw.experiments.scenario import Scenario
from awaremw.experiments.virtual import RunResult


def run_realtime(
    sc: Scenario,
    speed: float = 1.0,
    duration: float | None = None,
    mqtt: str | None = None,
    plain: bool = True,
) -> RunResult:
    raise NotImplementedError("the real-time experiment needs the fleet runtime; use --virtual")
