"""Every shell example of README.md runs, as printed (ports filled in).

The ```sh blocks are read from README.md and run line by line with bash, in a
fresh directory, with this venv's ``bin`` first on PATH (what ``. .venv/bin/
activate`` does) and a private ``XDG_STATE_HOME``. Lines ending in ``&`` start
in the background and are awaited until they say they are up; the others must
exit 0. Substitutions, and nothing else: the Zenoh port 7447 and the Mosquitto
port 1884 become free ports, the embedded broker's 1883 the port the gateway
printed, ``ACCOUNT`` the account it keeps; demos and real-time experiments get
``--duration``/``--speed`` appended so that the whole file runs in about two
minutes (argparse: the last value wins). The external-broker recipe runs
against Mosquitto started by its own line (``awaremw broker --mosquitto``).
Skipped: the lines that (re)install the venv or run the test suite and lint.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from lines import Lines

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

SKIP = ("pip install", "pytest", ".ci/run", "tests/containers", "ruff check", "mypy")
# What a background line prints once it is up.
READY = {
    "router": r"listening on",
    "broker": r"Mosquitto on mqtt://",
    "fleet": r"awaremw fleet: ",
    "gateway": r"awaremw gateway: motes",
}
FAST = {  # appended to long real-time runs
    "demo": "--duration 60 --speed 10 --plain",  # the robot is tracked from ~t=30 s
    "experiment": "--duration 60 --speed 10",
}


def sh_blocks() -> list[list[str]]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = []
    for body in re.findall(r"```sh\n(.*?)```", text, re.S):
        lines = [ln.strip() for ln in body.splitlines()]
        blocks.append([ln for ln in lines if ln and not ln.startswith("#")])
    return blocks


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Shell:
    """Runs README lines in one directory, one environment, one set of ports."""

    def __init__(self, cwd: Path) -> None:
        self.cwd = cwd
        self.env = dict(os.environ)
        self.env["PATH"] = f"{BIN}{os.pathsep}{self.env.get('PATH', '')}"
        self.env["XDG_STATE_HOME"] = str(cwd / "state")
        self.env.pop("VIRTUAL_ENV", None)
        self.subst = {"7447": str(free_port()), "1884": str(free_port())}
        self.background: list[subprocess.Popen[str]] = []
        self.ran: list[str] = []

    def fill(self, line: str) -> str:
        line = line.replace(".venv/", f"{BIN.parent}/")
        for port, actual in self.subst.items():
            line = re.sub(rf"(?<=[:\s]){port}\b", actual, line)
        if "ACCOUNT" in line:
            (acc,) = (self.cwd / "state/awaremw/deployments").glob("*/broker/mqtt-account")
            account = acc.read_text().strip()
            line = line.replace("ACCOUNT", account)
        verb = line.split()[1] if line.startswith("awaremw ") else ""
        if verb in FAST and not line.endswith("&"):
            # before a trailing comment, if any
            code, hash_, comment = line.partition(" #")
            line = f"{code.rstrip()} {FAST[verb]}" + (f" #{comment}" if hash_ else "")
            if verb == "demo":
                line = line.replace(" #", f" --summary {self.cwd}/summary.txt #", 1)
                if " #" not in line:
                    line += f" --summary {self.cwd}/summary.txt"
        return line

    def run(self, raw: str) -> None:
        line = self.fill(raw)
        self.ran.append(line)
        code = line.split(" #", 1)[0].rstrip()
        if code.endswith("&"):
            self._background(code[:-1].rstrip())
            return
        p = subprocess.run(
            ["bash", "-c", code],
            cwd=self.cwd,
            env=self.env,
            capture_output=True,
            text=True,
            timeout=150,
            check=False,
        )
        why = f"{raw!r} -> {code!r}: exit {p.returncode}\n{p.stdout[-1500:]}\n{p.stderr[-1500:]}"
        assert p.returncode == 0, why
        assert "Traceback" not in p.stderr, p.stderr[-2000:]

    def _background(self, code: str) -> None:
        proc = subprocess.Popen(
            ["bash", "-c", f"exec {code}"],
            cwd=self.cwd,
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        self.background.append(proc)
        verb = code.split()[1]
        out = Lines(proc)
        if verb == "gateway" and "--secrets" not in code:
            m = out.wait_for(r"embedded MQTT broker: mqtt://127\.0\.0\.1:(\d+)", 60)
            self.subst["1883"] = m.group(1)
        out.wait_for(READY[verb], 60)

    def close(self) -> None:
        for p in reversed(self.background):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait(5)


@pytest.fixture
def shell(tmp_path: Path) -> Iterator[Shell]:
    s = Shell(tmp_path)
    try:
        yield s
    finally:
        s.close()


def test_readme_has_the_examples_this_test_runs() -> None:
    text = "\n".join(ln for b in sh_blocks() for ln in b)
    assert ". .venv/bin/activate" in text
    assert "awaremw broker --mosquitto" in text
    assert re.search(r"demo .*--mqtt mqtt://gateway:.*--robot-mqtt mqtt://operator:", text)
    assert "awaremw fleet grid_small --connect tcp/127.0.0.1:7447" in text


@pytest.mark.parametrize("index", range(len(sh_blocks())))
def test_readme_shell_block_runs(index: int, shell: Shell) -> None:
    block = sh_blocks()[index]
    if any("awaremw broker --mosquitto" in ln for ln in block) and not (
        shutil.which("mosquitto") or os.access("/usr/sbin/mosquitto", os.X_OK)
    ):
        if os.environ.get("AWAREMW_REQUIRE_MOSQUITTO") == "1":
            pytest.fail("mosquitto not installed")
        pytest.skip("mosquitto not installed")
    ran = 0
    for raw in block:
        if any(s in raw for s in SKIP):
            continue
        if raw.startswith(". .venv/bin/activate"):
            # activating puts awaremw on PATH
            p = subprocess.run(
                ["bash", "-c", f". {BIN}/activate && command -v awaremw"],
                capture_output=True, text=True, timeout=30, check=False,
            )  # fmt: skip
            assert p.returncode == 0 and p.stdout.strip() == str(BIN / "awaremw"), p
            ran += 1
            continue
        shell.run(raw)
        ran += 1
    if not ran:
        pytest.skip("nothing runnable here (venv and test-suite lines)")
