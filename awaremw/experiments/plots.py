"""Figures of the experiments (matplotlib, Agg: no display needed).

* :func:`tracking_snapshots`: the group tracking the robot, a sequence of
  panels like the paper's Fig. 8;
* :func:`rssi_traces`: RSSI of the robot's beacons at some motes against the
  membership threshold, like Fig. 9;
* :func:`field_snapshots`: groups over a field (fire merge and split);
* :func:`membership_sizes`: group size against the true member count over time.

Figures are built with :class:`matplotlib.figure.Figure` (no pyplot state), so
they can be drawn from any thread.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from awaremw.experiments.metrics import Instant, Recorder
from awaremw.experiments.truth import GroundTruth
from awaremw.protocol.attributes import unit_of
from awaremw.protocol.frames import GroupTypeDef
from awaremw.world.fields import World

Area = tuple[float, float, float, float]  # xmin, xmax, ymin, ymax
_PALETTE = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
    "#8c564b", "#e377c2", "#bcbd22", "#17becf", "#7f7f7f",
)  # fmt: skip


class GroupColours:
    """A stable colour per group id (first come, first served)."""

    def __init__(self) -> None:
        self._map: dict[int, str] = {}

    def __call__(self, gid: int) -> str:
        if gid not in self._map:
            self._map[gid] = _PALETTE[len(self._map) % len(_PALETTE)]
        return self._map[gid]


# Print size: at 150 dpi a panel is about 6-7 cm wide on paper; these sizes stay
# readable there (axis labels and legends at 8-10 pt, titles 11 pt).
DPI = 150
FS_TICK = 8
FS_LABEL = 9
FS_LEGEND = 8
FS_TITLE = 11


def _save(fig: Figure, path: Path, dpi: int = DPI) -> Path:
    FigureCanvasAgg(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def _grid(n: int) -> tuple[int, int]:
    cols = 3 if n > 4 else min(n, 2) if n > 1 else 1
    rows = -(-n // cols)
    return rows, cols


def _draw_motes(
    ax: object,
    rec: Recorder,
    truth: GroundTruth,
    gtype: int,
    t: float,
    ids: Sequence[int],
    colours: GroupColours,
    true_members: frozenset[int],
    labels: bool = True,
) -> None:
    from matplotlib.axes import Axes

    assert isinstance(ax, Axes)
    members = rec.members_at(gtype, t)
    # One scatter per look (not per mote): 1,024 motes draw in a blink. Markers
    # shrink with the mote count so that a large field stays legible.
    k = min(1.0, LABELLED_MOTES / max(1, len(ids)))
    looks: dict[tuple[str, bool], tuple[list[float], list[float], list[str]]] = {}
    for n in ids:
        x, y = truth.position(n, t)
        st = members.get(n)
        look = ("#dddddd", False) if st is None or st.gid is None else (colours(st.gid), st.leader)
        xs, ys, rings = looks.setdefault(look, ([], [], []))
        xs.append(x)
        ys.append(y)
        rings.append("black" if n in true_members else "none")
        if labels and len(ids) <= LABELLED_MOTES:
            label = ax.annotate(str(n), (x, y), xytext=(4, 4), textcoords="offset points",
                                fontsize=FS_TICK, annotation_clip=True)  # fmt: skip
            label.set_in_layout(False)  # the axes fit the motes; labels need no layout pass
    for (colour, leader), (xs, ys, rings) in looks.items():
        plain = colour == "#dddddd"
        size = 70 if plain else 240 if leader else 90
        ax.scatter(
            xs, ys, s=size * k, c=colour, marker="*" if leader else "o", edgecolors=rings,
            linewidths=1.6 * k**0.5, zorder=2 if plain else 3,
        )  # fmt: skip


LABELLED_MOTES = 100  # above this many motes, no id labels and smaller markers


def _legend(
    ax: object,
    rec: Recorder,
    gtype: int,
    t: float,
    colours: GroupColours,
    extra: Sequence[Any] = (),
) -> None:
    from matplotlib.axes import Axes
    from matplotlib.lines import Line2D

    assert isinstance(ax, Axes)
    handles = [
        Line2D([], [], marker="o", ls="", color=colours(gid), label=f"group {gid}")
        for gid in sorted(rec.groups_at(gtype, t))
    ]
    handles.append(Line2D([], [], marker="*", ls="", color="k", ms=10, label="leader"))
    handles.append(Line2D([], [], marker="o", ls="", mfc="none", mec="k", label="true member"))
    handles.extend(extra)
    ax.legend(handles=handles, loc="upper right", fontsize=FS_LEGEND, framealpha=0.85)


def _axes_in_metres(ax: Any) -> None:
    ax.set_xlabel("x (m)", fontsize=FS_LABEL)
    ax.set_ylabel("y (m)", fontsize=FS_LABEL)
    ax.tick_params(labelsize=FS_TICK)


def tracking_snapshots(
    path: Path,
    rec: Recorder,
    truth: GroundTruth,
    gtype: int,
    defn: GroupTypeDef,
    times: Sequence[float],
    ids: Sequence[int],
    robot: int,
    area: Area,
    settle: float = 0.0,
    title: str = "Group tracking the robot",
    window_m: float | None = None,
) -> Path:
    """Panels at ``times``: motes coloured by group id, leaders as stars, true
    members (noise-free RSSI over the threshold) ringed, the robot and its trail.
    ``window_m``: each panel shows only the square of that half-side around the
    robot (within ``area``), for fields too large to see a group in."""
    rows, cols = _grid(len(times))
    fig = Figure(figsize=(4.6 * cols, 4.2 * rows), layout="constrained")
    colours = GroupColours()
    for k, t in enumerate(times):
        ax = fig.add_subplot(rows, cols, k + 1)
        rx, ry = truth.position(robot, t)
        view = area if window_m is None else _window(area, rx, ry, window_m)
        shown = ids if window_m is None else [n for n in ids if _inside(view, truth.position(n, t))]
        _draw_motes(ax, rec, truth, gtype, t + settle, shown, colours,
                    truth.members(defn, t, ids))  # fmt: skip
        trail = [truth.position(robot, t * i / 40) for i in range(41)]
        ax.plot([p[0] for p in trail], [p[1] for p in trail], "--", color="#cc0000", lw=0.8)
        ax.scatter([rx], [ry], marker="^", s=120, c="#cc0000", zorder=4)
        ax.set_xlim(view[0] - 1.5, view[1] + 1.5)
        ax.set_ylim(view[2] - 1.5, view[3] + 1.5)
        ax.set_aspect("equal")
        ax.set_title(f"t = {t:.0f} s", fontsize=FS_TITLE)
        _axes_in_metres(ax)
        if k == 0:
            robot_h = Line2D([], [], marker="^", ls="--", color="#cc0000", label="robot, trail")
            _legend(ax, rec, gtype, t + settle, colours, extra=[robot_h])
    fig.suptitle(title, fontsize=FS_TITLE + 1)
    return _save(fig, path)


def _window(area: Area, x: float, y: float, half: float) -> Area:
    """The square of half-side ``half`` around (x, y), moved to lie within ``area``."""

    def span(lo: float, hi: float, c: float) -> tuple[float, float]:
        if hi - lo <= 2 * half:
            return lo, hi
        a = min(max(c - half, lo), hi - 2 * half)
        return a, a + 2 * half

    x0, x1 = span(area[0], area[1], x)
    y0, y1 = span(area[2], area[3], y)
    return (x0, x1, y0, y1)


def _inside(a: Area, p: tuple[float, float]) -> bool:
    return a[0] - 2.0 <= p[0] <= a[1] + 2.0 and a[2] - 2.0 <= p[1] <= a[3] + 2.0


def rssi_traces(
    path: Path,
    rec: Recorder,
    truth: GroundTruth,
    robot: int,
    motes: Sequence[int],
    threshold: float,
    hysteresis: float,
    gtype: int,
    t0: float,
    t1: float,
) -> Path:
    """RSSI of the robot's beacons at ``motes``: what each mote measured (EWMA of
    received Hello frames), the noise-free mean, the threshold and hysteresis band,
    and shading while the mote was a group member."""
    fig = Figure(figsize=(8.0, 2.6 * len(motes) + 0.8), layout="constrained")
    ts = [t0 + (t1 - t0) * i / 400 for i in range(401)]
    axes: list[Any] = []
    for k, n in enumerate(motes):
        ax = fig.add_subplot(len(motes), 1, k + 1, sharex=axes[0] if axes else None)
        axes.append(ax)
        mean = [truth.mean_rssi(robot, n, t) for t in ts]
        ax.plot(ts, mean, color="#888888", lw=1.0, label="mean RSSI (truth)")
        samples = [(t, v) for t, v in rec.rssi.get(n, []) if t0 <= t <= t1 and v is not None]
        if samples:
            ax.plot(
                [s[0] for s in samples], [s[1] for s in samples], ".", ms=3, color="#1f77b4",
                label="measured (mote's EWMA)",
            )  # fmt: skip
        ax.axhline(threshold, color="#d62728", lw=1.0, label=f"threshold {threshold:g} dBm")
        if hysteresis:
            ax.axhline(threshold - hysteresis, color="#d62728", lw=0.8, ls="--",
                       label=f"leave below {threshold - hysteresis:g} dBm")  # fmt: skip
        # membership intervals
        start: float | None = None
        for t in ts:
            s = rec.state_at(n, gtype, t)
            inside = s is not None and s.gid is not None
            if inside and start is None:
                start = t
            elif not inside and start is not None:
                ax.axvspan(start, t, color="#2ca02c", alpha=0.15, lw=0)
                start = None
        if start is not None:
            ax.axvspan(start, ts[-1], color="#2ca02c", alpha=0.15, lw=0)
        ax.set_ylabel(f"mote {n}\nRSSI (dBm)", fontsize=FS_LABEL)
        ax.tick_params(labelsize=FS_TICK)
        if k == 0:
            from matplotlib.patches import Patch

            handles, _ = ax.get_legend_handles_labels()
            handles.append(Patch(color="#2ca02c", alpha=0.15, label="member of the group"))
            ax.legend(handles=handles, fontsize=FS_LEGEND, loc="lower right", ncol=2,
                      framealpha=0.85)  # fmt: skip
    axes[-1].set_xlabel("time (s); shaded: member of the robot's group", fontsize=FS_LABEL)
    fig.suptitle(f"RSSI of the robot's mote ({robot}) at motes {', '.join(map(str, motes))}",
                 fontsize=FS_TITLE)  # fmt: skip
    return _save(fig, path)


def field_snapshots(
    path: Path,
    rec: Recorder,
    truth: GroundTruth,
    world: World,
    gtype: int,
    defn: GroupTypeDef,
    times: Sequence[float],
    ids: Sequence[int],
    area: Area,
    field: str = "temperature",
    threshold: float | None = None,
    titles: Mapping[float, str] | None = None,
    settle: float = 0.0,
) -> Path:
    """Panels at ``times`` over a heat map of ``field``: motes coloured by group id,
    leaders as stars, true members ringed, the threshold contour."""
    rows, cols = _grid(len(times))
    fig = Figure(figsize=(5.0 * cols, 3.9 * rows), layout="constrained")
    colours = GroupColours()
    nx, ny = 90, 60
    xs = [area[0] - 1 + (area[1] - area[0] + 2) * i / (nx - 1) for i in range(nx)]
    ys = [area[2] - 1 + (area[3] - area[2] + 2) * j / (ny - 1) for j in range(ny)]
    for k, t in enumerate(times):
        ax = fig.add_subplot(rows, cols, k + 1)
        grid = [[world.value(field, x, y, t) for x in xs] for y in ys]
        # Filled contours (flat colours) read well and keep the PNG small.
        flat = [v for row in grid for v in row]
        lo, hi = min(flat), max(flat)
        levels = sorted({lo, *[lo + (hi - lo) * k / 8 for k in range(1, 8)], hi + 1e-6})
        if threshold is not None and lo < threshold < hi:
            levels = sorted({*levels, threshold})
        if hi - lo > 1e-6:
            filled = ax.contourf(xs, ys, grid, levels=levels, cmap="YlOrRd", alpha=0.8)
            bar = fig.colorbar(filled, ax=ax, shrink=0.85, format="%.0f")
            bar.set_label(f"{field} ({unit_of(field) or '-'})", fontsize=FS_LABEL)
            bar.ax.tick_params(labelsize=FS_TICK)
        ax.set_aspect("equal")
        if threshold is not None:
            ax.contour(xs, ys, grid, levels=[threshold], colors="#ff4444", linewidths=0.8)
        _draw_motes(
            ax, rec, truth, gtype, t + settle, ids, colours, truth.members(defn, t, ids), False
        )
        label = (titles or {}).get(t, "")
        ax.set_title(f"t = {t:.0f} s {label}".strip(), fontsize=FS_TITLE)
        _axes_in_metres(ax)
        extra: list[Any] = []
        if threshold is not None:
            unit = unit_of(field)
            extra.append(Line2D([], [], color="#ff4444", lw=1.0,
                                label=f"{field} = {threshold:g} {unit}".strip()))  # fmt: skip
        _legend(ax, rec, gtype, t + settle, colours, extra=extra)
    return _save(fig, path)


def membership_sizes(
    path: Path, series: Sequence[Instant], title: str = "Group membership vs truth"
) -> Path:
    """Members in a group of the type vs true members, and per-instant errors."""
    fig = Figure(figsize=(8.0, 3.2), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    ts = [i.t for i in series]
    ax.step(ts, [len(i.truth) for i in series], where="post", color="k", lw=1.2, label="truth")
    ax.step(ts, [len(i.members) for i in series], where="post", color="#1f77b4", lw=1.0,
            label="members (t + settle)")  # fmt: skip
    ax.bar(ts, [len(i.members ^ i.truth) for i in series], width=(ts[1] - ts[0]) if len(ts) > 1
           else 0.5, color="#d62728", alpha=0.35, label="disagreements")  # fmt: skip
    ax.set_xlabel("time (s)", fontsize=FS_LABEL)
    ax.set_ylabel("motes (count)", fontsize=FS_LABEL)
    ax.tick_params(labelsize=FS_TICK)
    ax.legend(fontsize=FS_LEGEND, framealpha=0.85)
    ax.set_title(title, fontsize=FS_TITLE)
    return _save(fig, path)
