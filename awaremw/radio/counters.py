"""Per-mote radio counters and the energy they imply.

Both media (the Zenoh medium and the virtual-clock driver) fill the same
counters with the same meaning; ``docs/radio.md`` ("Counters") defines each.
Energy counts airtime only: transmitting frames and ACKs, receiving frames
and ACKs. Idle listening and the MCU are not modelled (a deliberate
simplification: without a duty-cycled MAC the radio would listen all the time
and the budget would only measure wall time).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from awaremw.radio.model import RadioPreset


@dataclass(slots=True)
class MoteCounters:
    """What one mote's radio did. Bytes are our frame bytes (no PHY overhead)."""

    frames_tx: int = 0  # every attempt put on the air, retries included
    bytes_tx: int = 0
    frames_rx: int = 0  # frames received correctly (duplicates and malformed included)
    bytes_rx: int = 0
    dropped_distance: int = 0  # heard from a neighbouring cell but beyond max range
    dropped_loss: int = 0  # within range, lost by the PRR model (or below sensitivity)
    malformed: int = 0  # received but not decodable (reported by the core)
    unicast_ok: int = 0  # unicasts acknowledged (counted once, whatever the retries)
    unicast_failed: int = 0  # unicasts given up after max_retries
    retries: int = 0  # retransmissions of unicasts
    acks_tx: int = 0
    acks_rx: int = 0
    duplicates: int = 0  # retried unicasts received again (not passed to the core)
    refused: int = 0  # received but refused by link security (bad MIC, replay; radio/security.py)
    collisions: int = 0  # would have been received; lost to overlapping frames or own TX
    cca_busy: int = 0  # clear channel assessments that found the channel busy
    mac_drops: int = 0  # frames given up after too many busy assessments (channel access failure)

    def energy_mj(self, preset: RadioPreset, tx_power_dbm: float | None = None) -> float:
        """Radio energy in mJ: V * I * airtime, for TX (frames + ACKs) and RX (same)."""
        return self.tx_energy_mj(preset, tx_power_dbm) + self.rx_energy_mj(preset)

    def tx_energy_mj(self, preset: RadioPreset, tx_power_dbm: float | None = None) -> float:
        bits = 8 * (self.bytes_tx + self.frames_tx * preset.phy_overhead_bytes)
        bits += 8 * self.acks_tx * preset.ack_bytes
        return preset.voltage_v * preset.tx_current_at(tx_power_dbm) * bits / preset.bitrate_bps

    def rx_energy_mj(self, preset: RadioPreset) -> float:
        bits = 8 * (self.bytes_rx + self.frames_rx * preset.phy_overhead_bytes)
        bits += 8 * self.acks_rx * preset.ack_bytes
        return preset.voltage_v * preset.rx_current_ma * bits / preset.bitrate_bps

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    def add(self, other: MoteCounters) -> None:
        """Accumulate ``other`` into this one (for totals)."""
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))


@dataclass(slots=True)
class Battery:
    """A radio energy budget; the mote is dead once it has spent it."""

    budget_mj: float

    def __post_init__(self) -> None:
        if not self.budget_mj > 0:
            raise ValueError(f"battery budget must be > 0 mJ, got {self.budget_mj}")

    def remaining_mj(
        self, counters: MoteCounters, preset: RadioPreset, tx_power_dbm: float | None = None
    ) -> float:
        return self.budget_mj - counters.energy_mj(preset, tx_power_dbm)

    def is_dead(
        self, counters: MoteCounters, preset: RadioPreset, tx_power_dbm: float | None = None
    ) -> bool:
        return self.remaining_mj(counters, preset, tx_power_dbm) <= 0.0
