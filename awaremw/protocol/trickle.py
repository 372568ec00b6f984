"""Trickle (Levis et al., NSDI 2004; RFC 6206): a sans-IO, clock-free timer.

The caller feeds the current time and asks when to be woken; the object never
reads a clock. Semantics (RFC 6206, section 4.2):

* An interval ``I`` starts at ``t0``; the counter ``c`` is set to 0 and a
  transmission point ``t`` is drawn uniformly in ``[t0 + I/2, t0 + I)``.
* Hearing a consistent transmission increments ``c`` (:meth:`hear_consistent`).
* At ``t``, the caller transmits iff ``c < k`` (:meth:`handle_timer` returns True).
* At the end of the interval ``I`` doubles, up to ``tau_h``, and a new interval
  starts.
* An inconsistency (:meth:`reset`) sets ``I = tau_l`` and starts a new
  interval, unless ``I`` is already ``tau_l`` (then nothing changes: this is
  what keeps a burst of inconsistencies from resetting forever).

``tau_h`` is the largest interval in seconds (RFC 6206's ``Imax`` expressed as
a duration, as in Levis et al.'s tau_h), not a number of doublings.
"""

from __future__ import annotations

import random


class Trickle:
    """One Trickle timer. ``start`` it, then drive it with ``handle_timer``."""

    __slots__ = (
        "_counter",
        "_end",
        "_fire",
        "_fired",
        "_interval",
        "_rng",
        "k",
        "tau_h",
        "tau_l",
    )

    def __init__(self, tau_l: float, tau_h: float, k: int, rng: random.Random) -> None:
        if not tau_l > 0:
            raise ValueError(f"tau_l={tau_l} must be > 0")
        if not tau_h >= tau_l:
            raise ValueError(f"tau_h={tau_h} must be >= tau_l={tau_l}")
        if k < 1:
            raise ValueError(f"k={k} must be >= 1")
        self.tau_l = tau_l
        self.tau_h = tau_h
        self.k = k
        self._rng = rng
        self._interval: float | None = None  # None: not running
        self._counter = 0
        self._fire = 0.0  # transmission point of the current interval
        self._end = 0.0  # end of the current interval
        self._fired = False  # transmission point of this interval already handled

    # ------------------------------------------------------------------ state

    @property
    def running(self) -> bool:
        return self._interval is not None

    @property
    def interval(self) -> float | None:
        """Current interval length ``I`` (None when stopped)."""
        return self._interval

    @property
    def counter(self) -> int:
        return self._counter

    @property
    def interval_end(self) -> float | None:
        return self._end if self._interval is not None else None

    # ------------------------------------------------------------------ inputs

    def start(self, now: float) -> None:
        """(Re)start with the smallest interval beginning at ``now``."""
        self._begin(now, self.tau_l)

    def stop(self) -> None:
        self._interval = None

    def reset(self, now: float) -> None:
        """An inconsistency: back to ``tau_l`` unless already there (then no-op).

        A stopped timer is started.
        """
        if self._interval is None or self._interval > self.tau_l:
            self._begin(now, self.tau_l)

    def hear_consistent(self) -> None:
        """A neighbour said what we would have said: count it toward suppression."""
        self._counter += 1

    def next_deadline(self) -> float | None:
        """When :meth:`handle_timer` wants to be called (None when stopped)."""
        if self._interval is None:
            return None
        return self._end if self._fired else self._fire

    def handle_timer(self, now: float) -> bool:
        """Process what is due at ``now``; True iff the caller should transmit now.

        Calling early is harmless (returns False, changes nothing). A late call
        that passes both the transmission point and the interval's end still
        reports the transmission, then opens the next interval.
        """
        if self._interval is None:
            return False
        transmit = False
        if not self._fired and now >= self._fire:
            self._fired = True
            transmit = self._counter < self.k
        if now >= self._end:
            nxt = min(self._interval * 2.0, self.tau_h)
            # Start the next interval where this one ended; if the caller was
            # so late that it would end in the past too, start it at ``now``.
            self._begin(self._end if self._end + nxt > now else now, nxt)
        return transmit

    # ------------------------------------------------------------------ internals

    def _begin(self, t0: float, interval: float) -> None:
        self._interval = interval
        self._counter = 0
        self._fired = False
        self._fire = t0 + self._rng.uniform(interval / 2.0, interval)
        self._end = t0 + interval
