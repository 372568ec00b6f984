"""The medium options shared by the virtual-clock benchmarks.

``--mac`` and ``--collisions`` choose the virtual medium's channel access and
collision model (``docs/radio.md``, "Medium access and collisions"); the
defaults are the deployment defaults, ``csma`` and ``sinr``. ``--collisions
none --mac aloha`` is the medium as it was before airtime overlap existed.
``--noise`` and ``--hardware-variance`` are the deployment keys of the same
names (``docs/radio.md``, "Noise" and "Hardware variance").
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from typing import Any

from awaremw.radio.counters import MoteCounters
from awaremw.radio.environment import RadioSettings
from awaremw.radio.mac import COLLISION_MODES, MAC_KINDS


def add_medium_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mac", choices=MAC_KINDS, default="csma", help="medium access")
    parser.add_argument(
        "--collisions", choices=COLLISION_MODES, default="sinr", help="collision model"
    )


def add_radio_arguments(parser: argparse.ArgumentParser) -> None:
    """``--noise`` and ``--hardware-variance``, as the deployment keys (docs/radio.md)."""
    parser.add_argument(
        "--noise",
        default="white",
        help="white (default: the preset's floor), a shipped trace (meyer-heavy) or a trace file",
    )
    parser.add_argument(
        "--hardware-variance",
        action="store_true",
        help="per-mote TX power and noise floor offsets (asymmetric links)",
    )


def radio_of(args: argparse.Namespace) -> RadioSettings:
    """The radio's realism from parsed arguments (today's radio when absent)."""
    return RadioSettings(
        str(getattr(args, "noise", "white")), bool(getattr(args, "hardware_variance", False))
    )


def medium_of(args: argparse.Namespace) -> tuple[str, str]:
    """``(mac, collisions)`` from parsed arguments (defaults when absent)."""
    return str(getattr(args, "mac", "csma")), str(getattr(args, "collisions", "sinr"))


def mac_totals(counters: Iterable[MoteCounters]) -> dict[str, Any]:
    """Sums of the MAC counters: ``collisions``, ``cca_busy``, ``mac_drops``."""
    out = {"collisions": 0, "cca_busy": 0, "mac_drops": 0}
    for c in counters:
        out["collisions"] += c.collisions
        out["cca_busy"] += c.cca_busy
        out["mac_drops"] += c.mac_drops
    return out
