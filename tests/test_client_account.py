"""Client verbs on the gateway's machine find its embedded broker's account by
themselves; the gateway refuses an unknown command name on ``aware/errors``
with the list of the commands motes accept.

A real ``awaremw gateway`` (embedded broker, default state directory under a
private ``XDG_STATE_HOME``) and real client processes.
"""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import aiomqtt
import pytest
from lines import Lines

from awaremw.gateway.local_broker import find_local_broker
from awaremw.nodes.kinds import COMMANDS

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def gateway(tmp_path: Path) -> Iterator[tuple[dict[str, str], int]]:
    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path / "state")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "gateway", "grid_small",
         "--listen", f"tcp/127.0.0.1:{free_port()}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
    )  # fmt: skip
    try:
        m = Lines(proc).wait_for(r"embedded MQTT broker: mqtt://[\d.]+:(\d+)", timeout=60)
        yield env, int(m.group(1))
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def awaremw(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "awaremw", *args], env=env,
                          capture_output=True, text=True, timeout=60, check=False)  # fmt: skip


def test_client_verbs_find_the_account_and_unknown_commands_are_refused(
    gateway: tuple[dict[str, str], int], tmp_path: Path
) -> None:
    env, port = gateway
    # No --mqtt, no account on the command line: the verb reads the broker's state.
    r = awaremw(env, "define", "group", "1", "temperature > 15", "--wait", "2")
    assert r.returncode == 0, r.stderr
    # --wait waited for the gateway's take: its version, on the retained topic.
    assert r.stdout.startswith("aware/def/group/1 ") and r.stdout.endswith(" (version 1)\n")
    # A loopback URL without an account gets the account of the broker on that port.
    r = awaremw(env, "watch", "aware/def/group/#", "--count", "1", "--timeout", "20",
                "--mqtt", f"mqtt://127.0.0.1:{port}")  # fmt: skip
    assert r.returncode == 0 and r.stdout.startswith("aware/def/group/1 "), r.stderr
    # Elsewhere (another state home) there is no account: the refusal says where to look.
    other = {**env, "XDG_STATE_HOME": str(tmp_path / "nothing")}
    r = awaremw(other, "watch", "--count", "1", "--timeout", "5",
                "--mqtt", f"mqtt://127.0.0.1:{port}")  # fmt: skip
    assert r.returncode == 1 and "authorized" in r.stderr.lower(), r

    local = find_local_broker(port, base=tmp_path / "state" / "awaremw")
    assert local is not None

    async def refused() -> dict[str, object]:
        async with aiomqtt.Client(
            local.host, local.port, username=local.username, password=local.password,
            identifier="t-unknown",
        ) as c:  # fmt: skip
            await c.subscribe("aware/errors", qos=1)
            await c.publish("aware/cmd/reboot", b'{"target": "all"}', qos=1)
            async with asyncio.timeout(20):
                async for m in c.messages:
                    err = json.loads(bytes(m.payload))
                    if err.get("topic") == "aware/cmd/reboot":
                        return dict(err)
        raise AssertionError("unreachable")

    err = asyncio.run(refused())
    assert err["code"] == "unknown_command"
    assert f"motes accept: {', '.join(sorted(COMMANDS))}" in str(err["error"])
