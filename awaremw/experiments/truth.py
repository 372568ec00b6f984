"""Ground truth: what the emulator knows and the motes can only estimate.

Experiments score the middleware against it: which motes *should* be members
of a group type at time t, and how those members fall into separate regions.

Choices (docs/experiments.md explains them):

* a mote's true attribute value is the noise-free world value at its position
  (:meth:`awaremw.nodes.kinds.NodeApp.true_value`): no sensor noise, no ADC
  quantisation;
* the true ``rssi:<src>`` at a mote is the radio model's *mean* RSSI of the
  link (path loss plus the link's static shadowing; no per-packet fading),
  ``None`` when that mean is below the receiver's sensitivity (the mote would
  normally not hear ``src`` at all). Static shadowing is part of the truth
  because it is a fixed property of the place, as a wall is; fading is noise;
* membership truth is the strict condition (no hysteresis): hysteresis is the
  middleware's means to be stable, not part of the definition of the object;
* two true members are *connected* when the link between them is usable both
  ways (mean-RSSI packet reception ratio >= ``link_prr``); a true *region* is a
  connected component of the true members: the group the paper expects.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from awaremw.protocol import attributes as A
from awaremw.protocol.attributes import Application
from awaremw.protocol.frames import NODE_MASK, GroupTypeDef
from awaremw.protocol.groups import condition_holds
from awaremw.radio.model import Z_MAX, RadioModel
from awaremw.world.fields import World
from awaremw.world.mobility import Mobility

_FIELD_OF = {
    A.TEMPERATURE: "temperature",
    A.HUMIDITY: "humidity",
    A.LIGHT: "light",
    A.GAS: "gas",
}


MEMBERS_CACHE_MAX = 4096  # members() answers kept (instants x definitions x populations)


@dataclass(frozen=True, slots=True)
class TruthNode:
    """What the truth needs about one mote."""

    node: int
    mobility: Mobility
    app: Application | None
    tx_power: float
    radio: RadioModel


class GroundTruth:
    """Noise-free values, memberships and regions of a deployment at any time."""

    def __init__(self, nodes: Iterable[TruthNode], world: World, link_prr: float = 0.5) -> None:
        self.nodes: dict[int, TruthNode] = {n.node: n for n in nodes}
        self.world = world
        self.link_prr = link_prr
        # members() answers, by (definition, t, population): the scoring asks the
        # same instants several times (the pass, the series, the figures).
        self._reaches: dict[tuple[int, float], float] = {}
        self._members: dict[tuple[GroupTypeDef, float, frozenset[int] | None], frozenset[int]] = {}

    # ------------------------------------------------------------------ geometry and radio

    def position(self, node: int, t: float) -> tuple[float, float]:
        return self.nodes[node].mobility.position(t)

    def distance(self, a: int, b: int, t: float) -> float:
        (ax, ay), (bx, by) = self.position(a, t), self.position(b, t)
        return math.hypot(ax - bx, ay - by)

    def mean_rssi(self, src: int, dst: int, t: float) -> float:
        """Mean RSSI (dBm) at ``dst`` of frames from ``src`` at time ``t``."""
        s = self.nodes[src]
        return self.nodes[dst].radio.mean_rssi(src, dst, self.distance(src, dst, t), s.tx_power)

    def link_ok(self, a: int, b: int, t: float, frame_len: int = 40) -> bool:
        """A usable link both ways (mean PRR >= ``link_prr`` for a typical frame)."""
        ra, rb = self.nodes[a].radio, self.nodes[b].radio
        if self.distance(a, b, t) > max(ra.max_range_m(), rb.max_range_m()):
            return False
        return (
            rb.prr(self.mean_rssi(a, b, t), frame_len) >= self.link_prr
            and ra.prr(self.mean_rssi(b, a, t), frame_len) >= self.link_prr
        )

    def _reach(self, radio: RadioModel, tx_power: float) -> float:
        """Distance beyond which the mean RSSI is below sensitivity for every link
        (the most favourable static shadowing, ``Z_MAX`` sigmas): a shortcut that
        leaves :meth:`value` exact."""
        key = (id(radio), tx_power)
        r = self._reaches.get(key)
        if r is None:
            p = radio.preset
            budget = tx_power + p.shadowing_sigma_db * Z_MAX - p.sensitivity_dbm - p.pl_d0_db
            r = p.d0_m * 10.0 ** (budget / (10.0 * p.path_loss_exponent)) * (1.0 + 1e-9)
            self._reaches[key] = r  # a few radios x tx powers per deployment
        return r

    # ------------------------------------------------------------------ attribute values

    def value(self, node: int, attr: int, t: float) -> float | None:
        """The noise-free value of ``attr`` at ``node`` (None: not offered / not heard)."""
        n = self.nodes[node]
        if A.is_rssi(attr):
            src = attr & NODE_MASK
            if src == node or src not in self.nodes:
                return None
            d = self.distance(src, node, t)
            s = self.nodes[src]
            if d > self._reach(n.radio, s.tx_power):
                return None  # below sensitivity whatever the link's shadowing
            r = n.radio.mean_rssi(src, node, d, s.tx_power)
            return r if r >= n.radio.preset.sensitivity_dbm else None
        if attr in (A.X, A.Y):
            return self.position(node, t)[0 if attr == A.X else 1]
        app = n.app
        if app is None or not app.offers(attr):
            return None
        name = _FIELD_OF.get(attr)
        if name is not None:
            x, y = self.position(node, t)
            return self.world.value(name, x, y, t)
        return app.read(attr, t)  # battery and kind-specific attributes: as read

    def satisfies(self, node: int, defn: GroupTypeDef, t: float) -> bool:
        return all(condition_holds(c, self.value(node, c.attr, t), 0.0) for c in defn.conditions)

    def members(
        self, defn: GroupTypeDef, t: float, among: Iterable[int] | None = None
    ) -> frozenset[int]:
        """The motes (of ``among``, default all) whose true values meet ``defn``."""
        pool = None if among is None else frozenset(among)
        key = (defn, t, pool)
        got = self._members.get(key)
        if got is None:
            ids = self._in_reach(defn, t, self.nodes if pool is None else pool)
            got = frozenset(n for n in ids if self.satisfies(n, defn, t))
            if len(self._members) >= MEMBERS_CACHE_MAX:
                self._members.clear()  # pure function of the key: recomputable
            self._members[key] = got
        return got

    def _in_reach(self, defn: GroupTypeDef, t: float, ids: Iterable[int]) -> Iterable[int]:
        """``ids`` without the motes that cannot hear the source of an ``rssi:<src>``
        condition of ``defn`` (their value is None: the condition, and so the
        definition, fails there); all of ``ids`` without such a condition."""
        for c in defn.conditions:
            if not A.is_rssi(c.attr):
                continue
            s = self.nodes.get(c.attr & NODE_MASK)
            if s is None:
                return ()
            sx, sy = s.mobility.position(t)
            out = []
            for n in ids:
                node = self.nodes[n]
                x, y = node.mobility.position(t)
                if math.hypot(x - sx, y - sy) <= self._reach(node.radio, s.tx_power):
                    out.append(n)
            return out
        return ids

    def regions(
        self, defn: GroupTypeDef, t: float, among: Iterable[int] | None = None
    ) -> list[frozenset[int]]:
        """Connected components of the true members (largest first): the groups the
        paper's rule (members talk through members only) should produce."""
        return components(self.members(defn, t, among), lambda a, b: self.link_ok(a, b, t))


def components(nodes: Iterable[int], linked: Callable[[int, int], bool]) -> list[frozenset[int]]:
    """Connected components of ``nodes`` under the symmetric predicate ``linked``."""
    todo = set(nodes)
    out: list[frozenset[int]] = []
    while todo:
        seed = todo.pop()
        comp = {seed}
        stack = [seed]
        while stack:
            a = stack.pop()
            near = [b for b in todo if linked(a, b)]
            for b in near:
                todo.discard(b)
                comp.add(b)
                stack.append(b)
        out.append(frozenset(comp))
    out.sort(key=lambda c: (-len(c), min(c)))
    return out
