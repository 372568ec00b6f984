"""State that belongs to a deployment, and disks that refuse it (issues 21 and 22).

* the gateway keeps versions and its embedded broker per deployment: a run of
  another deployment starts clean, a restart on the same one keeps them;
  ``--fresh`` forgets; retained group states led by motes the network does not
  have are cleared at start;
* a state directory that cannot be created, written, or is full is one line
  and exit 2 at start; at run time a failed write is kept in memory, retried,
  reported on ``aware/errors``, and never a traceback.

Read-only and full directories are real: a read-only tmpfs and a tiny one
(``mount``, as root). Where mounting is not permitted these tests skip, unless
``AWAREMW_REQUIRE_MOUNT=1`` (CI), when they fail.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import aiomqtt
import pytest
from mosquitto import Collector, Mosquitto, mosquitto_fixture, pub  # noqa: F401

from awaremw.gateway.broker import EmbeddedBroker, account_for_port
from awaremw.gateway.leftovers import sort_leftovers
from awaremw.gateway.state import (
    StateError,
    default_dir,
    deployment_key,
    open_state,
    state_root,
)
from awaremw.gateway.store import VersionStore
from awaremw.protocol.frames import ChannelDef, Condition, GroupTypeDef, ItemKind, Op
from awaremw.runtime.deployment import shipped_dir

G1 = GroupTypeDef((Condition(0, Op.GT, 45.0),), 1.0)
C1 = ChannelDef(0, 1, 0xFFFF, 2000, 0)
GROUP = b'{"conditions": [{"attr": "temperature", "op": ">", "value": 45}]}'

Mount = Callable[..., Path]


# ----------------------------------------------------------------- real mounts


@pytest.fixture
def tmpfs(tmp_path: Path) -> Iterator[Mount]:
    """``tmpfs(size="64k", ro=False)``: a fresh tmpfs mounted under tmp_path."""
    mounted: list[Path] = []

    def mount(size: str = "4m", *, ro: bool = False) -> Path:
        d = tmp_path / f"mnt{len(mounted)}"
        d.mkdir()
        opts = f"size={size}" + (",ro" if ro else "")
        r = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(d)],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
        if r.returncode != 0:
            msg = f"cannot mount a tmpfs here ({r.stderr.strip()}): needs root or CAP_SYS_ADMIN"
            if os.environ.get("AWAREMW_REQUIRE_MOUNT") == "1":
                pytest.fail(msg)
            pytest.skip(msg)
        mounted.append(d)
        return d

    yield mount
    for d in reversed(mounted):
        subprocess.run(["umount", "-l", str(d)], capture_output=True, check=False)


def fill(d: Path) -> Path:
    """Fill ``d``'s file system to the last byte; the filler file (unlink it to free)."""
    filler = d / "filler"
    with open(filler, "wb", buffering=0) as f:
        for chunk in (65536, 4096, 512, 1):
            with contextlib.suppress(OSError):
                while True:
                    f.write(b"\0" * chunk)
    return filler


# ----------------------------------------------------------------- keys, marks, --fresh


def test_deployment_keys() -> None:
    shipped = shipped_dir()
    assert deployment_key("romeo4r", shipped / "romeo4r.toml", shipped) == "romeo4r"
    a = deployment_key("test", Path("/a/test.toml"), shipped)
    b = deployment_key("test", Path("/b/test.toml"), shipped)
    assert a.startswith("test-") and b.startswith("test-") and a != b  # two files, two keys
    assert deployment_key("../x y", None, None) == "x_y"  # never a path out of the root


def test_default_dir_follows_xdg_state_home(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    assert state_root() == tmp_path / "awaremw"
    assert default_dir("fire") == tmp_path / "awaremw" / "deployments" / "fire"
    monkeypatch.delenv("XDG_STATE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_dir("fire") == tmp_path / "home/.local/state/awaremw/deployments/fire"


def test_a_directory_of_another_deployment_is_refused_unless_fresh(tmp_path: Path) -> None:
    d = tmp_path / "state"
    with open_state(d, "grid_small", name="grid_small", source="grid_small") as st:
        with VersionStore(st.store_path) as s:
            s.apply(ItemKind.GROUP_TYPE, 1, G1, {})
        st.broker_dir.mkdir()
        (st.broker_dir / "mqtt-account").write_text("awaremw:pw\n")
        (st.broker_dir / "retained.sqlite").write_bytes(b"")
        # One gateway per directory at a time.
        with pytest.raises(StateError, match="in use by another gateway"):
            open_state(d, "grid_small", name="grid_small", source="grid_small")
    with pytest.raises(StateError, match="holds the state of deployment 'grid_small'"):
        open_state(d, "romeo4r", name="romeo4r", source="romeo4r")
    with open_state(d, "romeo4r", name="romeo4r", source="romeo4r", fresh=True) as st:
        assert set(st.forgotten) >= {"gateway.sqlite", "broker/retained.sqlite"}
        with VersionStore(st.store_path) as s:
            assert s.items() == []  # versions forgotten
        assert (st.broker_dir / "mqtt-account").read_text() == "awaremw:pw\n"  # account kept
    with open_state(d, "romeo4r", name="romeo4r", source="romeo4r") as st:  # now romeo4r's
        assert st.forgotten == ()


def test_a_file_where_the_directory_should_be_is_one_error(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("")
    with pytest.raises(StateError, match="cannot create the state directory") as e:
        open_state(tmp_path / "f" / "state", "x", name="x", source="x")
    assert "\n" not in str(e.value)


def test_read_only_and_full_directories_are_refused_at_start(tmpfs: Mount) -> None:
    ro = tmpfs("64k", ro=True)
    with pytest.raises(StateError, match="Read-only file system"):
        open_state(ro / "state", "x", name="x", source="x")
    full = tmpfs("64k")
    with pytest.raises(StateError, match=r"is full \(\d+ KiB free"):
        open_state(full / "state", "x", name="x", source="x")


async def test_clients_find_the_account_of_a_local_embedded_broker(tmp_path: Path) -> None:
    broker_dir = tmp_path / "awaremw" / "deployments" / "fire" / "broker"
    async with EmbeddedBroker(state_dir=broker_dir) as b:
        assert account_for_port(b.port, tmp_path / "awaremw") == (b.username, b.password)
        assert account_for_port(b.port + 1, tmp_path / "awaremw") is None


# ----------------------------------------------------------------- run-time write failures


def test_version_store_keeps_what_the_disk_refused_and_writes_it_later(tmpfs: Mount) -> None:
    d = tmpfs("4m")
    path = d / "gateway.sqlite"
    errors: list[str] = []
    store = VersionStore(path)
    store.on_write_error = errors.append
    assert store.apply(ItemKind.GROUP_TYPE, 1, G1, {"g": 1}) is not None
    filler = fill(d)
    for i in range(1, 40):  # accepted while the disk is full: no exception
        item = store.apply(ItemKind.CHANNEL, i, C1, {"c": i})
        assert item is not None and item.version == 1
    slot = store.command_slot("led", 4)
    assert store.write_failures >= 1 and store.pending_writes >= 39
    assert len(errors) == 1, errors  # rate-limited: one report for the burst
    assert "cannot be written" in errors[0] and "kept in memory" in errors[0]
    assert store.get(ItemKind.CHANNEL, 39) is not None  # served from memory
    assert not store.retry()  # still full
    filler.unlink()
    assert store.retry() and store.pending_writes == 0
    store.close()
    with VersionStore(path) as again:
        assert len(again.items(ItemKind.CHANNEL)) == 39
        assert again.command_slot("led", 4) == slot


async def test_embedded_broker_keeps_retained_messages_the_disk_refused(tmpfs: Mount) -> None:
    d = tmpfs("4m")
    errors: list[str] = []
    async with EmbeddedBroker(state_dir=d / "broker") as b:
        b.on_write_error = errors.append
        filler = fill(d)
        async with aiomqtt.Client(
            b.host, b.port, username=b.username, password=b.password, identifier="pub"
        ) as c:
            for i in range(30):
                await c.publish(f"aware/def/group/{i}", GROUP, qos=1, retain=True)
            await c.subscribe("aware/def/#", qos=1)
            got = set()
            async with asyncio.timeout(10):
                async for m in c.messages:  # served from memory meanwhile
                    got.add(m.topic.value)
                    if len(got) == 30:
                        break
        assert b.stats.write_failures >= 1 and b.stats.pending_writes == 30
        assert len(errors) == 1 and "retained store" in errors[0]
        assert not b.retry_writes()  # still full
        filler.unlink()  # room again: the stop writes what is pending
    async with EmbeddedBroker(state_dir=d / "broker") as b:
        assert b.stats.retained == 30
        filler = fill(d)
        async with aiomqtt.Client(
            b.host, b.port, username=b.username, password=b.password, identifier="pub"
        ) as c:
            await c.publish("aware/def/group/99", GROUP, qos=1, retain=True)
        filler.unlink()
        assert b.retry_writes() and b.stats.pending_writes == 0  # the periodic retry
    async with EmbeddedBroker(state_dir=d / "broker") as b:
        assert b.stats.retained == 31


# ----------------------------------------------------------------- the gateway verb


def _env(xdg: Path) -> dict[str, str]:
    return {**os.environ, "XDG_STATE_HOME": str(xdg)}


def _gateway(env: dict[str, str], dep: str, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "awaremw", "gateway", dep, "--no-hbn", "--mqtt-port", "0",
         *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip


def _ready(p: subprocess.Popen[str]) -> int:
    """Wait for the gateway's 'motes ...' line; the embedded broker's port."""
    assert p.stdout is not None
    lines: list[str] = []
    for line in p.stdout:
        lines.append(line)
        if line.startswith("awaremw gateway: motes"):
            m = re.search(r"embedded MQTT broker: mqtt://127\.0\.0\.1:(\d+)", "".join(lines))
            assert m, lines
            return int(m.group(1))
    raise AssertionError(f"gateway did not start: {lines} {p.stderr.read() if p.stderr else ''}")


def _stop(p: subprocess.Popen[str]) -> str:
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    return err


def _account(xdg: Path, key: str) -> tuple[str, str]:
    text = (xdg / "awaremw/deployments" / key / "broker/mqtt-account").read_text()
    user, _, password = text.strip().partition(":")
    return user, password


async def _retained_defs(port: int, account: tuple[str, str]) -> list[str]:
    """The retained aware/def/* topics, read up to the gateway's 'online' status (a
    second subscription: its retained message comes after every one of the first)."""
    user, password = account
    topics: list[str] = []
    async with aiomqtt.Client("127.0.0.1", port, username=user, password=password) as c:
        await c.subscribe("aware/def/#", qos=1)
        await c.subscribe("aware/gateway/status", qos=1)
        async with asyncio.timeout(20):
            async for m in c.messages:
                if m.topic.value == "aware/gateway/status" and m.payload == b"online":
                    return topics
                if m.topic.matches("aware/def/#"):
                    topics.append(m.topic.value)
    raise AssertionError("unreachable")


async def _define(port: int, account: tuple[str, str], topic: str, payload: bytes) -> None:
    user, password = account
    async with aiomqtt.Client("127.0.0.1", port, username=user, password=password) as c:
        await c.publish(topic, payload, qos=1, retain=True)


@pytest.mark.slow
async def test_a_deployment_never_sees_the_definitions_of_another(tmp_path: Path) -> None:
    """Default state directory (XDG_STATE_HOME in tmp_path): grid_small defines a
    group type; romeo4r starts with none; grid_small again still has it."""
    env = _env(tmp_path)
    p = _gateway(env, "grid_small")
    try:
        port = await asyncio.to_thread(_ready, p)
        acc = _account(tmp_path, "grid_small")
        assert await _retained_defs(port, acc) == []
        await _define(port, acc, "aware/def/group/9", GROUP)
        await _define(port, acc, "aware/groups/9/600", json.dumps({"leader": 999}).encode())
        await _define(port, acc, "aware/groups/9/601", json.dumps({"leader": 3}).encode())
    finally:
        _stop(p)
    p = _gateway(env, "romeo4r")
    try:
        port = await asyncio.to_thread(_ready, p)
        assert await _retained_defs(port, _account(tmp_path, "romeo4r")) == []
    finally:
        _stop(p)
    with VersionStore(tmp_path / "awaremw/deployments/romeo4r/gateway.sqlite") as s:
        assert s.items() == []
    p = _gateway(env, "grid_small", "--speed", "10")
    try:
        port = await asyncio.to_thread(_ready, p)
        acc = _account(tmp_path, "grid_small")
        assert await _retained_defs(port, acc) == ["aware/def/group/9"]
        # Mote 999 is not in grid_small: its group's state was cleared at start;
        # mote 3's group was not reported again: cleared after the expiry.
        groups = await _collect(port, acc, "aware/groups/#", until=lambda ms: ms == [])
        assert groups == []
    finally:
        _stop(p)
    with VersionStore(tmp_path / "awaremw/deployments/grid_small/gateway.sqlite") as s:
        item = s.get(ItemKind.GROUP_TYPE, 9)
        assert item is not None and item.version == 1  # kept, not renumbered
    p = _gateway(env, "grid_small", "--fresh")
    try:
        port = await asyncio.to_thread(_ready, p)
        # The account is kept; the retained definitions are gone.
        assert await _retained_defs(port, _account(tmp_path, "grid_small")) == []
    finally:
        _stop(p)


async def _collect(
    port: int,
    account: tuple[str, str],
    topic: str,
    *,
    until: Callable[[list[str]], bool],
    timeout: float = 30.0,
) -> list[str]:
    """Retained ``topic`` states now, re-read at every change until ``until`` holds."""
    user, password = account
    live: dict[str, bytes] = {}
    async with aiomqtt.Client("127.0.0.1", port, username=user, password=password) as c:
        await c.subscribe(topic, qos=1)
        await c.subscribe("aware/gateway/status", qos=1)
        async with asyncio.timeout(timeout):
            synced = False
            async for m in c.messages:
                payload = m.payload if isinstance(m.payload, bytes) else b""
                if m.topic.value == "aware/gateway/status":
                    synced = True
                elif payload:
                    live[m.topic.value] = payload
                else:
                    live.pop(m.topic.value, None)
                if synced and until(sorted(live)):
                    return sorted(live)
    raise AssertionError("unreachable")


def _one_line_exit_2(r: subprocess.CompletedProcess[str], *expect: str) -> None:
    err = [ln for ln in r.stderr.strip().splitlines() if ": warning: no --secrets" not in ln]
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert len(err) == 1 and "Traceback" not in r.stderr, r.stderr
    assert all(e in err[0] for e in expect), err


@pytest.mark.parametrize("broker", ["embedded", "mqtt"])
def test_read_only_or_full_state_directory_is_one_line_and_exit_2(
    tmpfs: Mount, broker: str
) -> None:
    # With --mqtt the state directory is checked before the broker is reached.
    extra = [] if broker == "embedded" else ["--mqtt", "mqtt://127.0.0.1:1"]
    for d, why in ((tmpfs("64k", ro=True), "Read-only file system"), (tmpfs("64k"), "is full")):
        r = subprocess.run(
            [sys.executable, "-m", "awaremw", "gateway", "grid_small", "--state-dir",
             str(d / "state"), *extra],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        _one_line_exit_2(r, "awaremw gateway: ", why)


@pytest.mark.slow
async def test_disk_filling_at_run_time_is_reported_not_a_traceback(tmpfs: Mount) -> None:
    d = tmpfs("4m")
    state = d / "state"
    p = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "gateway", "grid_small", "--no-hbn", "--mqtt-port",
         "0", "--state-dir", str(state)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        port = await asyncio.to_thread(_ready, p)
        user, _, password = (state / "broker/mqtt-account").read_text().strip().partition(":")
        filler = fill(d)
        async with aiomqtt.Client("127.0.0.1", port, username=user, password=password) as c:
            await c.subscribe("aware/errors", qos=1)
            # The gateway's take of each definition: its republication, with a version.
            await c.subscribe("aware/def/channel/+", qos=1)
            last: dict[int, float] = {}
            for i in range(200):  # 8 channels (the motes' table), 25 versions each
                ch, period = i % 8 + 1, round(1 + i / 100, 2)
                last[ch] = period
                await c.publish(
                    f"aware/def/channel/{ch}",
                    json.dumps({"attr": "temperature", "group_type": "*",
                                "period_s": period, "agg": "avg"}).encode(),
                    qos=1, retain=True,
                )  # fmt: skip
            codes: list[str] = []
            taken: dict[int, float] = {}
            # Until the disk is reported full and the gateway took the last definition
            # of every channel: the broker acknowledged them all, but a loaded machine
            # may still be handing them to the gateway, and one it never received is
            # not one it lost (the broker keeps it retained).
            async with asyncio.timeout(20):
                async for m in c.messages:
                    doc = json.loads(m.payload)  # type: ignore[arg-type]
                    if m.topic.matches("aware/errors"):
                        codes.append(doc["code"])
                    elif "version" in doc:
                        taken[int(m.topic.value.rsplit("/", 1)[1])] = doc["period_s"]
                    if "state_write_failed" in codes and taken == last:
                        break
        filler.unlink()
    finally:
        err = _stop(p)
    assert "Traceback" not in err
    assert "cannot be written" in err
    # Written after the disk had room (the gateway retries, and at the latest on stop).
    with VersionStore(state / "gateway.sqlite") as s:
        stored = {i.item_id: i.json["period_s"] for i in s.items(ItemKind.CHANNEL) if i.json}
    assert stored == last  # the last definition of each, nothing lost


def test_leftover_group_states_are_sorted_by_their_leader() -> None:
    states = {
        "groups/1/600": json.dumps({"leader": 999}).encode(),  # not a mote here
        "groups/1/601": json.dumps({"leader": 3}).encode(),
        "groups/1/602": json.dumps({"group_type": 1, "merged_into": 601}).encode(),
        "groups/1/603": b"garbage",
    }
    found = sort_leftovers(states, {0, 1, 2, 3})
    assert found.kept == ("groups/1/601",)
    assert found.foreign == ("groups/1/600", "groups/1/602", "groups/1/603")


async def test_a_gateway_clears_group_states_left_on_an_external_broker(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """Mosquitto (broker_cfg ACL): a state led by mote 999 (not in grid_small) is
    cleared at start; one led by mote 3 when grid_small does not report it again."""
    for rel, leader in (("groups/9/600", 999), ("groups/9/601", 3)):
        body = json.dumps({"group_type": 9, "group_id": int(rel[-3:]), "leader": leader})
        assert pub(mosquitto, "gateway", f"aware/{rel}", body).returncode == 0
    p = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "gateway", "grid_small", "--no-hbn", "--speed", "10",
         "--mqtt", mosquitto.url("gateway"), "--state-dir", str(tmp_path / "state")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        async with Collector(mosquitto.url("viewer"), "aware/groups/#") as seen:
            cleared = await seen.wait_for(
                lambda ms: {t for t, pl, _ in ms if not pl} >= {"aware/groups/9/600",
                                                               "aware/groups/9/601"},
                timeout=30,
            )  # fmt: skip
        order = [t for t, pl, _ in cleared if not pl]
        assert order.index("aware/groups/9/600") < order.index("aware/groups/9/601")
    finally:
        _stop(p)
