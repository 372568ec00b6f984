"""The ``--mac`` and ``--collisions`` options shared by the virtual-clock benchmarks.

They choose the virtual medium's channel access and collision model
(``docs/radio.md``, "Medium access and collisions"); the defaults are the
deployment defaults, ``csma`` and ``sinr``. ``--collisions none --mac aloha``
is the medium as it was before airtime overlap existed.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from typing import Any

from awaremw.radio.counters import MoteCounters
from awaremw.radio.mac import COLLISION_MODES, MAC_KINDS


def add_medium_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mac", choices=MAC_KINDS, default="csma", help="medium access")
    parser.add_argument(
        "--collisions", choices=COLLISION_MODES, default="sinr", help="collision model"
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
