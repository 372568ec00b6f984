"""Scripted virtual-clock scenarios of AwareMote fleets (shared test helper).

Builds motes on engineer A's :class:`~awaremw.radio.virtual_medium.VirtualNetwork`
with a scripted application whose attributes are functions of ``(position,
t)`` (so regions can move across a static grid, or motes across a region),
records every event, injects definitions the way a gateway does and checks
the group invariants against ground truth.

``LOSSLESS`` is the CC2420 preset without shadowing and fading: every link up
to ``LOSSLESS_RANGE`` metres delivers every frame, nothing beyond does. On a
grid of ``GRID`` metres that is an 8-neighbour grid (12 m and 17 m links,
24 m is out of range).
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from awaremw.protocol.attributes import X, Y
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.events import RecordProduced
from awaremw.protocol.frames import ChannelDef, CommandDef, GroupTypeDef, ItemBody, ItemKind
from awaremw.protocol.groups import Membership
from awaremw.protocol.mote import AwareMote
from awaremw.radio.model import PRESETS, RadioModel, RadioPreset
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.world.mobility import Mobility, Static

Point = tuple[float, float]
Field = Callable[[Point, float], float | None]

LOSSLESS: RadioPreset = replace(
    PRESETS["cc2420"], name="cc2420-lossless", shadowing_sigma_db=0.0, fading_sigma_db=0.0
)
LOSSLESS_RANGE = 20.0  # metres: every frame delivered within (PRR > 0.9999996 at 20 m)
GRID = 12.0


class ScriptedApp:
    """An application whose attributes are functions of (position, t)."""

    def __init__(self, mobility: Mobility, fields: Mapping[int, Field]) -> None:
        self.mobility = mobility
        self.fields = dict(fields)
        self.commands: list[tuple[CommandDef, float]] = []

    def offers(self, attr: int) -> bool:
        return attr in self.fields or attr in (X, Y)

    def read(self, attr: int, now: float) -> float | None:
        p = self.mobility.position(now)
        if attr in self.fields:
            return self.fields[attr](p, now)
        if attr == X:
            return p[0]
        if attr == Y:
            return p[1]
        return None

    def on_command(self, command: CommandDef, now: float) -> None:
        self.commands.append((command, now))


@dataclass
class Scenario:
    """A fleet of AwareMotes on a virtual network, with an event log."""

    seed: int = 1
    config: MiddlewareConfig = field(default_factory=MiddlewareConfig)
    preset: RadioPreset = LOSSLESS
    link_range: float = LOSSLESS_RANGE  # for ground-truth connectivity
    # The medium (docs/radio.md, "Medium access and collisions"). None: on the
    # lossless preset the medium before issue 13 (mac = "aloha", collisions =
    # "none": no carrier sense, no collisions, no channel access failures) -- the
    # protocol tests on it are about the protocol's logic on perfect links, not
    # about the channel; on any other preset the defaults ("csma", "sinr").
    mac: str | None = None
    collisions: str | None = None

    def __post_init__(self) -> None:
        perfect = self.preset is LOSSLESS
        mac = self.mac or ("aloha" if perfect else "csma")
        collisions = self.collisions or ("none" if perfect else "sinr")
        self.net = VirtualNetwork(
            RadioModel(self.preset, self.seed), self.seed, mac=mac, collisions=collisions
        )
        self.motes: dict[int, AwareMote] = {}
        self.apps: dict[int, ScriptedApp] = {}
        self.events: list[tuple[float, int, object]] = []
        self.net.on_event = self._on_event
        self.hooks: list[Callable[[float, int, object], None]] = []
        self._versions: dict[tuple[ItemKind, int], int] = {}

    # ------------------------------------------------------------------ building

    def add(
        self,
        nid: int,
        where: Point | Mobility,
        fields: Mapping[int, Field] | None = None,
        *,
        is_root: bool = False,
        start_at: float | None = None,
    ) -> AwareMote:
        mob: Mobility = Static(*where) if isinstance(where, tuple) else where
        app = ScriptedApp(mob, fields or {})
        cfg = replace(self.config, is_root=is_root) if is_root else self.config
        mote = AwareMote(nid, app, cfg, random.Random(self.seed * 1_000_003 + nid))
        self.motes[nid] = mote
        self.apps[nid] = app
        self.net.add(mote, mob, start_at=start_at)
        return mote

    def grid(
        self,
        nx: int,
        ny: int,
        fields: Mapping[int, Field] | None = None,
        *,
        spacing: float = GRID,
        first_id: int = 1,
        origin: Point = (0.0, 0.0),
    ) -> list[int]:
        ids = []
        for j in range(ny):
            for i in range(nx):
                nid = first_id + j * nx + i
                self.add(nid, (origin[0] + i * spacing, origin[1] + j * spacing), fields)
                ids.append(nid)
        return ids

    def _on_event(self, nid: int, ev: object, t: float) -> None:
        self.events.append((t, nid, ev))
        for h in self.hooks:
            h(t, nid, ev)

    # ------------------------------------------------------------------ driving

    @property
    def now(self) -> float:
        return self.net.now

    def run_until(self, t: float) -> None:
        self.net.run_until(t)

    def run_for(self, dt: float) -> None:
        self.net.run_until(self.net.now + dt)

    def at(self, t: float, fn: Callable[[], None]) -> None:
        self.net.call_at(t, fn)

    def kill(self, nid: int) -> None:
        self.net.kill(nid)

    def alive(self) -> list[int]:
        return [n for n in self.motes if self.net.alive(n)]

    def position(self, nid: int) -> Point:
        return self.apps[nid].mobility.position(self.now)

    def define(
        self,
        kind: ItemKind,
        item_id: int,
        item: ItemBody | None,
        *,
        everywhere: bool = True,
        at: Iterable[int] | None = None,
    ) -> int:
        """Inject a new version of an item, as a gateway does.

        ``everywhere``: at every live mote at once (the definition is known
        network-wide at this instant), else only at the motes ``at`` (a
        gateway's mote; dissemination spreads it). Returns the version.
        """
        v = self._versions.get((kind, item_id), 0) + 1
        self._versions[(kind, item_id)] = v
        srcs = self.alive() if everywhere else list(at or [])
        now = self.net.now
        for s in srcs:
            mote = self.motes[s]
            self.net.call(s, lambda m=mote: m.inject(kind, item_id, v, item, now))
        return v

    def define_group(self, gtype: int, defn: GroupTypeDef | None, **kw: Any) -> int:
        return self.define(ItemKind.GROUP_TYPE, gtype, defn, **kw)

    def define_channel(self, cid: int, defn: ChannelDef | None, **kw: Any) -> int:
        return self.define(ItemKind.CHANNEL, cid, defn, **kw)

    # ------------------------------------------------------------------ observing

    def of_type(self, cls: type, since: float = -math.inf) -> list[tuple[float, int, Any]]:
        return [(t, n, e) for t, n, e in self.events if isinstance(e, cls) and t >= since]

    def records(self, since: float = -math.inf) -> list[tuple[float, Any]]:
        return [(e.t, e.record) for _, _, e in self.of_type(RecordProduced, since)]

    def memberships(self, gtype: int) -> dict[int, Membership]:
        out = {}
        for n in self.alive():
            m = self.motes[n].groups.membership(gtype)
            if m is not None:
                out[n] = m
        return out

    def leaders(self, gtype: int) -> dict[int, int]:
        """group id -> leader, for live leaders (see leader_nodes for id clashes)."""
        return {m.group_id: n for n, m in self.memberships(gtype).items() if m.is_leader}

    def leader_nodes(self, gtype: int) -> list[int]:
        """Every live leader of the type (two with one id after a duplicated handover)."""
        return [n for n, m in self.memberships(gtype).items() if m.is_leader]

    def qualifying(self, pred: Callable[[int], bool]) -> set[int]:
        return {n for n in self.alive() if pred(n)}

    def components(self, nodes: set[int]) -> list[set[int]]:
        """Connected components of ``nodes`` over links shorter than ``link_range``."""
        pos = {n: self.position(n) for n in nodes}
        left = set(nodes)
        comps = []
        while left:
            seed = left.pop()
            comp = {seed}
            todo = [seed]
            while todo:
                a = todo.pop()
                ax, ay = pos[a]
                near = [
                    b for b in left if math.hypot(pos[b][0] - ax, pos[b][1] - ay) <= self.link_range
                ]
                for b in near:
                    left.discard(b)
                    comp.add(b)
                    todo.append(b)
            comps.append(comp)
        return comps

    def loops(self, gtype: int) -> list[int]:
        """Members whose parent chain comes back to a mote already on it."""
        ms = self.memberships(gtype)
        bad = []
        for n, m in ms.items():
            seen = {n}
            cur: Membership | None = m
            while cur is not None and not cur.is_leader and cur.parent in ms:
                if cur.parent in seen:
                    bad.append(n)
                    break
                seen.add(cur.parent)
                cur = ms[cur.parent]
        return bad

    def tree_ok(self, gtype: int) -> list[str]:
        """Problems of the group trees: loops, dangling parents, foreign parents."""
        ms = self.memberships(gtype)
        problems = []
        for n, m in ms.items():
            seen = {n}
            cur = m
            while not cur.is_leader:
                p = cur.parent
                if p is None or p not in ms:
                    problems.append(f"{n}: parent {p} is not a live member")
                    break
                nxt = ms[p]
                if nxt.group_id != m.group_id:
                    problems.append(f"{n}: parent {p} is in group {nxt.group_id}")
                    break
                if p in seen:
                    problems.append(f"{n}: loop through {p}")
                    break
                seen.add(p)
                cur = nxt
        return problems

    def group_problems(self, gtype: int, qualifying: set[int]) -> list[str]:
        """Invariants after convergence: members are exactly the qualifying motes,
        one leader per connected component, one id per component, distinct ids
        across components, trees without loops."""
        ms = self.memberships(gtype)
        problems = []
        if set(ms) != qualifying:
            extra = sorted(set(ms) - qualifying)
            missing = sorted(qualifying - set(ms))
            problems.append(f"members differ: extra {extra[:10]} missing {missing[:10]}")
        ids = []
        for comp in self.components(qualifying):
            gids = {ms[n].group_id for n in comp if n in ms}
            leaders = [n for n in comp if n in ms and ms[n].is_leader]
            if len(gids) != 1:
                problems.append(f"component of {len(comp)} has ids {sorted(gids)}")
            if len(leaders) != 1:
                problems.append(f"component of {len(comp)} has leaders {leaders}")
            ids.extend(gids)
        if len(ids) != len(set(ids)):
            problems.append(f"an id is shared by separate components: {ids}")
        problems.extend(self.tree_ok(gtype))
        return problems


def in_disc(cx: float, cy: float, r: float) -> Callable[[Point], bool]:
    return lambda p: math.hypot(p[0] - cx, p[1] - cy) <= r


def moving_disc(
    start: Point, velocity: Point, r: float, t0: float = 0.0
) -> Callable[[Point, float], bool]:
    def inside(p: Point, t: float) -> bool:
        dt = max(0.0, t - t0)
        cx, cy = start[0] + velocity[0] * dt, start[1] + velocity[1] * dt
        return math.hypot(p[0] - cx, p[1] - cy) <= r

    return inside


def indicator(
    inside: Callable[[Point, float], bool], hot: float = 80.0, cold: float = 20.0
) -> Field:
    """A temperature field: ``hot`` inside the region, ``cold`` outside."""
    return lambda p, t: hot if inside(p, t) else cold
