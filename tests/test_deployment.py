"""Deployment files: the format, the shipped files, and every error named."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

from awaremw.nodes.kinds import ALIASES, KINDS
from awaremw.radio.model import CC1000
from awaremw.runtime.deployment import (
    DeploymentError,
    find_deployment,
    load,
    load_deployment,
    shipped_dir,
    shipped_names,
)
from awaremw.world.mobility import Path as MovePath
from awaremw.world.mobility import Static

KNOWN = set(KINDS) | set(ALIASES)

HEAD = 'radio = "cc2420"\nseed = 3\narea = [100.0, 50.0]\n'


def write(tmp_path: Path, body: str, head: str = HEAD) -> Path:
    p = tmp_path / "dep.toml"
    p.write_text(head + body)
    return p


def error(tmp_path: Path, body: str, head: str = HEAD) -> str:
    p = write(tmp_path, body, head)
    with pytest.raises(DeploymentError) as e:
        load_deployment(p, KNOWN)
    msg = str(e.value)
    assert msg.startswith(f"{p}: "), msg
    return msg


def test_full_format(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        """
name = "demo"
tx_power_dbm = -5
[world]
ambient_temperature = 20
[middleware]
drip_k = 2
[[groups]]
type = 1
[[channels]]
id = 1
attr = "temperature"
[viewer]
zoom = 2

[[nodes]]
id = 7
kind = "gateway"
position = [0, 0]
battery_mj = 500
noise = { temperature = 0.2 }

[[nodes]]
id = 100
kind = "robot"
path = [[0.0, 5.0], [12.5, 5.0]]
speed_mps = 0.5
start_s = 10
pause_s = 2
loop = true
tx_power_dbm = -10
boot_s = 3

[[grid]]
first_id = 1
kind = "tmote"
origin = [10, 10]
spacing = [20, 15]
cols = 3
rows = 2
jitter_m = 0.5
battery_mj = 100
""",
    )
    d = load_deployment(p, KNOWN)
    assert d.name == "demo" and d.radio == "cc2420" and d.seed == 3 and d.path == p
    assert d.area == (100.0, 50.0) and d.tx_power_dbm == -5.0
    assert d.ids == (1, 2, 3, 4, 5, 6, 7, 100)
    assert d.world.ambient_temperature == 20.0 and d.world_model().ambient_temperature == 20.0
    assert d.middleware == {"drip_k": 2}
    assert d.groups == ({"type": 1},) and d.channels == ({"id": 1, "attr": "temperature"},)
    assert d.extra == {"viewer": {"zoom": 2}} and d.experiment == {}
    gw = d.node(7)
    assert gw.noise == {"temperature": 0.2} and gw.middleware == {}
    assert gw.battery_mj == 500.0 and not gw.is_mobile
    assert isinstance(gw.mobility(), Static) and d.tx_power_of(gw) == -5.0
    robot = d.node(100)
    m = robot.mobility()
    assert isinstance(m, MovePath) and robot.is_mobile and robot.position == (0.0, 5.0)
    assert m.position(10.0) == (0.0, 5.0) and m.position(15.0) == pytest.approx((2.5, 5.0))
    assert (robot.loop, robot.pause_s, robot.boot_s, d.tx_power_of(robot)) == (True, 2, 3, -10)
    grid = [d.node(i) for i in range(1, 7)]
    nominal = [(10 + 20 * c, 10 + 15 * r) for r in range(2) for c in range(3)]
    for spec, (x, y) in zip(grid, nominal, strict=True):
        assert spec.kind == "tmote" and spec.battery_mj == 100.0
        assert abs(spec.position[0] - x) <= 0.5 and abs(spec.position[1] - y) <= 0.5
    assert len({s.position for s in grid}) == 6
    assert d.radio_model().seed == 3 and len(d.of_kind("tmote")) == 6


def test_grid_jitter_is_seeded(tmp_path: Path) -> None:
    body = (
        '[[grid]]\nfirst_id = 0\nkind = "tmote"\nspacing = 10\ncols = 4\nrows = 4\njitter_m = 2\n'
    )
    a = load_deployment(write(tmp_path, body))
    b = load_deployment(write(tmp_path, body))
    c = load_deployment(write(tmp_path, body, HEAD.replace("seed = 3", "seed = 4")))
    pos = [n.position for n in a.nodes]
    assert pos == [n.position for n in b.nodes]
    assert pos != [n.position for n in c.nodes]
    assert all(0 <= x <= 100 and 0 <= y <= 50 for x, y in pos)  # clamped to the area


@pytest.mark.parametrize(
    ("head", "body", "expected"),
    [
        (HEAD, "[[nodes]]\nid = 17\nposition = [1, 1]\n", "nodes[0] (id 17): missing key 'kind'"),
        (HEAD, '[[nodes]]\nkind = "tmote"\nposition = [1, 1]\n', "nodes[0]: missing key 'id'"),
        (
            HEAD,
            '[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1, 1]\n'
            '[[nodes]]\nid = 1\nkind = "tmote"\nposition = [2, 1]\n',
            "nodes[1] (id 1): duplicate id 1 (also nodes[0])",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 3\nkind = "tmote"\nposition = [1, 1]\n'
            '[[grid]]\nfirst_id = 1\nkind = "tmote"\nspacing = 5\ncols = 3\nrows = 1\n',
            "grid[0] (ids 1..3): id 3: duplicate id 3 (also nodes[0])",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 70000\nkind = "tmote"\nposition = [1, 1]\n',
            "nodes[0] (id 70000): id 70000 is outside 0..65533",
        ),
        (
            HEAD,
            '[[nodes]]\nid = -1\nkind = "tmote"\nposition = [1, 1]\n',
            "nodes[0] (id -1): id -1 is outside 0..65533",
        ),
        (
            HEAD,
            '[[grid]]\nfirst_id = 65530\nkind = "tmote"\nspacing = 1\ncols = 10\nrows = 1\n',
            "grid[0] (ids 65530..65539): id 65539 is outside 0..65533",
        ),
        (
            HEAD.replace("cc2420", "nrf24"),
            "",
            "unknown radio preset 'nrf24' (known: cc2420, cc1000)",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 2\nkind = "tmote"\nposition = [101, 1]\n',
            "nodes[0] (id 2): position (101, 1) is outside the area 100 x 50 m",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 2\nkind = "robot"\npath = [[1, 1], [1, 60]]\n',
            "nodes[0] (id 2): path[1] (1, 60) is outside the area 100 x 50 m",
        ),
        (
            HEAD,
            '[[grid]]\nfirst_id = 1\nkind = "tmote"\nspacing = 12\ncols = 5\nrows = 6\n',
            "grid[0] (ids 1..30): position of id 26 (0, 60) is outside the area 100 x 50 m",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 9\nkind = "drone"\nposition = [1, 1]\n',
            "nodes[0] (id 9): unknown kind 'drone' (known: gateway, mica2, robot,",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 1\nkind = "robot"\npath = [[1, 1]]\nspeed_mps = "fast"\n',
            "nodes[0] (id 1): 'speed_mps' must be a number, got 'fast'",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 1\nkind = "robot"\npath = [[1, 1]]\nspeed_mps = 0\n',
            "nodes[0] (id 1): 'speed_mps' must be > 0, got 0",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 1.5\nkind = "tmote"\nposition = [1, 1]\n',
            "nodes[0]: 'id' must be an integer, got 1.5",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1, 1, 1]\n',
            "nodes[0] (id 1): 'position' must be an array of length 2, got [1, 1, 1]",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1, 1]\npath = [[1, 1]]\n',
            "nodes[0] (id 1): give exactly one of 'position' or 'path'",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1, 1]\nloop = true\n',
            "nodes[0] (id 1): 'loop' only makes sense with a 'path'",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1, 1]\ntx_power_dbm = 3\n',
            "nodes[0] (id 1): tx power 3.0 dBm outside cc2420's [-25.0, 0.0] dBm",
        ),
        (
            HEAD,
            '[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1, 1]\nbattery_mj = 0\n',
            "nodes[0] (id 1): 'battery_mj' must be > 0, got 0",
        ),
        (
            HEAD,
            '[[grid]]\nfirst_id = 1\nkind = "tmote"\ncols = 2\nrows = 2\n',
            "grid[0]: missing key 'spacing'",
        ),
        (
            HEAD,
            'nodez = 3\n[[nodes]]\nid = 1\nkind = "t"\nposition = [1, 1]\n',
            "unknown key 'nodez'",
        ),
        (
            'radio = "cc2420"\n',
            '[[nodes]]\nid = 1\nkind = "t"\nposition = [1, 1]\n',
            "missing key 'area'",
        ),
        (HEAD, "", "no nodes"),
        (HEAD, "[[nodes]\nid = 1\n", "invalid TOML: "),
        (HEAD, "world = 3\n", "'world' must be a table"),
    ],
)
def test_errors_are_named(tmp_path: Path, head: str, body: str, expected: str) -> None:
    msg = error(tmp_path, body, head)
    assert expected in msg, msg


def test_kinds_are_free_without_a_registry(tmp_path: Path) -> None:
    p = write(tmp_path, '[[nodes]]\nid = 1\nkind = "drone"\nposition = [1, 1]\n')
    assert load_deployment(p).nodes[0].kind == "drone"


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(DeploymentError, match="cannot read"):
        load_deployment(tmp_path / "missing.toml")
    bad = tmp_path / "bin.toml"
    bad.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(DeploymentError, match=r"bin\.toml: not UTF-8"):
        load_deployment(bad)


def test_find_deployment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    shipped = shipped_dir() / "grid_small.toml"
    # the package data of awaremw.deployments (the checkout's nodes/ when editable)
    import awaremw.deployments

    assert shipped.parent == Path(awaremw.deployments.__file__).parent
    monkeypatch.chdir(tmp_path)
    assert find_deployment("grid_small") == shipped
    assert find_deployment("grid_small.toml") == shipped
    # A file of that name in the working directory overrides the shipped one.
    local = tmp_path / "grid_small.toml"
    local.write_text(HEAD + '[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1, 1]\n')
    assert find_deployment("grid_small") == local
    assert load("grid_small").ids == (1,)
    assert find_deployment(str(shipped)) == shipped
    with pytest.raises(DeploymentError, match=r"no such deployment .* shipped: .*grid_small"):
        find_deployment("atlantis")
    assert {"romeo4r", "fire", "grid_small", "large"} <= set(shipped_names())
    assert os.path.isabs(find_deployment("large"))


@pytest.mark.parametrize("name", ["grid_small", "large"])
def test_shipped_files(name: str) -> None:
    d = load(name, KNOWN)
    assert d.name == name and d.path == shipped_dir() / f"{name}.toml"
    assert len(d.of_kind("gateway")) == 1
    if name == "large":
        assert len(d.nodes) >= 1000 and len(d.of_kind("robot")) == 1
        # About ten neighbours whose noise-free RSSI is above sensitivity
        # (sampled: interior and edge motes alike).
        m = d.radio_model()
        counts = []
        for s in d.nodes[::40]:
            counts.append(
                sum(
                    1
                    for t in d.nodes
                    if t.id != s.id
                    and math.dist(s.position, t.position) < 60
                    and m.mean_rssi(s.id, t.id, math.dist(s.position, t.position), 0.0)
                    >= m.preset.sensitivity_dbm
                )
            )
        assert 8 <= sum(counts) / len(counts) <= 13


def test_deployment_tx_power_uses_the_preset(tmp_path: Path) -> None:
    head = 'radio = "cc1000"\narea = [10, 10]\n'
    d = load_deployment(
        write(tmp_path, '[[nodes]]\nid = 1\nkind = "mica2"\nposition = [1, 1]\n', head)
    )
    assert d.preset is CC1000 and d.tx_power_dbm == CC1000.tx_power_dbm and d.seed == 0
    assert d.name == "dep"
