"""Section V of the paper: a group tracks the Romeo 4R robot.

Runs ``nodes/romeo4r.toml`` (virtual clock, or the real-time fleet over Zenoh
with the gateway and an MQTT subscriber), then scores the tracking group
against the ground truth and draws the paper's figures:

* ``romeo4r_snapshots.png`` -- the group following the robot (Fig. 8);
* ``romeo4r_rssi.png`` -- RSSI of the robot's beacons at motes 1, 4 and 17
  against the membership threshold (Fig. 9);
* ``romeo4r_membership.png`` -- group size against the true member count;
* ``metrics.json`` -- the figures of docs/experiments.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from awaremw.experiments import metrics as M
from awaremw.experiments import plots
from awaremw.experiments.metrics import RunResult
from awaremw.experiments.scenario import Scenario
from awaremw.protocol.attributes import is_rssi
from awaremw.protocol.frames import Op

IDEAL_IDS = 1  # one group id for the whole pass (summary of --seeds)


def threshold_of(sc: Scenario) -> tuple[float, float]:
    """(threshold, hysteresis) of the tracking group's RSSI condition."""
    defn = sc.group_def()
    for c in defn.conditions:
        if is_rssi(c.attr) and c.op in (Op.GT, Op.GE):
            return c.value, defn.hysteresis
    raise ValueError(f"{sc.name}: the tracking group has no 'rssi:<robot> >' condition")


def analyse(result: RunResult, out: Path) -> dict[str, Any]:
    """Metrics and figures of a finished run; writes them into ``out``."""
    return analyse_tracking(result, out, "romeo4r", "Group tracking Romeo 4R")


def analyse_tracking(
    result: RunResult, out: Path, prefix: str, title: str, window_m: float | None = None
) -> dict[str, Any]:
    """The robot-tracking metrics of any scenario with a robot and an
    ``rssi:<robot> >`` group; figures named ``<prefix>_*.png``; ``window_m``: the
    snapshot panels show the square of that half-side around the robot."""
    if result.scenario.robot is None:
        raise ValueError(f"{result.scenario.name}: no robot in the deployment")
    # The pass: while the ground truth has members (the robot is sensed).
    a = M.scored(result, through_last_sensed=True)
    out.mkdir(parents=True, exist_ok=True)
    metrics = a.metrics()
    metrics["pass_s"] = [a.t0, a.t1]
    metrics["robot_entry_s"] = a.t0
    _figures(a.sc, a.rec, a.truth, a.series, out, a.settle, prefix, title, result.duration,
             window_m)  # fmt: skip
    return M.rounded(metrics)


def _figures(
    sc: Scenario,
    rec: M.Recorder,
    truth: Any,
    series: list[M.Instant],
    out: Path,
    settle: float,
    prefix: str,
    title: str,
    duration: float,
    window_m: float | None,
) -> None:
    gtype = sc.tracking_group
    defn = sc.group_def()
    robot = sc.robot
    assert robot is not None
    # The scenario's instants that the run reached; else four over the pass.
    snaps = [float(t) for t in sc.get("snapshots_s", []) if float(t) <= duration]
    if not snaps:
        a = series[0].t if series else 0.0
        b = series[-1].t if series else duration
        snaps = [a + (b - a) * i / 3 for i in range(4)] if b > a else [b]
    plots.tracking_snapshots(
        out / f"{prefix}_snapshots.png", rec, truth, gtype, defn, snaps, sc.sensors, robot,
        sc.field, settle=0.0,
        title=f"{title} (colour: group id; star: leader; ring: true member)",
        window_m=window_m,
    )  # fmt: skip
    thr, hyst = threshold_of(sc)
    motes = [int(m) for m in sc.get("rssi_motes", [])]
    if motes:
        plots.rssi_traces(
            out / f"{prefix}_rssi.png", rec, truth, robot, motes, thr, hyst, gtype,
            max(0.0, series[0].t - 10), min(series[-1].t + 15, sc.duration),
        )  # fmt: skip
    plots.membership_sizes(
        out / f"{prefix}_membership.png", series,
        title=f"Tracking group size vs truth (members compared {settle:g} s later)",
    )  # fmt: skip
