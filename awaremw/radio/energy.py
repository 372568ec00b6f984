"""Radio energy a user can read: per mote and per role, per hour, and what it
means for a mote on two AA cells (docs/energy.md).

The counters (radio/counters.py) give each mote's radio energy in mJ (airtime
of frames and ACKs sent and received) and its frames sent. Over a window of
``seconds`` they become rates: mJ per hour and frames per hour. A mote's role
in the window is what it did for the middleware:

``leader``     led a group (aggregates its group, beacons, sends the records);
``member``     was in a group (samples, sends partials, forwards beacons);
``forwarder``  in no group, but acknowledged unicasts: collection data (records,
               reports) went through it towards the gateway;
``idle``       none of these: it only keeps the control plane (CTP beacons,
               Drip) and hears its neighbours.

Lifetime on two AA cells (2 x 1.5 V x 2,500 mAh = 27 kJ) is given twice:
``lifetime_days_traffic`` counts only the modelled radio traffic (the
middleware's own share: an upper bound), ``lifetime_days_lpl`` adds the
listening a duty-cycled MAC costs whatever the traffic: the radio on for
``LPL_DUTY`` (1 %) of the time at its receive current (low-power listening
as in TinyOS's BoX-MAC; the MCU and sensors are left out).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from enum import Enum

from awaremw.radio.model import RadioPreset

AA2_MJ = 2 * 1.5 * 2500.0 * 3.6 * 1000.0  # two AA cells in series, 2,500 mAh: 27 kJ in mJ
LPL_DUTY = 0.01  # fraction of time a low-power-listening radio is on to check the channel


class EnergyRole(Enum):
    LEADER = "leader"
    MEMBER = "member"
    FORWARDER = "forwarder"
    IDLE = "idle"


def role_of(leader: bool, member: bool, acks_tx: int) -> EnergyRole:
    """A mote's role in a window: led a group, was in one, acknowledged unicasts
    (``acks_tx`` in the window: data was routed through it), or none."""
    if leader:
        return EnergyRole.LEADER
    if member:
        return EnergyRole.MEMBER
    return EnergyRole.FORWARDER if acks_tx > 0 else EnergyRole.IDLE


def listen_mj_per_hour(preset: RadioPreset, duty: float = LPL_DUTY) -> float:
    """What a duty-cycled MAC's channel checks cost per hour, traffic aside."""
    return duty * preset.voltage_v * preset.rx_current_ma * 3600.0  # mW x s = mJ


def lifetime_days(mj_per_hour: float, floor_mj_per_hour: float = 0.0) -> float | None:
    """Days two AA cells last at this rate (None: nothing spent)."""
    rate = mj_per_hour + floor_mj_per_hour
    return None if rate <= 0 else AA2_MJ / rate / 24.0


@dataclass(frozen=True, slots=True)
class MoteEnergy:
    """One mote over a window: its role, radio energy (mJ) and frames sent."""

    node: int
    role: EnergyRole
    mj: float
    frames: int


@dataclass(frozen=True, slots=True)
class RoleEnergy:
    """The motes of one role over a window, as rates per hour."""

    motes: int
    mj_per_hour: float  # mean over the motes
    mj_per_hour_max: float
    frames_per_hour: float  # mean
    frames_per_hour_max: float
    lifetime_days_traffic: float | None  # of the role's most spending mote
    lifetime_days_lpl: float | None  # ... with the listening floor

    def as_dict(self) -> dict[str, float | int | None]:
        def r(v: float | None, n: int) -> float | None:
            return None if v is None else round(v, n)

        return {
            "motes": self.motes,
            "mj_per_hour": r(self.mj_per_hour, 2),
            "mj_per_hour_max": r(self.mj_per_hour_max, 2),
            "frames_per_hour": r(self.frames_per_hour, 1),
            "frames_per_hour_max": r(self.frames_per_hour_max, 1),
            "lifetime_days_traffic": r(self.lifetime_days_traffic, 0),
            "lifetime_days_lpl": r(self.lifetime_days_lpl, 0),
        }


def by_role(
    motes: Iterable[MoteEnergy], seconds: float, preset: RadioPreset
) -> dict[EnergyRole, RoleEnergy]:
    """Per-role rates over a window of ``seconds`` (roles without motes left out)."""
    if not seconds > 0:
        raise ValueError(f"window must be > 0 s, got {seconds}")
    per_hour = 3600.0 / seconds
    floor = listen_mj_per_hour(preset)
    groups: dict[EnergyRole, list[MoteEnergy]] = {}
    for m in motes:
        groups.setdefault(m.role, []).append(m)
    out: dict[EnergyRole, RoleEnergy] = {}
    for role in EnergyRole:
        ms = groups.get(role)
        if not ms:
            continue
        mj = [m.mj * per_hour for m in ms]
        fr = [m.frames * per_hour for m in ms]
        worst = max(mj)
        out[role] = RoleEnergy(
            len(ms),
            sum(mj) / len(ms),
            worst,
            sum(fr) / len(ms),
            max(fr),
            lifetime_days(worst),
            lifetime_days(worst, floor),
        )
    return out


def role_table(
    motes: Iterable[MoteEnergy], seconds: float, preset: RadioPreset
) -> dict[str, dict[str, float | int | None]]:
    """:func:`by_role` as JSON-ready dicts keyed by role name."""
    return {r.value: e.as_dict() for r, e in by_role(motes, seconds, preset).items()}
