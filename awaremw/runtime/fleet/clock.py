"""Keeping a fleet on the network's emulated time: the earliest origin wins.

Every process of an emulation anchors emulated time 0 at one wall instant (its
clock's ``start_wall``). A launcher gives its workers one; a gateway joining
running fleets asks them for theirs. A process started *under* running peers
without that (a fleet restarted under a running gateway, a gateway whose
fleets did not answer in time) would count from 0 while its peers are at
minutes: its medium refuses every frame of theirs as starting in the future
("early"), and it hears nobody until its own clock catches up -- about 110 s
for a fleet restarted under a gateway that had run that long.

So a fleet listens to what its medium refuses as early. Each such frame says
how far ahead the sender's clock is, hence the origin the sender counts from.
Once :data:`CONFIRM` early frames agree on an earlier origin (within
:data:`AGREE_S` wall seconds: one stray frame moves nothing), the clock is
re-anchored there and the fleet's motes re-arm their timers on it. Origins only
ever move earlier, so every process ends on the earliest one and none moves
twice for the same peer. Under ``--secrets`` only fleet and gateway accounts may
put on the radio, so only they can move a clock.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable

from awaremw.world.clock import EmulatedClock

log = logging.getLogger(__name__)

CONFIRM = 3  # early frames that must agree before the clock moves
AGREE_S = 0.5  # wall seconds within which their implied origins agree
WINDOW_S = 5.0  # wall seconds an early frame counts as evidence
# The agreeing frames must span this much wall time: a running peer's frames
# keep implying the same origin as time goes on, while envelopes that all carry
# one fixed time (a fuzzer's, a replay burst) imply an origin that drifts with
# the wall clock, and never agree for this long (they moved a fleet 18 h ahead).
MIN_SPAN_S = 1.0
MAX_EVIDENCE = 256  # early frames remembered (a flood of them is bounded)


class ClockSync:
    """Moves ``clock``'s origin to an earlier one its peers demonstrably use.

    ``on_early(ahead)`` is fed by the medium with every frame refused for
    starting ``ahead`` emulated seconds in our future; ``on_jump(ahead)`` is
    called after the clock moved forward by ``ahead`` emulated seconds (the
    fleet re-arms its motes). Inactive until :meth:`activate` (a launcher's
    worker learns the shared origin first).
    """

    def __init__(
        self,
        name: str,
        clock: EmulatedClock,
        on_jump: Callable[[float], None],
        wall: Callable[[], float] = time.monotonic,
    ) -> None:
        self.name = name
        self.clock = clock
        self.on_jump = on_jump
        self.wall = wall
        self.active = False
        self.jumps = 0
        self._seen: deque[tuple[float, float]] = deque(maxlen=MAX_EVIDENCE)  # (wall, origin)

    def activate(self) -> None:
        self.active = True

    def on_early(self, ahead: float) -> None:
        """A frame heard starting ``ahead`` emulated seconds after our now."""
        if not self.active or not ahead > 0:
            return
        now = self.wall()
        # The sender's origin, as far as this frame tells (its transit makes it
        # look a little later than it is; the earliest of the agreeing ones wins).
        origin = self.clock.start_wall - ahead / self.clock.speed
        seen = self._seen
        seen.append((now, origin))
        while seen and now - seen[0][0] > WINDOW_S:
            seen.popleft()
        agree = [(w, o) for w, o in seen if abs(o - origin) <= AGREE_S]
        if len(agree) < CONFIRM or agree[-1][0] - agree[0][0] < MIN_SPAN_S:
            return
        target = min(o for _, o in agree)
        seen.clear()
        if target >= self.clock.start_wall:
            return
        jump = (self.clock.start_wall - target) * self.clock.speed
        self.clock.restart(target)
        self.jumps += 1
        log.warning(
            "fleet %s: its peers' emulated time is %.1f s ahead (this process started under "
            "running peers); joining it",
            self.name,
            jump,
        )
        self.on_jump(jump)
