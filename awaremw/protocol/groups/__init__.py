"""Group management (paper II-A, IV-B, IV-C): membership, leaders, group trees.

Per defined group type a mote is in one of five roles:

``IDLE``          not in a group of this type (it still listens to leader beacons
                  and remembers the groups nearby, but does not forward them);
``WAITING``       qualifies, heard no group nearby, waits a random backoff before
                  creating one (joins at once if a beacon of the type arrives);
``MEMBER``        in a group: forwards each new beacon of it once, keeps a parent
                  in the group tree (fewest hops to the leader for the newest seq);
``LEADER``        beacons every ``beacon_period`` and reports to the gateway;
``HANDING_OVER``  a leader that stopped qualifying and is handing its group over.

In short: membership is checked every ``check_period`` with hysteresis; a
qualifying mote joins the heaviest group of its type heard, else creates one
after a random backoff and a tentative id announcement (so contention ends
before any mote holds the losing id); members forward only the heaviest group
they know; a leader that stops qualifying hands its group over; members that
lose the leader claim the group with its id (failover) or, later, create one
with a new id (the paper's split rule). Every rule, with the ties and choices
the paper leaves open: docs/protocol-groups.md, "Groups".

The package, in layers (a module imports only those above it in this list):

``values``       roles, public records, timer names, constants, pure rules
``standing``     Standing: a type's definition, role and group (id, leader, weight, seq)
``kit``          Kit: the shared services; Moves: the role changes a part may trigger
``conditions``   Conditions: qualifying, hysteresis, parking of the checks
``lineage``      Lineage: former and split ids (merge and split)
``pace``         Pace: the leader's beacons and reports, the interval members see
``tree``         GroupTree: parents, hop counts, upstream, link keys, children
``flood``        Flood: beacon forwarding and its suppression, rebuttals
``election``     Election: groups heard, waiting, tentative ids, creation
``liveness``     Liveness: leader_ok, suspicion, probes, claims, leader lost
``handover``     Handovers: candidates, handover and refusals
``roles``        Roles: the role changes (Moves) and the membership check
``merge``        Merge: beacons of the type (same group, switch, yield, rebut)
``coordinator``  Groups: the Component; routes frames, link results and timers
"""

from awaremw.protocol.groups.coordinator import Groups
from awaremw.protocol.groups.values import (
    ELECTION_BACKOFF_FACTOR,
    MAX_GROUP_ID,
    MAX_HOPS,
    MAX_WEIGHT,
    PARK_PERIODS,
    GroupStats,
    Membership,
    Role,
    condition_holds,
    condition_may_hold,
    heavier,
    seq_newer,
)

__all__ = [
    "ELECTION_BACKOFF_FACTOR",
    "MAX_GROUP_ID",
    "MAX_HOPS",
    "MAX_WEIGHT",
    "PARK_PERIODS",
    "GroupStats",
    "Groups",
    "Membership",
    "Role",
    "condition_holds",
    "condition_may_hold",
    "heavier",
    "seq_newer",
]
