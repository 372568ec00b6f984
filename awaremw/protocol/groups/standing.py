"""Standing: one mote's place in the groups of one type.

The definition of the type, the mote's role and the group it is in (id,
leader, weight, newest beacon seq): what every part reads. Its methods are the
only writers, one per change the protocol makes.
"""

from __future__ import annotations

from awaremw.protocol.frames import GroupTypeDef
from awaremw.protocol.groups.values import MAX_WEIGHT, Role


class Standing:
    """The role and the group of one group type (read by every part)."""

    __slots__ = ("defn", "gid", "gtype", "leader", "role", "seq", "weight")

    def __init__(self, gtype: int, defn: GroupTypeDef) -> None:
        self.gtype = gtype
        self.defn = defn
        self.role = Role.IDLE
        self.gid = 0
        self.leader = 0
        self.weight = 0
        self.seq = 0

    def redefine(self, defn: GroupTypeDef) -> None:
        self.defn = defn

    def move_to(self, role: Role) -> None:
        """A role change that keeps the group (waiting, idle, handing over)."""
        self.role = role

    def join(self, role: Role, gid: int, leader: int, weight: int, seq: int) -> None:
        """Member or leader of group ``gid`` (its leader, weight and seq as known)."""
        self.role = role
        self.gid, self.leader, self.weight, self.seq = gid, leader, weight, seq

    def follow(self, seq: int, leader: int, weight: int) -> None:
        """A member heard a newer beacon of its group (maybe from a new claimant)."""
        self.seq, self.leader, self.weight = seq, leader, weight

    def catch_up(self, seq: int) -> None:
        """A leader heard a lighter claimant of its id with a newer seq: outnumber it."""
        self.seq = seq

    def gain(self, n: int) -> None:
        """The leader aggregated ``n`` readings of one epoch."""
        self.weight = min(self.weight + n, MAX_WEIGHT)

    def next_seq(self) -> int:
        """The leader's next beacon."""
        self.seq = (self.seq + 1) & 0xFFFF
        return self.seq
