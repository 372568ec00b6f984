"""Tracking at scale: a group follows a robot across 1,024 motes.

Runs ``awaremw/deployments/large.toml``: a 32 x 32 grid of tmote sky motes
(CC2420, 12 m apart), the gateway's mote in the middle, a robot driving a loop
through the field while its mote beacons; group type 1 is "hears the robot
above -90 dBm", with an AVG temperature channel (2 s) and a COUNT channel
(4 s) on it. The metrics are romeo4r's (:mod:`awaremw.experiments.romeo4r`,
docs/experiments.md) over the 1,024 sensing motes; figures
``large_snapshots.png`` and ``large_membership.png``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from awaremw.experiments.metrics import RunResult
from awaremw.experiments.romeo4r import analyse_tracking

IDEAL_IDS = 1  # one group id follows the robot


def analyse(result: RunResult, out: Path) -> dict[str, Any]:
    """Metrics and figures of a finished run; writes them into ``out``."""
    return analyse_tracking(result, out, "large", "Group tracking the robot over 1,024 motes")
