"""Commands: run the node kind's handler on each targeted mote, once per version.

Commands travel as Drip items of kind COMMAND; the item id is a *slot* that
the gateway reuses, and every new command in a slot gets a new version. This
component is told (through :meth:`Commands.define`) whenever a slot's content
changes and runs ``ctx.app.on_command`` exactly once per ``(slot, version)``
when the command targets this mote:

* ``TargetKind.ALL``: every mote;
* ``TargetKind.NODE``: the mote whose id is ``target_a``;
* ``TargetKind.GROUP``: a mote that is, when the command arrives, a member of a
  group of type ``target_a`` with id ``target_b`` (``ANY_GROUP_ID``: any group
  of that type), as the groups component reports through
  ``groups.membership(group_type)``.

A command is network state until its slot is reused or deleted: a mote that
joins late (or reboots, losing its memory) catches up on the slot and runs the
command it finds there once. The gateway deletes a slot to retire a command.
"""

from __future__ import annotations

from collections.abc import Callable

from awaremw.protocol.component import Component, MoteContext
from awaremw.protocol.events import CommandExecuted
from awaremw.protocol.frames import ANY_GROUP_ID, CommandDef, ItemBody, ItemKind, TargetKind
from awaremw.protocol.groups import Groups

VersionOf = Callable[[ItemKind, int], "int | None"]


class Commands(Component):
    def __init__(
        self, ctx: MoteContext, groups: Groups, version_of: VersionOf | None = None
    ) -> None:
        super().__init__(ctx)
        self.groups = groups
        # Where the slot's current version comes from (the dissemination component).
        # Without it, each define() of a command counts as a new version.
        self.version_of = version_of
        self._seen: dict[int, int] = {}  # slot -> last version handled
        self.executed = 0

    def define(self, slot: int, item: ItemBody | None, now: float) -> None:
        """The content of command ``slot`` changed (None: the slot was deleted)."""
        if item is None:
            return  # nothing to undo: a command has run or not
        if not isinstance(item, CommandDef):
            raise TypeError(f"command slot {slot} given a {type(item).__name__}")
        version = self.version_of(ItemKind.COMMAND, slot) if self.version_of else None
        if version is None:
            version = self._seen.get(slot, 0) + 1
        if self._seen.get(slot) == version:
            return  # exactly once per (slot, version)
        self._seen[slot] = version
        if not self.targets_me(item) or self.ctx.app is None:
            return
        self.ctx.app.on_command(item, now)
        self.groups.app_changed(now)
        self.executed += 1
        self.ctx.emit(CommandExecuted(item.name, slot, version))

    def targets_me(self, cmd: CommandDef) -> bool:
        if cmd.target_kind == TargetKind.ALL:
            return True
        if cmd.target_kind == TargetKind.NODE:
            return cmd.target_a == self.ctx.node_id
        # GROUP: engineer D's groups component answers membership(group_type).
        membership = getattr(self.groups, "membership", None)
        if membership is None:
            return False
        m = membership(cmd.target_a)
        if m is None:
            return False
        return cmd.target_b == ANY_GROUP_ID or getattr(m, "group_id", None) == cmd.target_b
