"""Rich rendering of a :class:`~awaremw.view.snapshot.Snapshot`: a character map
of the motes coloured by group, leaders, the robot and the gateway, beside
tables of the groups and the latest records."""

from __future__ import annotations

from rich.console import Group, RenderableType
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from awaremw.view.snapshot import MoteDot, Snapshot

PALETTE = (
    "bright_blue", "bright_magenta", "bright_green", "yellow", "bright_cyan",
    "orange3", "orchid", "spring_green3", "deep_sky_blue1", "gold1",
)  # fmt: skip


LED_STYLES = {"red": "red", "green": "green", "blue": "blue", "yellow": "yellow"}


class GroupStyles:
    """A stable colour per group id (first come, first served)."""

    def __init__(self) -> None:
        self._map: dict[int, str] = {}

    def __call__(self, gid: int) -> str:
        if gid not in self._map:
            self._map[gid] = PALETTE[len(self._map) % len(PALETTE)]
        return self._map[gid]


def _glyph(m: MoteDot, styles: GroupStyles) -> tuple[str, str]:
    if not m.alive:
        return "x", "grey35"
    if m.kind == "robot":
        return "▲", "bold red"
    if m.kind == "gateway":
        return "■", "bold white"
    if m.group is None:
        return "·", "grey62"
    return ("★" if m.leader else "●"), ("bold " if m.leader else "") + styles(m.group)


def map_text(snap: Snapshot, width: int, height: int, styles: GroupStyles) -> Text:
    """The motes on a ``width`` x ``height`` character grid (y up), with ids."""
    xmin, xmax, ymin, ymax = snap.area
    pad_x = (xmax - xmin) * 0.06 + 0.5
    pad_y = (ymax - ymin) * 0.06 + 0.5
    xmin, xmax, ymin, ymax = xmin - pad_x, xmax + pad_x, ymin - pad_y, ymax + pad_y
    cells: list[list[tuple[str, str]]] = [[(" ", "")] * width for _ in range(height)]

    def put(col: int, row: int, ch: str, style: str, force: bool = False) -> None:
        if 0 <= row < height and 0 <= col < width and (force or cells[row][col][0] == " "):
            cells[row][col] = (ch, style)

    # Robots last so they stay visible over motes.
    for m in sorted(snap.motes, key=lambda m: m.kind == "robot"):
        col = round((m.x - xmin) / (xmax - xmin) * (width - 1))
        row = height - 1 - round((m.y - ymin) / (ymax - ymin) * (height - 1))
        ch, style = _glyph(m, styles)
        put(col, row, ch, style, force=True)
        label = str(m.node)
        lstyle = "grey50" if m.group is None else styles(m.group)
        if m.leds:  # the led command's effect: the id on the first lit LED's colour
            lstyle = f"bold black on {LED_STYLES.get(m.leds[0], 'white')}"
        for i, c in enumerate(label):
            put(col + 1 + i, row, c, lstyle, force=bool(m.leds))
    text = Text()
    for r, line in enumerate(cells):
        for ch, style in line:
            text.append(ch, style=style or None)
        if r < height - 1:
            text.append("\n")
    return text


def render(snap: Snapshot, width: int = 64, height: int = 22) -> RenderableType:
    styles = GroupStyles()
    for g in sorted(snap.groups, key=lambda g: g.group_id):
        styles(g.group_id)
    gtype = "" if snap.group_type is None else f" (group type {snap.group_type})"
    legend = Text.assemble(
        ("★", "bold"), " leader  ", ("●", ""), " member  ", ("·", "grey62"), " idle  ",
        ("▲", "bold red"), " robot  ", ("■", "bold white"), " gateway  ", ("x", "grey35"),
        " down  ", ("id", "bold black on green"), " LED lit",
    )  # fmt: skip
    the_map = Panel(
        Group(map_text(snap, width, height, styles), legend),
        title=f"{snap.title}  t = {snap.t:7.1f} s{gtype}",
        border_style="grey50",
    )
    groups = Table(title="groups", expand=False, box=None, header_style="bold")
    for col in ("type", "id", "leader", "members"):
        groups.add_column(col, justify="right")
    for g in sorted(snap.groups, key=lambda g: (g.group_type, g.group_id)):
        groups.add_row(
            str(g.group_type),
            Text(str(g.group_id), style=styles(g.group_id)),
            "-" if g.leader is None else str(g.leader),
            str(g.members),
        )
    records = Table(title="latest records", expand=False, box=None, header_style="bold")
    for col in ("t", "ch", "group", "value", "n"):
        records.add_column(col, justify="right")
    for r in snap.records[-8:]:
        records.add_row(
            f"{r.t:.1f}",
            str(r.channel),
            Text(f"{r.group_type}/{r.group_id}", style=styles(r.group_id)),
            f"{r.agg} {r.value:.2f}{' ' + r.unit if r.unit else ''}",
            str(r.count),
        )
    stats = Table.grid(padding=(0, 1))
    stats.add_column(justify="right", style="grey70")
    stats.add_column()
    for k, v in snap.stats.items():
        stats.add_row(k, f"{v:.1f}" if isinstance(v, float) else str(v))
    side = Group(groups, Text(""), records, Text(""), stats)
    grid = Table.grid(padding=(0, 2))
    grid.add_column()
    grid.add_column()
    grid.add_row(the_map, side)
    return grid
