"""Kept for existing imports: the emulated clock lives in :mod:`awaremw.world.clock`
(below the radio, which reads it)."""

from awaremw.world.clock import EmulatedClock

__all__ = ["EmulatedClock"]
