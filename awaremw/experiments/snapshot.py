"""The view of an experiment run at one instant: a :class:`~awaremw.view.snapshot.Snapshot`
built from the scenario, the recorder's events and the robot client's records.

It lives with the experiments (it reads their recorder and scenario); the view
layer below only draws snapshots.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

from awaremw.experiments.client import Received
from awaremw.experiments.metrics import Recorder
from awaremw.experiments.scenario import Scenario
from awaremw.gateway.schema import agg_name
from awaremw.protocol.attributes import unit_of
from awaremw.radio.energy import EnergyRole, role_of
from awaremw.view.snapshot import GroupLine, MoteDot, RecordLine, Snapshot


def record_line(r: Received) -> RecordLine:
    """A RecordLine from a client's :class:`~awaremw.experiments.client.Received`."""
    d = r.record
    return RecordLine(r.t, d.channel, d.group_type, d.group_id, r.agg, d.value, d.count, d.leader,
                      unit_of(r.attr, r.agg))  # fmt: skip


def snapshot_of(
    sc: Scenario,
    rec: Recorder,
    now: float,
    live: object | None = None,
    traffic: Mapping[int, tuple[int, int, float]] | None = None,
    title: str | None = None,
    forwarders: Collection[int] = (),
) -> Snapshot:
    """The view of a run at ``now``: positions from the deployment's mobility,
    memberships from the recorded events, records from the robot client;
    with ``traffic``, frames and radio energy per mote, and per role per hour
    (``forwarders``: motes that acknowledged unicasts, see radio/energy.py)."""
    gtype = sc.tracking_group if sc.group_json else None
    members = rec.members_at(gtype, now) if gtype is not None else {}
    dots = []
    for spec in sc.deployment.nodes:
        x, y = spec.mobility().position(now)
        s = members.get(spec.id)
        dots.append(
            MoteDot(
                spec.id, x, y, spec.kind,
                None if s is None else s.gid, bool(s and s.leader),
                alive=spec.id not in rec.down and spec.boot_s <= now,
            )
        )  # fmt: skip
    groups: list[GroupLine] = []
    if gtype is not None:
        leaders = rec.leaders_at(gtype, now)
        for gid, nodes in sorted(rec.groups_at(gtype, now).items()):
            groups.append(GroupLine(gtype, gid, leaders.get(gid), len(nodes)))
    records: tuple[RecordLine, ...] = ()
    got = getattr(live, "records", None)
    if got:
        records = tuple(record_line(r) for r in got[-8:])
    else:
        records = tuple(
            RecordLine(a.t, a.record.channel, a.record.group_type, a.record.group_id,
                       agg_name(a.record.agg), a.record.value, a.record.count, a.record.leader,
                       unit_of(_attr_of(sc, a.record.channel), agg_name(a.record.agg)))
            for a in sorted(rec.arrivals.values(), key=lambda a: a.t)[-8:]
        )  # fmt: skip
    stats: dict[str, float | int | str] = {
        "records": len(rec.arrivals),
        "groups seen": len(rec.group_ids(gtype, 0.0, now)) if gtype is not None else 0,
        "handovers": len(rec.handovers),
    }
    if traffic:
        sensors = [n for n in sc.sensors if n in traffic]
        if sensors:
            stats["frames/mote"] = sum(traffic[n][0] for n in sensors) / len(sensors)
            stats["mJ/mote"] = sum(traffic[n][2] for n in sensors) / len(sensors)
            for role, e in role_energy(sc, rec, now, traffic, forwarders).items():
                stats[f"mJ/h {role}"] = e["mj_per_hour"]
                stats[f"frames/h {role}"] = e["frames_per_hour"]
    w, h = sc.deployment.area
    return Snapshot(
        now, (0.0, w, 0.0, h), tuple(dots), tuple(groups), records, stats,
        title=title or f"awaremw {sc.name}", group_type=gtype,
    )  # fmt: skip


def role_energy(
    sc: Scenario,
    rec: Recorder,
    now: float,
    traffic: Mapping[int, tuple[int, int, float]],
    forwarders: Collection[int] = (),
) -> dict[str, dict[str, float]]:
    """Radio energy and frames per hour since the start (means over the sensor
    motes) by the role each has at ``now``: ``leader``, ``member`` (of the
    tracked group type), ``forwarder`` (in ``forwarders``: it acknowledged
    unicasts, data went through it), ``idle`` (radio/energy.py). Role name ->
    ``{"motes", "mj_per_hour", "frames_per_hour"}``; empty at ``now`` <= 0."""
    if now <= 0:
        return {}
    gtype = sc.tracking_group if sc.group_json else None
    members = rec.members_at(gtype, now) if gtype is not None else {}
    fwd = set(forwarders)
    by: dict[EnergyRole, list[int]] = {}
    for n in sc.sensors:
        if n not in traffic:
            continue
        s = members.get(n)
        role = role_of(bool(s and s.leader), s is not None, 1 if n in fwd else 0)
        by.setdefault(role, []).append(n)
    per_hour = 3600.0 / now
    out: dict[str, dict[str, float]] = {}
    for role in EnergyRole:
        ns = by.get(role)
        if ns:
            out[role.value] = {
                "motes": len(ns),
                "mj_per_hour": sum(traffic[n][2] for n in ns) / len(ns) * per_hour,
                "frames_per_hour": sum(traffic[n][0] for n in ns) / len(ns) * per_hour,
            }
    return out


def _attr_of(sc: Scenario, channel: int) -> str | None:
    """The attribute the scenario's channel samples (None if it defines no such channel)."""
    attr = sc.channel_json.get(channel, {}).get("attr")
    return None if attr is None else str(attr)
