"""Tracking at city scale: nine fires and a robot over 10,000 motes.

Runs ``city.toml``: a 100 x 100 grid of tmote sky motes (CC2420, 12 m apart),
nine gateway motes (one per district, all collection roots), a fire looping
around each district's centre at 1 m/s and a robot patrolling the middle
district. Group type 1 holds the motes over 50 degC (the fires), group type 2
the motes that hear the robot above -90 dBm; an AVG channel reports each
every 2 s.

Metrics: the common ones of :func:`awaremw.experiments.metrics.run_metrics`
for the fires' group type (membership F1 over all 10,000 sensing motes against
the ground truth), and per object (:mod:`awaremw.experiments.objects`: a
record belongs to the object nearest its leader): ``records_per_object``,
``ids_per_object`` (distinct group ids of its delivered records; ideally one),
``objects_tracked`` (objects with a delivered record produced in the last
stretch of the run: its last quarter, at least 10 s, before the 5 s records
may still be in flight), ``one_id_per_object`` and ``every_object_tracked``. Figure:
``city_field.png``, the whole field at the last snapshot with every group and
object.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from awaremw.experiments import metrics as M
from awaremw.experiments import objects as O
from awaremw.experiments.metrics import RunResult
from awaremw.world.mobility import square_loop

IDEAL_IDS = 9  # one group id per fire (group type 1)


def analyse(result: RunResult, out: Path) -> dict[str, Any]:
    """Metrics and figures of a finished run; writes them into ``out``."""
    a = M.scored(result)
    metrics = a.metrics()
    sc = result.scenario
    rec = result.recorder
    d = sc.deployment
    fires, robots = O.fires_of(sc.world), O.robots_of(d)
    mobility = {s.id: s.mobility() for s in d.nodes}
    robot_types = _robot_group_types(sc)
    per_type: dict[int, list[O.TrackedObject]] = {sc.tracking_group: fires}
    for t in robot_types:
        per_type[t] = robots
    until = result.duration - 5.0  # records produced later may still be in flight
    late = until - max(10.0, 0.25 * until)  # "still followed": a record in the last stretch
    scores: list[O.ObjectScore] = []
    for gtype, objs in per_type.items():
        records = {
            k: (t, mobility[r.leader].position(t) if r.leader in mobility else None,
                k in rec.arrivals)
            for k, (t, r) in rec.produced.items()
            if k[1] == gtype and t <= until
        }  # fmt: skip
        scores.append(O.score(objs, records, late))
    names = [o.name for objs in per_type.values() for o in objs]
    per = [n for s in scores for n in s.records]
    ids = [n for s in scores for n in s.ids]
    tracked = [b for s in scores for b in s.tracked]
    metrics |= {
        "objects": names,
        "objects_tracked": sum(tracked),
        "records_per_object": per,
        "ids_per_object": ids,
        "records_unattributed": sum(s.unattributed for s in scores),
        "one_id_per_object": all(n == 1 for n in ids),
        "every_object_tracked": all(tracked),
        "sinks": len(d.of_kind("gateway")),
    }
    out.mkdir(parents=True, exist_ok=True)
    _figure(out / "city_field.png", a, per_type, result.duration)
    return M.rounded(metrics)


def _robot_group_types(sc: Any) -> list[int]:
    """Group types other than the tracking one whose conditions hear a robot."""
    from awaremw.protocol.attributes import is_rssi

    out = []
    for t in sorted(sc.group_json):
        if t == sc.tracking_group:
            continue
        if any(is_rssi(c.attr) for c in sc.group_def(t).conditions):
            out.append(t)
    return out


def _figure(
    path: Path, a: M.Scored, per_type: dict[int, list[O.TrackedObject]], duration: float
) -> None:
    """The whole field at the end: every mote in a group coloured by group id,
    leaders as stars, each object's position as a cross."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure  # no pyplot: no global state, no display

    rec, sc = a.rec, a.sc
    t = max(0.0, duration - a.settle)
    pos = {s.id: s.position for s in sc.deployment.nodes}
    tab20 = colormaps["tab20"]
    fig = Figure(figsize=(7.5, 7.5), dpi=110)
    ax = fig.subplots()
    xs = [pos[n][0] for n in sc.sensors]
    ys = [pos[n][1] for n in sc.sensors]
    ax.scatter(xs, ys, s=0.3, color="0.8", linewidths=0)
    for gtype in per_type:
        for gid, members in rec.groups_at(gtype, t).items():
            colour = tab20(gid % 20)
            mx = [pos[n][0] for n in members if n in pos]
            my = [pos[n][1] for n in members if n in pos]
            ax.scatter(mx, my, s=6, color=colour, linewidths=0)
        for gid, leader in rec.leaders_at(gtype, t).items():
            if leader in pos:
                ax.scatter(*pos[leader], marker="*", s=60, color=tab20(gid % 20),
                           edgecolors="black", linewidths=0.4)  # fmt: skip
    for objs in per_type.values():
        for o in objs:
            at = o.where(t)
            if at is not None:
                ax.scatter(*at, marker="x", s=50, color="black", linewidths=1.2)
    for g in sc.deployment.of_kind("gateway"):
        ax.scatter(*g.position, marker="s", s=30, color="tab:blue")
    ax.set_aspect("equal")
    ax.set_title(f"city at t = {t:.0f} s: groups (colour), leaders (*), objects (x), sinks (■)")
    fig.tight_layout()
    fig.savefig(path)


# --------------------------------------------------------------------------- the deployment

SPACING_M = 12.0
FIRE_LOOP = 0.25  # a fire loops at this fraction of its district's side from the centre
ROBOT_LOOP_M = 60.0  # half-side of the robot's square patrol around the middle district's centre
ROBOT_ID = 40000  # above 32,767: the whole 16-bit short address space in use
FIRST_GATEWAY_ID = 50001


_PATROL = "speed_mps = 1.0\nloop = true\n"


def city_toml(side: int = 100, districts: int = 3) -> str:
    """The text of ``city.toml`` for a ``side x side`` grid cut into ``districts``
    per side (the shipped file is ``city_toml()``; tests build smaller cities
    of the same shape)."""
    w = side * SPACING_M
    k = districts
    dist = w / k
    n = side * side
    out = [
        f"""# A city block of sensors: {n:,} tmote sky motes on a {side} x {side} grid, 12 m
# apart ({w / 1000:g} km square; about ten radio neighbours each at 0 dBm with the
# cc2420 preset), cut into {districts} x {districts} districts. Each district has a
# gateway mote at its centre ({districts * districts} collection roots, all bridged by
# one gateway service; a record takes the nearest) and a fire that loops around
# the centre at 1 m/s, a fire front's pace; a robot patrols the middle district.
# Group type 1 tracks the fires (temperature above 50 degC), group type 2 the
# robot (its RSSI above -90 dBm); channels report both every 2 s. Ids above
# 32,767 (the gateways, the robot) use the whole 16-bit short address space.
# `awaremw experiment city --virtual [--seeds 1-10]` scores tracking at scale;
# docs/scale.md. Generated by awaremw.experiments.city.city_toml(). Format:
# docs/deployments.md.

name = "city"
description = "{side} x {side} tmote grid ({n:,} motes), {k * k} gateways, {k * k} fires, a robot"
radio = "cc2420"
seed = 11
tx_power_dbm = 0.0
area = [{w:.1f}, {w:.1f}]   # width, height (m)
"""
    ]
    gid = FIRST_GATEWAY_ID
    for b in range(districts):
        for a in range(districts):
            cx, cy = dist * (a + 0.5), dist * (b + 0.5)
            where = f"position = [{cx:.1f}, {cy:.1f}]"
            out.append(f'[[nodes]]\nid = {gid}\nkind = "gateway"\n{where}\n')
            gid += 1
    c, r = w / 2, ROBOT_LOOP_M
    square = ((c - r, c - r), (c + r, c - r), (c + r, c + r), (c - r, c + r))
    path = ", ".join(f"[{x:.1f}, {y:.1f}]" for x, y in square)
    out.append(f'[[nodes]]\nid = {ROBOT_ID}\nkind = "robot"\npath = [{path}]\n{_PATROL}')
    out.append(
        f"""[[grid]]
first_id = 1
kind = "tmote"
origin = [{SPACING_M / 2:.1f}, {SPACING_M / 2:.1f}]
spacing = {SPACING_M:.1f}
cols = {side}
rows = {side}
jitter_m = 1.5

[world]
ambient_temperature = 20.0
ambient_humidity = 50.0
ambient_light = 400.0
variation = 0.5
"""
    )
    loop = FIRE_LOOP * dist
    for b in range(districts):
        for a in range(districts):
            k = b * districts + a
            cx, cy = dist * (a + 0.5), dist * (b + 0.5)
            keys = []
            # Each fire starts at another corner: they do not move in step.
            for i, (t, x, y) in enumerate(square_loop(cx, cy, loop, 1.0, k, 9)):
                extra = ", radius = 25.0, peak = 80.0" if i == 0 else ""
                keys.append(f"    {{ t = {t:g}, x = {x:.1f}, y = {y:.1f}{extra} }},")
            out.append(
                f'[[world.fires]]\nname = "fire-{k}"\nedge = 4.0\nkeyframes = [\n'
                + "\n".join(keys)
                + "\n]\n"
            )
    out.append(
        f"""# The fires: every mote above 50 degC, about 10-15 motes around each fire.
[[groups]]
type = 1
conditions = [{{ attr = "temperature", op = ">", value = 50.0 }}]

# The robot: the motes that hear its mote above -90 dBm (about 15 m).
[[groups]]
type = 2
conditions = [{{ attr = "rssi:{ROBOT_ID}", op = ">", value = -90.0 }}]
hysteresis = 2.0

[[channels]]
id = 1
attr = "temperature"
group_type = 1
group_id = "*"
period_s = 2.0
agg = "avg"

[[channels]]
id = 2
attr = "temperature"
group_type = 2
group_id = "*"
period_s = 2.0
agg = "avg"

[experiment]
robot = {ROBOT_ID}
gateway = {FIRST_GATEWAY_ID + (districts * districts) // 2}
tracking_group = 1
channel = 1
define_at_s = 1.0
duration_s = 60.0
snapshots_s = [20, 40, 55]
"""
    )
    return "\n".join(out)
