"""Run the shell and Python blocks of a Markdown file as printed (ports filled in).

Shared by tests/test_readme_shell.py (README.md) and tests/test_docs.py
(docs/*.md). Blocks run in a fresh directory, with this venv's ``bin`` first on
PATH (what ``. .venv/bin/activate`` does) and a private ``XDG_STATE_HOME``.
Lines ending in ``&`` start in the background and are awaited until they say
they are up; the others must exit 0. Substitutions, and nothing else: the
Zenoh ports 7447/7448, the Mosquitto port 1884 and the web port 8080 become
free ports, the embedded broker's 1883 the port the gateway printed; demos and
real-time experiments get ``--duration``/``--speed`` appended so that a file
runs in minutes (argparse: the last value wins), and ``--seeds A-B`` runs two
seeds.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from lines import Lines

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent

# What a background line prints once it is up.
READY = {
    "router": r"listening on",
    "broker": r"Mosquitto on mqtt://",
    "fleet": r"awaremw fleet: ",
    "gateway": r"awaremw gateway: motes",
}
FAST = {  # appended to long real-time runs
    "demo": "--duration 60 --speed 10 --plain",  # the robot is tracked from ~t=32 s
    "experiment": "--duration 60 --speed 10",
}
PORTS = ("7447", "7448", "1884", "8080")


@dataclass(frozen=True)
class Block:
    """A fenced block of a Markdown file: its language, first line number, lines."""

    path: Path
    lang: str
    line: int
    text: str
    section: str  # the ``## `` heading it is under ("" before the first)

    @property
    def commands(self) -> list[str]:
        """Shell lines without blanks and whole-line comments."""
        lines = [ln.strip() for ln in self.text.splitlines()]
        return [ln for ln in lines if ln and not ln.startswith("#")]

    def __str__(self) -> str:
        return f"{self.path.name}:{self.line}"


def blocks(path: Path, langs: tuple[str, ...] = ("sh", "python")) -> list[Block]:
    text = path.read_text(encoding="utf-8")
    out = []
    for m in re.finditer(r"^```(\w*)\n(.*?)^```", text, re.S | re.M):
        if m.group(1) in langs:
            before = text[: m.start()]
            headings = re.findall(r"^## (.*)$", before, re.M)
            section = headings[-1] if headings else ""
            out.append(Block(path, m.group(1), before.count("\n") + 1, m.group(2), section))
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Shell:
    """Runs a document's lines in one directory, one environment, one set of ports."""

    def __init__(self, cwd: Path) -> None:
        self.cwd = cwd
        self.env = dict(os.environ)
        self.env["PATH"] = f"{BIN}{os.pathsep}{self.env.get('PATH', '')}"
        self.env["XDG_STATE_HOME"] = str(cwd / "state")
        self.env.pop("VIRTUAL_ENV", None)
        self.subst = {port: str(free_port()) for port in PORTS}
        self.background: list[subprocess.Popen[str]] = []
        self.ran: list[str] = []

    def ports(self, text: str) -> str:
        for port, actual in self.subst.items():
            text = re.sub(rf"(?<=[:\s]){port}\b", actual, text)
        return text

    def fill(self, line: str) -> str:
        line = line.replace(".venv/", f"{BIN.parent}/")
        line = self.ports(line)
        line = re.sub(r"--seeds \d+-\d+", "--seeds 1-2", line)
        verb = line.split()[1] if line.startswith("awaremw ") else ""
        if verb in FAST and not line.endswith("&"):
            # before a trailing comment, if any
            code, hash_, comment = line.partition(" #")
            extra = FAST[verb]
            if verb == "experiment" and "--virtual" in code:
                extra = ""  # as fast as the CPU allows already
            if verb == "demo":
                extra += f" --summary {self.cwd}/summary.txt"
            line = f"{code.rstrip()} {extra}".rstrip() + (f" #{comment}" if hash_ else "")
        return line

    def run(self, raw: str, timeout: float = 150) -> None:
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
            timeout=timeout,
            check=False,
        )
        why = f"{raw!r} -> {code!r}: exit {p.returncode}\n{p.stdout[-1500:]}\n{p.stderr[-1500:]}"
        assert p.returncode == 0, why
        assert "Traceback" not in p.stderr, p.stderr[-2000:]

    def python(self, block: Block, argv: list[str], timeout: float = 120) -> str:
        """Run a Python block as a script (ports filled in); its stdout."""
        script = self.cwd / f"block_{block.line}.py"
        script.write_text(self.ports(block.text), encoding="utf-8")
        p = subprocess.run(
            [sys.executable, str(script), *(self.ports(a) for a in argv)],
            cwd=self.cwd,
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
        why = f"{block}: exit {p.returncode}\n{p.stdout[-1500:]}\n{p.stderr[-3000:]}"
        assert p.returncode == 0, why
        return p.stdout

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
        if verb == "gateway" and "--mqtt" not in code:
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
        self.background.clear()
