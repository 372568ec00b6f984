"""Counted, rate-limited reports of rejected input and of contained faults.

Two kinds of events end here, never in a traceback that kills a process:

* a **rejection**: bytes heard on a radio key that are not a valid envelope or
  frame (a remote fault: counted per reason, dropped);
* a **fault**: an exception that escaped a mote handler or a Zenoh callback
  (our bug, contained by the last guard so that one mote's bug does not stop
  the fleet; counted per place and exception type, logged with its traceback
  the first time).

Logging is rate-limited: the first event of a reason is logged at once, then
at most one summary line per reason every :data:`LOG_EVERY_S` wall seconds
(``"<reason>: N more in the last 10 s"``), so garbage at line rate cannot
flood the log. Counts are plain integers (``as_dict``), shown by
``awaremw fleet-ctl stats``.

Bound: at most :data:`MAX_REASONS` distinct reasons are kept per log; further
ones are counted under ``"other"`` (reasons come from fixed tags and
exception type names, so the bound is not expected to be reached).
Thread-safe: Zenoh callbacks report from Zenoh's threads.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

MAX_REASONS = 64
LOG_EVERY_S = 10.0
OTHER = "other"


class FaultLog:
    """Per-reason counters with rate-limited logging (one per process and purpose)."""

    __slots__ = ("_clock", "_counts", "_lock", "_log", "_logged", "_pending", "level", "what")

    def __init__(
        self,
        what: str,
        logger: logging.Logger,
        level: int = logging.WARNING,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.what = what  # "rejected envelope", "fault", ...
        self.level = level
        self._log = logger
        self._clock = clock
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}  # bound: MAX_REASONS + 1 keys
        self._logged: dict[str, float] = {}  # same keys: wall time of the last line
        self._pending: dict[str, int] = {}  # same keys: events not yet in a log line

    def count(self, reason: str, detail: str = "", exc: BaseException | None = None) -> None:
        """One more event of ``reason``; log it (rate-limited)."""
        now = self._clock()
        with self._lock:
            if reason not in self._counts and len(self._counts) >= MAX_REASONS:
                reason = OTHER
            self._counts[reason] = self._counts.get(reason, 0) + 1
            last = self._logged.get(reason)
            if last is not None and now - last < LOG_EVERY_S:
                self._pending[reason] = self._pending.get(reason, 0) + 1
                return
            self._logged[reason] = now
            more = self._pending.pop(reason, 0)
        if last is None:
            self._log.log(self.level, "%s (%s): %s", self.what, reason, detail[:200], exc_info=exc)
        else:
            self._log.log(
                self.level,
                "%s (%s): %d more in the last %.0f s; latest: %s",
                self.what, reason, more + 1, now - last, detail[:200],
            )  # fmt: skip

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())

    def as_dict(self) -> dict[str, int]:
        with self._lock:
            return dict(sorted(self._counts.items()))

    def get(self, reason: str) -> int:
        with self._lock:
            return self._counts.get(reason, 0)
