"""The README's robot client works as printed, against a real fleet and gateway.

The Python block under "A robot client in Python" is extracted from README.md
and run unchanged, as a user would: ``awaremw fleet romeo4r`` and ``awaremw
gateway romeo4r`` (embedded MQTT broker, its state in the default directory
under a private ``XDG_STATE_HOME``) are real processes talking over Zenoh on
loopback, and the block finds the broker and its account by itself. (The
fleet and gateway run at x4 with a shared start, to keep the test short.)
"""

from __future__ import annotations

import ast
import os
import re
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from lines import Lines

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.slow


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def readme_robot_client() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## A robot client in Python", 1)[1]
    m = re.search(r"```python\n(.*?)```", section, re.S)
    assert m, "README has no python block in 'A robot client in Python'"
    return m.group(1)


@pytest.fixture
def procs() -> Iterator[list[subprocess.Popen[str]]]:
    started: list[subprocess.Popen[str]] = []
    yield started
    for p in started:
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


def test_readme_robot_client_gets_data(procs: list[subprocess.Popen[str]], tmp_path: Path) -> None:
    zenoh_ep = f"tcp/127.0.0.1:{_free_port()}"
    start_at = time.time() + 3.0
    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path / "state")}

    def spawn(*args: str) -> subprocess.Popen[str]:
        p = subprocess.Popen(
            [sys.executable, "-m", "awaremw", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=tmp_path,
            env=env,
        )
        procs.append(p)
        return p

    spawn(
        "fleet",
        "romeo4r",
        "--without-kind",
        "gateway",
        "--plain",
        "--speed",
        "4",
        "--listen",
        zenoh_ep,
        "--start-at",
        f"{start_at:.3f}",
        "--progress",
        "30",
    )
    gw = Lines(
        spawn(
            "gateway",
            "romeo4r",
            "--connect",
            zenoh_ep,
            "--speed",
            "4",
        )
    )
    gw.wait_for(r"embedded MQTT broker: mqtt://([\d.]+):(\d+) account '(\w+)'", timeout=30)

    script = tmp_path / "robot.py"
    script.write_text(readme_robot_client())  # as printed
    client = subprocess.Popen(
        [sys.executable, "-u", str(script)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,
        env=env,
    )
    procs.append(client)
    robot = Lines(client)
    # The robot starts moving at t = 25 s and is heard above the threshold from
    # about t = 32 s (8 s of wall time at x4); its group's first record follows
    # within a few channel periods.
    m = robot.wait_for(r"^aware/data/1/1/(\d+) (\{.*\})$", timeout=90)
    record = ast.literal_eval(m.group(2))  # the client prints the decoded JSON object
    assert record["agg"] == "avg" and record["count"] >= 1
    assert 1 <= int(m.group(1)) <= 0xFFFE
    assert -20.0 < record["value"] < 60.0  # a temperature in degC
