"""Fires that merge and split: the group id rules of the paper's section II-A.

Runs ``nodes/fire.toml`` and checks, against the ground truth (the connected
regions of motes whose noise-free temperature is over the threshold):

* while there are two fires, each is one group with its own id;
* after they merge, one group whose id is one of the two (``merge_single_id``,
  ``merge_id_inherited``);
* after the split, the part holding the merged group's leader keeps its id and
  the other part has a new one (``split_leader_part_keeps_id``,
  ``split_new_id``);

plus the common metrics (membership F1, records, traffic). Figures:
``fire_snapshots.png`` (groups over the temperature field at the phases) and
``fire_membership.png``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from awaremw.experiments import metrics as M
from awaremw.experiments import plots
from awaremw.experiments.metrics import RunResult
from awaremw.experiments.scenario import Scenario
from awaremw.experiments.truth import GroundTruth

IDEAL_IDS = 3  # two fires, then the id of the part that split off
MIN_REGION = 2  # motes: smaller true regions are not counted as fires


@dataclass(frozen=True, slots=True)
class PhaseView:
    """At one instant: each true region (largest first) with its majority group id."""

    t: float
    regions: tuple[frozenset[int], ...]
    gids: tuple[int | None, ...]
    leaders: dict[int, int]  # gid -> leader node


def phase_view(
    rec: M.Recorder, truth: GroundTruth, sc: Scenario, t: float, settle: float
) -> PhaseView:
    defn = sc.group_def()
    gtype = sc.tracking_group
    regions = tuple(r for r in truth.regions(defn, t, sc.sensors) if len(r) >= MIN_REGION)
    members = rec.members_at(gtype, t + settle)
    gids: list[int | None] = []
    for r in regions:
        c = Counter(members[n].gid for n in r if n in members)
        gids.append(c.most_common(1)[0][0] if c else None)
    return PhaseView(t, regions, tuple(gids), rec.leaders_at(gtype, t + settle))


def _majority(values: Sequence[Any]) -> Any:
    c = Counter(v for v in values if v is not None)
    return c.most_common(1)[0][0] if c else None


def analyse(result: RunResult, out: Path) -> dict[str, Any]:
    a = M.scored(result)
    sc, rec, truth, gtype, defn = a.sc, a.rec, a.truth, a.gtype, a.defn
    settle, end, t0 = a.settle, a.end, a.t0

    def views(key: str) -> list[PhaseView]:
        a, b = (float(x) for x in sc.get(key, [0.0, 0.0]))
        return [phase_view(rec, truth, sc, t, settle) for t in M.instants(a, min(b, end), 1.0)]

    two, merged, split = views("two_fires_s"), views("merged_s"), views("split_s")

    # Two fires: two regions, two distinct ids (each region's id over the phase).
    two_ok = [v for v in two if len(v.regions) == 2]
    fire_ids = (
        _majority([v.gids[0] for v in two_ok]),
        _majority([v.gids[1] for v in two_ok]),
    )
    two_distinct = bool(two_ok) and None not in fire_ids and fire_ids[0] != fire_ids[1]
    two_frac = sum(1 for v in two if len(v.regions) == 2 and len(set(v.gids)) == 2 and
                   None not in v.gids) / max(1, len(two))  # fmt: skip

    # Merged: one region, one id, one of the two.
    merged_one = [v for v in merged if len(v.regions) == 1]
    merged_id = _majority([v.gids[0] for v in merged_one])
    end_view = merged[-1] if merged else None
    ids_at_end = (
        set() if end_view is None else
        {s.gid for s in rec.members_at(gtype, end_view.t + settle).values()}
    )  # fmt: skip
    merge_single = end_view is not None and len(end_view.regions) == 1 and ids_at_end == {merged_id}
    merge_frac = sum(
        1
        for v in merged
        if len(v.regions) == 1
        and {s.gid for n, s in rec.members_at(gtype, v.t + settle).items() if n in v.regions[0]}
        == {merged_id}
    ) / max(1, len(merged))
    merged_leader = None
    if end_view is not None and merged_id is not None:
        merged_leader = end_view.leaders.get(merged_id)

    # Split: two regions; the leader's part keeps the id, the other gets a new one.
    split_two = [v for v in split if len(v.regions) == 2]
    last = split_two[-1] if split_two else None
    keep_ok = new_ok = fresh = False
    leader_part: int | None = None
    split_ids: list[int | None] = []
    if last is not None:
        split_ids = list(last.gids)
        leader_now = last.leaders.get(merged_id) if merged_id is not None else None
        for i, r in enumerate(last.regions):
            if leader_now is not None and leader_now in r:
                leader_part = i
        if leader_part is not None:
            other = 1 - leader_part
            keep_ok = last.gids[leader_part] == merged_id
            new_ok = last.gids[other] is not None and last.gids[other] != merged_id
            fresh = new_ok and last.gids[other] not in fire_ids
        else:
            # The merged leader is gone: both parts must have new ids.
            new_ok = all(g is not None and g != merged_id for g in last.gids)
    metrics = a.metrics()
    metrics |= {
        "merges_yielded": len([y for y in rec.yields if y[2] == gtype]),
        "first_fire_sensed_s": t0,
        "fire_ids_before_merge": list(fire_ids),
        "two_fires_distinct_ids": two_distinct,
        "two_fires_instants_ok": two_frac,
        "merged_id": merged_id,
        "merged_leader": merged_leader,
        "merge_single_id": merge_single,
        "merge_id_inherited": merged_id is not None and merged_id in fire_ids,
        "merged_instants_ok": merge_frac,
        "split_ids": split_ids,
        "split_leader_part_keeps_id": keep_ok,
        "split_new_id": new_ok,
        "split_new_id_fresh": fresh,
    }
    out.mkdir(parents=True, exist_ok=True)
    snaps = [float(t) for t in sc.get("snapshots_s", [])]
    labels = _labels(sc, snaps)
    thr = sc.group_def().conditions[0].value
    plots.field_snapshots(
        out / "fire_snapshots.png", rec, truth, sc.world, gtype, defn, snaps, sc.sensors,
        sc.field, threshold=thr, titles=labels, settle=settle,
    )  # fmt: skip
    plots.membership_sizes(
        out / "fire_membership.png", a.series,
        title=f"Fire group members vs truth (members compared {settle:g} s later)",
    )  # fmt: skip
    return M.rounded(metrics)


def _labels(sc: Scenario, times: Sequence[float]) -> dict[float, str]:
    phases = [
        (float(sc.get(key, [0.0, -1.0])[0]), float(sc.get(key, [0.0, -1.0])[1]), label)
        for key, label in (("two_fires_s", "two fires"), ("merged_s", "merged"),
                           ("split_s", "split"))
    ]  # fmt: skip
    out: dict[float, str] = {}
    for t in times:
        for k, (a, b, label) in enumerate(phases):
            if a <= t <= b:
                out[t] = f"({label})"
            elif k + 1 < len(phases) and b < t < phases[k + 1][0]:
                out[t] = "(merging)" if k == 0 else "(splitting)"
    return out
