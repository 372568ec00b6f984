"""Tracking at scale: a group follows a robot across 1,024 motes.

Runs ``nodes/large.toml``: a 32 x 32 grid of tmote sky motes
(CC2420, 12 m apart), the gateway's mote in the middle, a robot driving a loop
through the field while its mote beacons; group type 1 is "hears the robot
above -90 dBm", with an AVG temperature channel (2 s) and a COUNT channel
(4 s) on it. The metrics are romeo4r's (:mod:`awaremw.experiments.romeo4r`,
docs/experiments.md) over the 1,024 sensing motes; figures
``large_snapshots.png`` (panels of 108 x 108 m around the robot: the whole
field would show the group as a speck) and ``large_membership.png``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from awaremw.experiments.metrics import RunResult
from awaremw.experiments.romeo4r import analyse_tracking

IDEAL_IDS = 1  # one group id follows the robot
WINDOW_M = 54.0  # snapshot panels: 108 m squares around the robot (about 80 motes)


def analyse(result: RunResult, out: Path) -> dict[str, Any]:
    """Metrics and figures of a finished run; writes them into ``out``."""
    return analyse_tracking(
        result, out, "large", "Group tracking the robot in a field of 1,024 motes", WINDOW_M
    )
