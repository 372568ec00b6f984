"""Who hears whom: the cell grid of one medium's motes and per-sender receiver caches.

Both radio media -- the Zenoh medium (:mod:`awaremw.radio.zenoh_medium`) and
the virtual-clock driver (:mod:`awaremw.radio.virtual_medium`) -- find the
receivers of a frame (rules 3 and 4 of ``docs/radio.md``, "Medium
semantics") through this module, and decide each reception in
:mod:`awaremw.radio.reception`:

* :class:`Station` is what a medium knows of one mote's radio here (position,
  cell, TX power, range, counters, on the air or not); each medium subclasses
  it (through :class:`~awaremw.radio.linklayer.LinkStation`).
* :class:`Neighbourhood` keeps the medium's motes on the air: static ones in a
  grid of cells of side ``model.cell_size_m``, moving ones in a list
  (relocated when asked). :meth:`Neighbourhood.listeners` says who listens to
  a cell.
* :meth:`Neighbourhood.sender` gives, for a sender at ``(x, y)`` with power
  ``txp``, a :class:`SenderCache` of the static receivers in its 3x3 cells,
  split once into those that may hear it (``near``: with their mean RSSI and
  fading link hash, for the per-packet decision), those that never can
  (``far_loss``: no fading draw lifts the mean RSSI to sensitivity) and those
  beyond range (``far_dist``). The last two are counted in bulk: the medium
  bumps ``pending`` per broadcast and :meth:`SenderCache.flush` folds the
  count into the receivers' counters when the cache is dropped (a static mote
  appeared or vanished within one cell: :meth:`Neighbourhood.touch`; the
  sender moved) or the counters are read (:meth:`Neighbourhood.flush_all`).
  :meth:`Neighbourhood.link` caches unicast links between static motes in the
  same cache.

The per-packet loop over ``near`` (:meth:`Reception.broadcast
<awaremw.radio.reception.Reception.broadcast>`) is the hot path of both media.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

from mypy_extensions import mypyc_attr

from awaremw.radio.counters import MoteCounters
from awaremw.radio.model import Z_MAX, RadioModel, cell_of
from awaremw.world.mobility import Mobility, Static

Cell = tuple[int, int]


# Bound of the sender caches (one per sender id heard, ids chosen by remote
# senders): beyond it the oldest built is dropped (its bulk counts folded in).
# It grows with the static motes of the medium (twice their number: each is a
# sender, and as many remote ones may stand near them), so that a large network
# never rebuilds its caches over and over (10,000 motes in one process thrashed
# a fixed bound of 4,096).
MAX_SENDER_CACHES = 4096


def adjacent(a: Cell, b: Cell) -> bool:
    """True if a mote in cell ``a`` listens to cell ``b`` (its own or one of the 8 around)."""
    return abs(a[0] - b[0]) <= 1 and abs(a[1] - b[1]) <= 1


# The base of LinkStation, which Python code subclasses in the compiled build (setup.py).
@mypyc_attr(allow_interpreted_subclasses=True)
class Station:
    """A mote's radio as the neighbourhood sees it. Subclassed by each medium."""

    __slots__ = (
        "alive",
        "cell",
        "counters",
        "mobility",
        "node_id",
        "pos_t",
        "range_m",
        "static",
        "tx_power",
        "x",
        "y",
    )

    def __init__(
        self,
        node_id: int,
        mobility: Mobility,
        tx_power: float,
        range_m: float,
        counters: MoteCounters,
    ) -> None:
        self.node_id = node_id
        self.mobility = mobility
        self.static = isinstance(mobility, Static)
        self.tx_power = tx_power
        self.range_m = range_m  # model.max_range_m(tx_power)
        self.counters = counters
        self.alive = False  # on the air (rule 1)
        self.x = 0.0
        self.y = 0.0
        self.cell: Cell = (0, 0)
        self.pos_t = -math.inf  # time x, y, cell were computed (moving motes)


S = TypeVar("S", bound=Station)

# (receiver, its counters, mean RSSI of the link, fading link hash)
NearEntry = tuple[S, MoteCounters, float, int]
# (receiver, distance, mean RSSI, fading link hash) of one static pair
Link = tuple[S, float, float, int]


class SenderCache(Generic[S]):
    """The static receivers of sender ``src`` standing at ``(x, y)`` with power ``txp``.

    Valid while no static mote appears or vanishes within one cell of it
    (:meth:`Neighbourhood.touch`) and the sender stays where it is.
    """

    __slots__ = (
        "cell", "far_dist", "far_loss", "links", "mw", "near", "pending", "src", "txp", "x", "y",
    )  # fmt: skip

    def __init__(self, src: int, x: float, y: float, txp: float, cell: Cell) -> None:
        self.src = src
        self.x = x
        self.y = y
        self.txp = txp
        self.cell = cell
        self.near: list[NearEntry[S]] = []
        self.far_loss: list[S] = []  # in range, but no fading draw can deliver
        self.far_dist: list[S] = []  # in the 3x3 cells, beyond range
        self.pending = 0  # broadcasts not yet folded into the far_* receivers' counters
        # Unicast links to static receivers (None: not listening to the sender's cell).
        self.links: dict[int, Link[S] | None] = {}
        # Mean power (mW) of its frames at static receivers, filled by the Air's
        # collision and carrier-sense checks (radio/mac.py, OnAir.mw_cache).
        self.mw: dict[int, float] = {}

    def flush(self) -> None:
        """Fold the bulk-counted broadcasts into the far receivers' counters."""
        k = self.pending
        if k:
            for r in self.far_loss:
                r.counters.dropped_loss += k
            for r in self.far_dist:
                r.counters.dropped_distance += k
            self.pending = 0


class Neighbourhood(Generic[S]):
    """One medium's motes on the air, by cell, and per-sender receiver caches.

    ``on_cell`` (optional) is called with the new cell whenever :meth:`locate`
    moves a mote into another cell (the Zenoh medium subscribes to it).
    """

    __slots__ = (
        "_by_cell", "_caches", "_grid", "_static", "cell_size", "model", "moving", "on_cell",
    )  # fmt: skip

    def __init__(self, model: RadioModel, on_cell: Callable[[Cell], None] | None = None) -> None:
        self.model = model
        self.cell_size = model.cell_size_m
        self.on_cell = on_cell
        self._grid: dict[Cell, list[S]] = {}  # static motes on the air, by cell
        self.moving: list[S] = []  # moving motes on the air (do not mutate)
        self._caches: dict[int, SenderCache[S]] = {}  # by sender id; MAX_SENDER_CACHES
        self._by_cell: dict[Cell, dict[int, SenderCache[S]]] = {}  # the same, by sender cell
        self._static = 0  # static motes on the air (the cache bound grows with them)

    # ------------------------------------------------------------------ motes

    def add(self, r: S, now: float) -> None:
        """Put ``r`` (on the air) where its mobility says it is at ``now``."""
        r.x, r.y = r.mobility.position(now)
        r.cell = cell_of(r.x, r.y, self.cell_size)
        r.pos_t = now
        if r.static:
            self._grid.setdefault(r.cell, []).append(r)
            self._static += 1
            self.touch(r.cell)
        else:
            self.moving.append(r)

    def remove(self, r: S) -> None:
        """Take ``r`` out (switched off, or about to change its mobility)."""
        if r.static:
            self._grid[r.cell].remove(r)
            self._static -= 1
            self.touch(r.cell)  # its own cache too: a sender is within one cell of itself
        else:
            self.moving.remove(r)

    def locate(self, r: S, now: float) -> None:
        """Refresh a moving mote's position and cell for ``now`` (static: nothing)."""
        if r.static or r.pos_t == now:
            return
        r.x, r.y = r.mobility.position(now)
        r.pos_t = now
        cell = cell_of(r.x, r.y, self.cell_size)
        if cell != r.cell:
            r.cell = cell
            if self.on_cell is not None:
                self.on_cell(cell)

    def cells_around(self, cell: Cell) -> Iterator[list[S]]:
        """The non-empty lists of static motes in ``cell`` and the 8 around it."""
        cx, cy = cell
        grid = self._grid
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                lst = grid.get((cx + dx, cy + dy))
                if lst:
                    yield lst

    def any_static_around(self, cell: Cell) -> bool:
        return any(True for _ in self.cells_around(cell))

    def moving_listeners(self, cell: Cell, now: float) -> list[S]:
        """Moving motes that listen to ``cell`` at ``now`` (located first)."""
        out = []
        for r in self.moving:
            self.locate(r, now)
            if adjacent(r.cell, cell):
                out.append(r)
        return out

    def listeners(self, cell: Cell, now: float) -> list[S]:
        """Every mote that listens to ``cell``: static ones first, in grid order."""
        out = [r for lst in self.cells_around(cell) for r in lst]
        out.extend(self.moving_listeners(cell, now))
        return out

    # ------------------------------------------------------------------ sender caches

    def sender(self, src: int, x: float, y: float, txp: float) -> SenderCache[S]:
        """The receiver cache of sender ``src`` at ``(x, y)``, built if needed (a
        moving sender gets a new one wherever it stands: prefer :func:`hear`)."""
        c = self._caches.get(src)
        if c is not None and c.x == x and c.y == y and c.txp == txp:
            return c
        return self._build(src, x, y, txp)

    def cached(self, src: int, x: float, y: float, txp: float) -> bool:
        c = self._caches.get(src)
        return c is not None and c.x == x and c.y == y and c.txp == txp

    def _build(self, src: int, x: float, y: float, txp: float) -> SenderCache[S]:
        self.drop(src)
        if len(self._caches) >= max(MAX_SENDER_CACHES, 2 * self._static):
            self.drop(next(iter(self._caches)))  # the oldest built (ids are remote-chosen)
        m = self.model
        cell = cell_of(x, y, self.cell_size)
        c: SenderCache[S] = SenderCache(src, x, y, txp, cell)
        rng = m.max_range_m(txp)
        near, far_loss, far_dist = c.near, c.far_loss, c.far_dist
        mean_rssi = m.mean_rssi
        link_hash = m.fading_link_hash
        hypot = math.hypot
        # never_delivers(mean), inlined: mean + max fade < sensitivity.
        max_fade = m.preset.fading_sigma_db * Z_MAX  # as RadioModel computes it
        sens = m.preset.sensitivity_dbm
        for lst in self.cells_around(cell):
            for r in lst:
                rid = r.node_id
                if rid == src:
                    continue
                d = hypot(r.x - x, r.y - y)
                if d > rng:
                    far_dist.append(r)
                    continue
                mean = mean_rssi(src, rid, d, txp)
                if mean + max_fade < sens:
                    far_loss.append(r)
                else:
                    near.append((r, r.counters, mean, link_hash(src, rid)))
        self._caches[src] = c
        self._by_cell.setdefault(cell, {})[src] = c
        return c

    def drop(self, src: int) -> None:
        """Forget ``src``'s cache (its bulk counts folded in first)."""
        c = self._caches.pop(src, None)
        if c is not None:
            c.flush()
            here = self._by_cell[c.cell]
            del here[src]
            if not here:
                del self._by_cell[c.cell]

    def touch(self, cell: Cell) -> None:
        """The static motes of ``cell`` changed: drop the caches of the senders
        within one cell of it (bulk counts folded in); they are rebuilt lazily."""
        cx, cy = cell
        by_cell = self._by_cell
        caches = self._caches
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                cs = by_cell.pop((cx + dx, cy + dy), None)
                if cs:
                    for src, c in cs.items():
                        c.flush()
                        del caches[src]

    def flush_all(self) -> None:
        """Fold every pending bulk count in (before counters are read)."""
        for c in self._caches.values():
            if c.pending:
                c.flush()

    def link(self, s: S, r: S, now: float) -> Link[S] | None:
        """``(r, distance, mean RSSI, fading link hash)`` of ``s -> r`` at ``now``
        if ``r`` listens to ``s``'s cell, else None. Cached for two static motes."""
        links = None
        if s.static and r.static:
            links = self.sender(s.node_id, s.x, s.y, s.tx_power).links
            if r.node_id in links:
                hit = links[r.node_id]
                if hit is None or hit[0] is r:  # not a mote re-added under the same id
                    return hit
        self.locate(s, now)
        self.locate(r, now)
        out: Link[S] | None = None
        if adjacent(r.cell, s.cell):
            d = math.hypot(r.x - s.x, r.y - s.y)
            m = self.model
            out = (
                r,
                d,
                m.mean_rssi(s.node_id, r.node_id, d, s.tx_power),
                m.fading_link_hash(s.node_id, r.node_id),
            )
        if links is not None:
            links[r.node_id] = out
        return out
