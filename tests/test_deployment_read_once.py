"""A deployment file is read once, in one place (docs/deployments.md, "Read once").

Followed from ``load_scenario``, the file's contents reach their typed value
(:class:`awaremw.runtime.deployment.Deployment`) inside one call of the reader,
going down a tree of modules: each module the reading enters is entered from one
module only, so nothing bounces back to a module through another door. Once the
value exists nothing parses again: the node kinds, the world and the
experiments only read it (the gateway's schema alone turns the ``[[groups]]`` /
``[[channels]]`` payloads into definitions, as it does MQTT payloads).

Measured by running the code (``sys.setprofile``), not by reading it.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

import pytest

import awaremw
from awaremw.experiments.scenario import Scenario, load_scenario
from awaremw.nodes import KindsFactory, build_core, config_for
from awaremw.runtime.deployment import Deployment, NodeSpec

ROOT = Path(awaremw.__file__).resolve().parent
READER = "awaremw.runtime.deployment"
ENTRY = "awaremw.experiments.scenario"
# What the reading may enter below the reader: the shapes' adapter, the radio's
# presets and files, the world's table and fields (and what a dataclass of theirs
# runs). Never the node kinds, the gateway or the experiments.
MAY_ENTER = {
    READER,
    "awaremw.protocol.validation",
    "awaremw.protocol.config",
    "awaremw.radio.model",
    "awaremw.radio.environment",
    "awaremw.radio.links",
    "awaremw.radio.noise",
    "awaremw.radio.textfile",
    "awaremw.world.table",
    "awaremw.world.fields",
    "awaremw.world.mobility",
}
# Whoever calls one of these after the value exists parses the file again.
PARSERS = {
    ("awaremw.protocol.validation", "convert"),
    ("awaremw.protocol.config", "with_overrides"),
    ("awaremw.world.table", "world_from_table"),
    (READER, "parse_deployment"),
    (READER, "parse"),
}


def _module(frame: FrameType | None) -> tuple[str, FrameType | None]:
    """The awaremw module of ``frame`` or of its nearest awaremw caller."""
    while frame is not None:
        name = frame.f_globals.get("__name__", "")
        if name.startswith("awaremw."):
            return name, frame
        frame = frame.f_back
    return "", None


@dataclass
class Trace:
    doors: dict[str, set[str]] = field(default_factory=dict)  # module -> whence it was entered
    order: list[str] = field(default_factory=list)  # modules as first entered, in order
    after: list[tuple[str, str]] = field(default_factory=list)  # parsers called after the value
    value: Any = None


@contextmanager
def traced() -> Iterator[Trace]:
    """Trace ``load_scenario``: the reading (the reader's ``load`` called from the
    scenario, until it returns) and what comes after it."""
    trace = Trace()
    reading: list[FrameType] = []  # the reader's frame while it reads
    done = [False]

    def profile(frame: FrameType, event: str, arg: Any) -> None:
        if event == "return" and reading and frame is reading[0]:
            trace.value = arg
            reading.clear()
            done[0] = True
            return
        if event != "call":
            return
        name = frame.f_globals.get("__name__", "")
        if not name.startswith("awaremw."):
            return
        caller, _ = _module(frame.f_back)
        code = frame.f_code.co_name
        if code == "<module>":  # a module imported for the first time: no reading
            return
        if not reading and not done[0]:
            if name == READER and code == "load" and caller == ENTRY:
                reading.append(frame)
                trace.doors[name] = {caller}
                trace.order.append(name)
            return
        if reading:
            if caller != name:
                if name not in trace.doors:
                    trace.order.append(name)
                trace.doors.setdefault(name, set()).add(caller)
        elif (name, code) in PARSERS:
            trace.after.append((name, code))

    sys.setprofile(profile)
    try:
        yield trace
    finally:
        sys.setprofile(None)


@pytest.mark.parametrize("name", ["romeo4r", "fire", "intel_lab"])
def test_load_scenario_reads_the_file_once_down_one_tree(name: str) -> None:
    with traced() as trace:
        sc = load_scenario(name)
    assert isinstance(trace.value, Deployment) and sc.deployment is trace.value
    # The reading enters its modules in this order, each from one door.
    assert trace.order[0] == READER, trace.order
    assert set(trace.order) <= MAY_ENTER, set(trace.order) - MAY_ENTER
    many = {m: sorted(d) for m, d in trace.doors.items() if len(d) > 1}
    assert not many, f"entered through more than one door: {many}"
    assert trace.doors[READER] == {ENTRY}
    # A tree: no module is entered from one it leads to (no way back up).
    for module in trace.order:
        seen = {module}
        door = next(iter(trace.doors[module]))
        while door != ENTRY:
            assert door not in seen, f"{module} is reached around a circle: {sorted(seen)}"
            seen.add(door)
            door = next(iter(trace.doors[door]))
    # And once the value exists, nobody parses again.
    assert trace.after == [], trace.after


def test_the_value_is_typed_and_frozen() -> None:
    sc = load_scenario("romeo4r")
    d = sc.deployment
    with pytest.raises(AttributeError):
        d.seed = 3  # type: ignore[misc]
    assert type(d.world).__name__ == "WorldTable" and d.world_model() == sc.world
    assert all(isinstance(n, NodeSpec) for n in d.nodes)
    assert all(isinstance(g["type"], int) for g in d.groups)
    assert all(isinstance(c["id"], int) for c in d.channels)
    assert isinstance(sc, Scenario) and dict(d.experiment) == dict(sc.settings)


def test_node_kinds_take_the_typed_value() -> None:
    d = load_scenario("romeo4r").deployment
    robot = d.node(100)
    world = d.world_model()
    config = config_for(robot, d)
    assert config.hello_period is not None and build_core(robot, d, world) is not None
    assert KindsFactory(world)(d.node(0), d) is not None


# Modules that take the value: they call none of the reading's tools, and read
# no TOML (the reader itself, runtime/deployment.py, is the one that does).
READERS_ONLY = ("nodes", "experiments", "world", "runtime/fleet", "gateway", "view", "cli")
PARSING = {"convert", "with_overrides", "world_from_table"}


def _parsing(path: Path) -> set[str]:
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            found |= {name} & PARSING
        elif isinstance(node, ast.Import | ast.ImportFrom):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module]
            found |= {"import tomllib" for m in mods if m == "tomllib"}
    return found


@pytest.mark.parametrize("place", READERS_ONLY)
def test_readers_of_the_value_parse_nothing(place: str) -> None:
    offenders = {}
    for path in sorted((ROOT / place).rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel == "world/table.py":
            continue  # the [world] table's shape, and its raw form for callers with a table
        if found := _parsing(path):
            offenders[rel] = sorted(found)
    assert not offenders, offenders
