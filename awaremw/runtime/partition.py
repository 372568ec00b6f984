"""How a launcher spreads a deployment over worker processes: node filters
(:class:`XStripe` along x, or :class:`IdModulo` for benchmarks)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from awaremw.runtime.deployment import Deployment, NodeSpec


@dataclass(frozen=True, slots=True)
class XStripe:
    """Node filter: motes whose position (first waypoint) has ``lo <= x < hi``."""

    lo: float
    hi: float

    def __call__(self, spec: NodeSpec) -> bool:
        return self.lo <= spec.position[0] < self.hi


@dataclass(frozen=True, slots=True)
class IdModulo:
    """Node filter: motes with ``id % n == k`` (the worst case for cross-process
    traffic: neighbours mostly live in other processes; benchmarks only)."""

    k: int
    n: int

    def __call__(self, spec: NodeSpec) -> bool:
        return spec.id % self.n == self.k


@dataclass(frozen=True, slots=True)
class WorkerFilter:
    """A worker's node filter: its stripe, minus the excluded kinds (picklable)."""

    stripe: XStripe | IdModulo
    exclude_kinds: frozenset[str] = frozenset()

    def __call__(self, spec: NodeSpec) -> bool:
        return spec.kind not in self.exclude_kinds and self.stripe(spec)


Layout = Literal["stripes", "interleaved"]


def partition(
    deployment: Deployment, n: int, layout: Layout = "stripes"
) -> list[XStripe | IdModulo]:
    """The node filters of ``n`` workers."""
    if layout == "interleaved":
        return [IdModulo(k, n) for k in range(n)]
    return list(stripes(deployment, n))


def stripes(deployment: Deployment, n: int) -> list[XStripe]:
    """Split the deployment into ``n`` stripes along x holding about as many motes each.

    Motes with the same x always fall in the same stripe; the first and last
    stripes are open-ended, so motes added later anywhere have an owner.
    """
    if n < 1:
        raise ValueError("need at least one stripe")
    xs = sorted(spec.position[0] for spec in deployment.nodes)
    cuts: list[float] = []
    for k in range(1, n):
        x = xs[min(len(xs) - 1, (k * len(xs)) // n)]
        if x > (cuts[-1] if cuts else xs[0]):  # no empty stripe in front
            cuts.append(x)
    bounds = [-math.inf, *cuts, math.inf]
    out = [XStripe(bounds[i], bounds[i + 1]) for i in range(len(bounds) - 1)]
    while len(out) < n:  # fewer distinct x than processes: empty stripes
        out.append(XStripe(math.inf, math.inf))
    return out
