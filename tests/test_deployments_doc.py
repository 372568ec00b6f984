"""docs/deployments.md matches the parser: its example loads and builds, names
every key the parser knows and no other, lists the current kinds, its error
lines are the parser's own, and its table of shipped files is right."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from awaremw.gateway.schema import Limits, parse_channel, parse_group_type
from awaremw.gateway.service import deployment_definitions
from awaremw.nodes import NODE_EXTRA_KEYS, KindsFactory, kind_names, world_of
from awaremw.nodes.kinds import ALIASES, KINDS
from awaremw.runtime.deployment import (
    GRID_KEYS,
    NODE_KEYS,
    RAW_TABLES,
    TOP_KEYS,
    DeploymentError,
    load,
    load_deployment,
    parse_deployment,
)

ROOT = Path(__file__).resolve().parent.parent
DOC = (ROOT / "docs" / "deployments.md").read_text(encoding="utf-8")


def example() -> str:
    m = re.search(r"## Format\n.*?```toml\n(.*?)```", DOC, re.S)
    assert m, "docs/deployments.md has no toml block under '## Format'"
    return m.group(1)


def test_the_example_loads_and_builds_every_mote(tmp_path: Path) -> None:
    path = tmp_path / "example.toml"
    path.write_text(example(), encoding="utf-8")
    dep = load_deployment(path, known_kinds=kind_names())
    assert len(dep.nodes) == 2 + 25
    factory = KindsFactory(world_of(dep))
    for spec in dep.nodes:
        assert factory(spec, dep) is not None  # node extras checked here
    # [[groups]] and [[channels]]: what the gateway makes of them passes its schema
    defs = deployment_definitions(dep.groups, dep.channels)
    assert [t for t, _ in defs] == ["def/group/1", "def/channel/1"]
    parse_group_type("1", defs[0][1], Limits())
    parse_channel("1", defs[1][1], Limits())


def test_the_example_names_every_key_the_parser_knows_and_no_other() -> None:
    doc = tomllib.loads(example())
    # A links deployment cannot have the example's robot: its key has its own block.
    m = re.search(r"## Links files\n.*?```toml\n(.*?)```", DOC, re.S)
    assert m, "docs/deployments.md has no toml block under '## Links files'"
    links = tomllib.loads(m.group(1))
    assert set(links) == {"links"}
    top = set(doc) | set(links)
    assert top == set(TOP_KEYS) | set(RAW_TABLES), top ^ (set(TOP_KEYS) | set(RAW_TABLES))
    node_keys = set().union(*(set(n) for n in doc["nodes"]))
    assert node_keys == set(NODE_KEYS) | NODE_EXTRA_KEYS, node_keys ^ (NODE_KEYS | NODE_EXTRA_KEYS)
    grid_keys = set().union(*(set(g) for g in doc["grid"]))
    # a grid takes its own keys and the per-mote extras of a node entry
    assert grid_keys >= GRID_KEYS, GRID_KEYS - grid_keys
    assert grid_keys <= GRID_KEYS | NODE_EXTRA_KEYS


def test_the_kinds_listed_are_the_kinds() -> None:
    m = re.search(r'^kind = "gateway"\s+# required: (.*)$', example(), re.M)
    assert m
    names = re.findall(r"[a-z][a-z0-9-]*", m.group(1).replace("required", ""))
    assert set(names) - {"aliases"} == set(KINDS) | set(ALIASES)


# An input for every error line the doc shows.
BAD = {
    "missing key 'kind'": '[[nodes]]\nid = 17\nposition = [1, 1]\n',
    "duplicate id 4": '[[nodes]]\nid = 4\nkind = "tmote"\nposition = [1, 1]\n'
    '[[nodes]]\nid = 4\nkind = "tmote"\nposition = [2, 2]\n',
    "is outside the area": '[[grid]]\nfirst_id = 1\nkind = "tmote"\nspacing = 12.0\n'
    "cols = 5\nrows = 6\n",
    "is outside 0..": '[[nodes]]\nid = 70000\nkind = "tmote"\nposition = [1, 1]\n',
    "unknown radio preset": 'radio = "nrf24"\n',
    "unknown mac": 'mac = "tdma"\n',
    "unknown collisions": 'collisions = "maybe"\n',
    "unknown kind": '[[nodes]]\nid = 9\nkind = "drone"\nposition = [1, 1]\n',
    "must be a number": '[[nodes]]\nid = 1\nkind = "robot"\npath = [[0, 0], [5, 5]]\n'
    'speed_mps = "fast"\n',
}


@pytest.mark.parametrize("key", sorted(BAD))
def test_every_error_line_of_the_doc_is_the_parsers(key: str) -> None:
    errors = re.search(r"## Errors\n.*?```\n(.*?)```", DOC, re.S)
    assert errors
    [line] = [ln for ln in errors.group(1).splitlines() if key in ln]
    text = 'area = [100.0, 50.0]\n' + BAD[key]
    if key.startswith("unknown radio") or key.startswith("unknown mac") or "collisions" in key:
        text = BAD[key] + 'area = [100.0, 50.0]\n'
    data = tomllib.loads(text)
    with pytest.raises(DeploymentError) as e:
        parse_deployment(data, Path("x.toml"), known_kinds=kind_names())
    assert str(e.value) == line.strip(), (str(e.value), line)


def test_refusals_the_doc_promises(tmp_path: Path) -> None:
    with pytest.raises(DeploymentError, match="unknown key 'sead'"):
        parse_deployment({"area": [10, 10], "sead": 3}, Path("x.toml"))
    p = tmp_path / "x.toml"
    p.write_text('area = [10.0, 10.0]\n[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1, 1]\n'
                 "colour = 1\n")  # fmt: skip
    with pytest.raises(DeploymentError, match=r"unknown key\(s\) 'colour'"):
        load_deployment(p, known_kinds=kind_names())


def test_the_shipped_table_matches_the_files() -> None:
    rows = re.findall(r"^\| `(\w+)\.toml` \| ([\d,]+) \| (\w+) \|", DOC, re.M)
    assert {name for name, _, _ in rows} >= {"romeo4r", "fire", "grid_small", "large"}
    for name, motes, radio in rows:
        dep = load(name)
        assert (len(dep.nodes), dep.radio) == (int(motes.replace(",", "")), radio), name
