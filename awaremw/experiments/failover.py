"""Leader failover: a stable group whose leader is killed at a known time.

Runs ``nodes/failover.toml`` on the virtual clock. At ``kill_at_s``
(:func:`prepare` schedules it) the mote that leads the tracking group then is
killed. The metrics, besides the common ones:

* ``victim``, ``group_id_at_kill``: the killed leader and its group's id;
* ``new_leader``, ``new_leader_cause``: the first mote to lead a group of the
  type after the kill (a failover claim, or a new group);
* ``failover_s`` / ``failover_epochs``: time from the kill to that leader, in
  seconds and in channel periods (None: no new leader);
* ``id_kept``: the new leader leads the same id, and at the end of the run the
  motes of the type are in that one group (no second group);
* ``second_group``: some mote was in another group of the type after the kill;
* ``leaders_at_end``: the leaders then (one, of the kept id).

Figure: ``failover_membership.png`` (group size against the truth).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from awaremw.experiments import metrics as M
from awaremw.experiments import plots
from awaremw.experiments.metrics import RunResult
from awaremw.experiments.virtual import VirtualRun
from awaremw.protocol.mote import AwareMote

IDEAL_IDS = 1  # the id survives its leader


def kill_at(run: VirtualRun) -> float:
    return float(run.scenario.get("kill_at_s", run.scenario.duration / 2))


def prepare(run: VirtualRun) -> None:
    """Schedule the kill of the tracking group's leader at ``kill_at_s``."""
    gtype = run.scenario.tracking_group

    def kill() -> None:
        for node, core in sorted(run.cores.items()):
            if not isinstance(core, AwareMote) or not run.net.alive(node):
                continue
            m = core.groups.membership(gtype)
            if m is not None and m.is_leader:
                run.net.kill(node, "failover experiment")
                return

    run.net.call_at(kill_at(run), kill)


def analyse(result: RunResult, out: Path) -> dict[str, Any]:
    a = M.scored(result)
    sc, rec, gtype = a.sc, a.rec, a.gtype
    t_kill = float(sc.get("kill_at_s", sc.duration / 2))
    period = sc.channel_def().period_ms / 1000.0

    killed = [n for n, t in rec.down.items() if abs(t - t_kill) < 1e-6]
    victim = killed[0] if killed else None
    gid = None
    if victim is not None:
        st = rec.state_at(victim, gtype, t_kill - 1e-6)
        gid = None if st is None else st.gid
    after = sorted(
        (e for e in rec.elections if e.group_type == gtype and e.t >= t_kill),
        key=lambda e: e.t,
    )
    first = after[0] if after else None
    failover_s = None if first is None else first.t - t_kill
    later_ids = rec.group_ids(gtype, t_kill, result.duration)
    final = rec.groups_at(gtype, result.duration)
    leaders_end = rec.leaders_at(gtype, result.duration)
    id_kept = (
        gid is not None
        and first is not None
        and first.group_id == gid
        and set(final) == {gid}
        and set(leaders_end) == {gid}
    )
    metrics = a.metrics()
    metrics |= {
        "kill_at_s": t_kill,
        "victim": victim,
        "group_id_at_kill": gid,
        "new_leader": None if first is None else first.node,
        "new_leader_cause": None if first is None else first.cause,
        "failover_s": failover_s,
        "failover_epochs": None if failover_s is None else failover_s / period,
        "id_kept": id_kept,
        "second_group": bool(later_ids - {gid}),
        "ids_after_kill": sorted(later_ids),
        "leaders_at_end": {str(g): n for g, n in sorted(leaders_end.items())},
    }
    out.mkdir(parents=True, exist_ok=True)
    plots.membership_sizes(
        out / "failover_membership.png", a.series,
        title=f"Group size vs truth; leader killed at {t_kill:g} s",
    )  # fmt: skip
    return M.rounded(metrics)
