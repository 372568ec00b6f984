"""A deployment as an experiment: its definitions, its ``[experiment]`` table,
its world and its ground truth.

The deployment file is read and checked once, by
:mod:`awaremw.runtime.deployment`; a scenario only reads that value.
``[[groups]]`` and ``[[channels]]`` entries are the MQTT JSON payloads of
``aware/def/group/<type>`` and ``aware/def/channel/<id>`` plus the ``type`` /
``id`` key of the topic; the gateway's own schema (:mod:`awaremw.gateway.schema`)
turns them into definitions, with the limits of the deployment's gateway mote,
so a scenario defines exactly what a robot client would publish.

The ``[experiment]`` table (all optional; its keys are checked when the file is
read, ``EXPERIMENT_KEYS`` of :mod:`awaremw.runtime.deployment`):

``robot``, ``gateway``        node ids of the robot's and the gateway's motes
``tracking_group``, ``channel`` the group type and channel the metrics follow
``define_at_s``               when the client defines the groups and channels
``duration_s``                length of the run (emulated seconds)
``rssi_motes``                motes whose RSSI is plotted (Fig. 9)
``snapshots_s``               instants of the snapshot figures
``field``                     [xmin, xmax, ymin, ymax] of the sensor field
``two_fires_s``, ``merged_s``, ``split_s``  phases of the fire checks
``kill_at_s``                 when the failover experiment kills the group's leader
``analysis``                  which experiment scores the file when it is given by path
                              (``awaremw experiment ./mine.toml``): romeo4r, fire, ...
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from awaremw.experiments.truth import GroundTruth, TruthNode
from awaremw.gateway.schema import (
    Definition,
    Limits,
    SchemaError,
    parse_channel,
    parse_group_type,
)
from awaremw.nodes import build_app, config_for, kind_names
from awaremw.protocol.frames import ChannelDef, GroupTypeDef
from awaremw.runtime.deployment import Deployment, DeploymentError, load
from awaremw.world.fields import World


@dataclass(frozen=True)
class Scenario:
    deployment: Deployment
    world: World
    definitions: tuple[Definition, ...]
    group_json: Mapping[int, Mapping[str, Any]]  # type -> MQTT payload
    channel_json: Mapping[int, Mapping[str, Any]]  # id -> MQTT payload
    settings: Mapping[str, Any] = field(default_factory=dict)

    # ------------------------------------------------------------------ settings

    @property
    def name(self) -> str:
        return self.deployment.name

    def get(self, key: str, default: Any = None) -> Any:
        return self.settings.get(key, default)

    @property
    def robot(self) -> int | None:
        r = self.get("robot")
        if r is None:
            robots = self.deployment.of_kind("robot")
            return robots[0].id if robots else None
        return int(r)

    @property
    def gateway(self) -> int:
        g = self.get("gateway")
        if g is None:
            gws = self.deployment.of_kind("gateway")
            if not gws:
                raise DeploymentError(f'{self.name}: no gateway mote (kind = "gateway")')
            return gws[0].id
        return int(g)

    @property
    def tracking_group(self) -> int:
        return int(self.get("tracking_group", min(self.group_json, default=1)))

    @property
    def channel(self) -> int:
        return int(self.get("channel", min(self.channel_json, default=1)))

    @property
    def define_at(self) -> float:
        return float(self.get("define_at_s", 2.0))

    @property
    def duration(self) -> float:
        return float(self.get("duration_s", 60.0))

    @property
    def sensors(self) -> list[int]:
        """The motes that sense (not robots, not gateways): the scored population."""
        return [n.id for n in self.deployment.nodes if n.kind not in ("robot", "gateway")]

    @property
    def field(self) -> tuple[float, float, float, float]:
        f = self.get("field")
        if f is not None:
            return (float(f[0]), float(f[1]), float(f[2]), float(f[3]))
        pts = [self.deployment.node(i).position for i in self.sensors]
        return (
            min(p[0] for p in pts),
            max(p[0] for p in pts),
            min(p[1] for p in pts),
            max(p[1] for p in pts),
        )

    def group_def(self, gtype: int | None = None) -> GroupTypeDef:
        g = self.tracking_group if gtype is None else gtype
        for d in self.definitions:
            if d.kind.name == "GROUP_TYPE" and d.item_id == g and isinstance(d.body, GroupTypeDef):
                return d.body
        raise KeyError(f"{self.name}: no group type {g} defined")

    def channel_def(self, cid: int | None = None) -> ChannelDef:
        c = self.channel if cid is None else cid
        for d in self.definitions:
            if d.kind.name == "CHANNEL" and d.item_id == c and isinstance(d.body, ChannelDef):
                return d.body
        raise KeyError(f"{self.name}: no channel {c} defined")

    # ------------------------------------------------------------------ truth

    def truth(self, link_prr: float = 0.5) -> GroundTruth:
        d = self.deployment
        model = d.radio_model()
        nodes = [
            TruthNode(s.id, s.mobility(), build_app(s, d, self.world), d.tx_power_of(s), model)
            for s in d.nodes
        ]
        return GroundTruth(nodes, self.world, link_prr)

    def robot_entry(self, truth: GroundTruth, step: float = 0.25) -> float | None:
        """When the robot enters the area where motes sense it: the first instant
        after the definitions at which the ground truth has a member."""
        defn = self.group_def()
        t = self.define_at
        while t <= self.duration:
            if truth.members(defn, t, self.sensors):
                return t
            t += step
        return None


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a deployment as a scenario (raises DeploymentError)."""
    return scenario_of(load(name_or_path, kind_names()))


def scenario_of(d: Deployment) -> Scenario:
    """The scenario of a deployment: its definitions, through the gateway's schema."""
    gw = d.of_kind("gateway")
    cfg = config_for(gw[0], d) if gw else config_for(d.nodes[0], d)
    limits = Limits.from_config(cfg, known_nodes=d.ids)
    where = str(d.path) if d.path is not None else d.name
    defs: list[Definition] = []
    gjson: dict[int, Mapping[str, Any]] = {}
    cjson: dict[int, Mapping[str, Any]] = {}
    for kind, key, entries in (("groups", "type", d.groups), ("channels", "id", d.channels)):
        for i, entry in enumerate(entries):
            ident = entry[key]
            body = {k: v for k, v in entry.items() if k != key}
            payload = json.dumps(body).encode()
            try:
                if kind == "groups":
                    defn = parse_group_type(str(ident), payload, limits, gjson)
                    gjson[ident] = body
                else:
                    defn = parse_channel(str(ident), payload, limits, cjson)
                    cjson[ident] = body
            except SchemaError as e:
                raise DeploymentError(f"{where}: {kind}[{i}] ({key} {ident}): {e}") from None
            defs.append(defn)
    return Scenario(d, d.world_model(), tuple(defs), gjson, cjson, dict(d.experiment))
