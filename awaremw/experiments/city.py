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
``objects_tracked`` (objects with a delivered record in the last quarter of
the run), ``one_id_per_object`` and ``every_object_tracked``. Figure:
``city_field.png``, the whole field at the last snapshot with every group and
object.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from awaremw.experiments import metrics as M
from awaremw.experiments import objects as O
from awaremw.experiments.metrics import RunResult

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
    late = 0.75 * result.duration
    until = result.duration - 5.0  # records produced later may still be in flight
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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec, sc = a.rec, a.sc
    t = max(0.0, duration - a.settle)
    pos = {s.id: s.position for s in sc.deployment.nodes}
    fig, ax = plt.subplots(figsize=(7.5, 7.5), dpi=110)
    xs = [pos[n][0] for n in sc.sensors]
    ys = [pos[n][1] for n in sc.sensors]
    ax.scatter(xs, ys, s=0.3, color="0.8", linewidths=0)
    for gtype in per_type:
        for gid, members in rec.groups_at(gtype, t).items():
            colour = plt.cm.tab20(gid % 20)
            mx = [pos[n][0] for n in members if n in pos]
            my = [pos[n][1] for n in members if n in pos]
            ax.scatter(mx, my, s=6, color=colour, linewidths=0)
        for gid, leader in rec.leaders_at(gtype, t).items():
            if leader in pos:
                ax.scatter(*pos[leader], marker="*", s=60, color=plt.cm.tab20(gid % 20),
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
    plt.close(fig)
