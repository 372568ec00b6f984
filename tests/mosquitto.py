"""A real Mosquitto broker for tests, started on a free loopback port.

It runs ``broker_cfg/mosquitto.conf`` (password file, ACL) with the listener
and file paths rewritten, persistence off (``awaremw.cli.broker.local_config``,
what ``awaremw broker --mosquitto`` runs). Use the ``mosquitto`` fixture
(``from mosquitto import mosquitto_fixture  # noqa: F401`` in a test module). Without
the binary the tests skip, unless ``AWAREMW_REQUIRE_MOSQUITTO=1`` (CI), when
they fail.

Accounts: ``operator``, ``gateway``, ``viewer`` with passwords
``<name>-pw`` (see broker_cfg/make_passwd.sh).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import aiomqtt
import pytest

from awaremw.cli.broker import local_config
from awaremw.gateway.mqtt import MqttSettings
from awaremw.security.keys import make_broker_tls

ROOT = Path(__file__).resolve().parent.parent
CFG = ROOT / "broker_cfg"
PASSWORDS = {"operator": "operator-pw", "gateway": "gateway-pw", "viewer": "viewer-pw"}


def find_tool(name: str) -> str | None:
    for d in ("", "/usr/sbin", "/usr/local/sbin", "/usr/bin"):
        p = (
            shutil.which(name)
            if not d
            else (f"{d}/{name}" if os.access(f"{d}/{name}", os.X_OK) else None)
        )
        if p:
            return p
    return None


def require(name: str) -> str:
    """Path of a Mosquitto tool; skip (or fail in CI) when it is missing."""
    p = find_tool(name)
    if p is None:
        msg = f"{name} not installed (apt-get install mosquitto mosquitto-clients)"
        if os.environ.get("AWAREMW_REQUIRE_MOSQUITTO") == "1":
            pytest.fail(msg)
        pytest.skip(msg)
    return p


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Mosquitto:
    """One broker process; :meth:`kill` and :meth:`start` again on the same port."""

    def __init__(self, workdir: Path, port: int | None = None, *, tls: bool = False) -> None:
        self.binary = require("mosquitto")
        self.workdir = workdir
        self.port = port or free_port()
        self.tls_port = free_port() if tls else None
        self.ca_file = workdir / "ca.crt"
        if tls:
            make_cert(workdir)
        self.proc: subprocess.Popen[bytes] | None = None
        self.conf = workdir / "mosquitto.conf"
        self.log = workdir / "mosquitto.log"
        self._write_conf()

    def _write_conf(self) -> None:
        extra: tuple[str, ...] = ()
        if self.tls_port is not None:
            extra = (
                f"listener {self.tls_port} 127.0.0.1",
                f"certfile {self.workdir / 'server.crt'}",
                f"keyfile {self.workdir / 'server.key'}",
            )
        local_config(CFG, self.workdir, self.port, extra=extra)

    def lock_out(self, *users: str) -> None:
        """Remove accounts from the password file (takes effect at start or :meth:`reload`)."""
        lines = (CFG / "passwd").read_text().splitlines()
        keep = [ln for ln in lines if ln.split(":", 1)[0] not in users]
        (self.workdir / "passwd").write_text("\n".join(keep) + "\n")

    def let_in(self) -> None:
        """Restore every account and make the running broker re-read the password file."""
        shutil.copy(CFG / "passwd", self.workdir / "passwd")
        self.reload()

    def reload(self) -> None:
        assert self.proc is not None and self.proc.poll() is None
        self.proc.send_signal(signal.SIGHUP)

    def url(self, user: str | None = None) -> str:
        cred = f"{user}:{PASSWORDS[user]}@" if user else ""
        return f"mqtt://{cred}127.0.0.1:{self.port}"

    def tls_url(self, user: str) -> str:
        assert self.tls_port is not None
        return f"mqtts://{user}:{PASSWORDS[user]}@127.0.0.1:{self.tls_port}"

    def start(self, timeout: float = 10.0) -> None:
        assert self.proc is None or self.proc.poll() is not None
        self.proc = subprocess.Popen(
            [self.binary, "-c", str(self.conf)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                err = self.proc.stderr.read().decode() if self.proc.stderr else ""
                log = self.log.read_text() if self.log.exists() else ""
                raise RuntimeError(f"mosquitto exited with {self.proc.returncode}: {err}{log}")
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2),
            ):
                return
            time.sleep(0.02)  # polling the port: the process gives no readiness signal
        raise RuntimeError(f"mosquitto did not listen on {self.port} within {timeout} s")

    def kill(self) -> None:
        """SIGKILL: the broker vanishes without closing anything gracefully."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(5)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.kill()


def make_cert(workdir: Path) -> None:
    """A CA and a server certificate for localhost/127.0.0.1, as `awaremw keys init` makes."""
    for name, data in make_broker_tls().items():
        (workdir / name).write_bytes(data)


@pytest.fixture(name="mosquitto")
def mosquitto_fixture(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mosquitto]:
    m = Mosquitto(tmp_path_factory.mktemp("mosquitto"))
    m.start()
    try:
        yield m
    finally:
        m.stop()


@pytest.fixture(name="mosquitto_tls")
def mosquitto_tls_fixture(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mosquitto]:
    """Mosquitto with a second, TLS listener (``tls_url``, ``ca_file``)."""
    m = Mosquitto(tmp_path_factory.mktemp("mosquitto"), tls=True)
    m.start()
    try:
        yield m
    finally:
        m.stop()


def pub(
    m: Mosquitto,
    user: str,
    topic: str,
    payload: str | bytes | None,
    *,
    retain: bool = True,
    qos: int = 1,
    version: str = "5",
) -> subprocess.CompletedProcess[bytes]:
    """``mosquitto_pub`` as ``user``; ``payload=None`` sends an empty (deleting) message."""
    args = [*_client_args(m, "mosquitto_pub", user, topic), "-q", str(qos), "-V", version]
    if retain:
        args.append("-r")
    if payload is None:
        args.append("-n")
        data = None
    else:
        args += ["-s"]
        data = payload.encode() if isinstance(payload, str) else payload
    return subprocess.run(args, input=data, capture_output=True, timeout=10, check=False)


def _client_args(m: Mosquitto, tool: str, user: str, topic: str) -> list[str]:
    """A Mosquitto client on the test broker, as ``user``, on ``topic``."""
    return [require(tool), "-h", "127.0.0.1", "-p", str(m.port), "-u", user,
            "-P", PASSWORDS[user], "-t", topic]  # fmt: skip


def sub_args(m: Mosquitto, user: str, topic: str, *extra: str) -> list[str]:
    """Arguments of a ``mosquitto_sub`` printing ``topic payload`` lines."""
    return [
        *_client_args(m, "mosquitto_sub", user, topic),
        "-v",
        "-q",
        "1",
        *extra,
    ]


class Collector:
    """An aiomqtt subscriber that records ``(topic, payload, retain)`` for assertions.

    ``await c.wait_for(pred)`` waits (with a timeout) until ``pred(messages)``
    holds; nothing sleeps for synchronisation.
    """

    def __init__(self, url: str, topic: str, *, protocol: str = "5") -> None:
        self.settings = MqttSettings.from_url(url)
        self.topic = topic
        self.protocol = protocol
        self.messages: list[tuple[str, bytes, bool]] = []
        self._changed = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self.subscribes = 0  # successful (re)subscriptions

    async def __aenter__(self) -> Collector:
        s = self.settings
        ready = asyncio.Event()
        proto = aiomqtt.ProtocolVersion.V5 if self.protocol == "5" else aiomqtt.ProtocolVersion.V311

        async def run() -> None:
            # Reconnects (polling every 50 ms) so that it survives a broker restart.
            while True:
                client = aiomqtt.Client(
                    s.host,
                    s.port,
                    username=s.username,
                    password=s.password,
                    protocol=proto,
                    identifier=f"collector-{id(self):x}",  # never "" (amqtt shares that session)
                )
                try:
                    async with client:
                        await client.subscribe(self.topic, qos=1)
                        self.subscribes += 1
                        ready.set()
                        self._changed.set()
                        async for m in client.messages:
                            if not m.topic.matches(self.topic):
                                continue  # amqtt: retained messages of others' filters
                            payload = m.payload if isinstance(m.payload, bytes) else b""
                            self.messages.append((m.topic.value, payload, bool(m.retain)))
                            self._changed.set()
                except aiomqtt.MqttError:
                    self._changed.set()
                    await asyncio.sleep(0.05)

        self._task = task = asyncio.create_task(run())
        waiter = asyncio.create_task(ready.wait())
        await asyncio.wait({task, waiter}, timeout=10, return_when=asyncio.FIRST_COMPLETED)
        waiter.cancel()
        if task.done():
            task.result()
        assert ready.is_set(), "collector could not subscribe"
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                await self._task

    def payloads(self, prefix: str = "") -> list[bytes]:
        return [p for t, p, _ in self.messages if t.startswith(prefix)]

    async def wait_for(
        self, pred: Callable[[list[tuple[str, bytes, bool]]], bool], timeout: float = 10.0
    ) -> list[tuple[str, bytes, bool]]:
        await self.until(lambda: pred(self.messages), timeout)
        return self.messages

    async def until(self, cond: Callable[[], bool], timeout: float = 10.0) -> None:
        """Wait until ``cond()`` holds, re-checking at every message or (re)connection."""

        async def loop() -> None:
            while not cond():
                self._changed.clear()
                if self._task is not None and self._task.done():
                    self._task.result()
                    raise AssertionError("collector stopped")
                await self._changed.wait()

        try:
            await asyncio.wait_for(loop(), timeout)
        except TimeoutError:
            raise AssertionError(
                f"timed out after {timeout} s; {len(self.messages)} messages, last: "
                f"{self.messages[-5:]!r}"
            ) from None


class MosquittoSub:
    """A ``mosquitto_sub -v`` process; ``lines`` are ``(topic, payload)`` as they arrive."""

    def __init__(self, m: Mosquitto, user: str, topic: str, *extra: str) -> None:
        self.args = sub_args(m, user, topic, *extra)
        self.lines: list[tuple[str, str]] = []
        self._changed = asyncio.Event()
        self._proc: asyncio.subprocess.Process | None = None
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> MosquittoSub:
        self._proc = await asyncio.create_subprocess_exec(
            *self.args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
        )
        self._task = asyncio.create_task(self._read())
        return self

    async def _read(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        async for raw in self._proc.stdout:
            # A payload need not be UTF-8 (a refused definition a viewer may read).
            topic, _, payload = raw.decode(errors="replace").rstrip("\n").partition(" ")
            self.lines.append((topic, payload))
            self._changed.set()
        self._changed.set()

    async def __aexit__(self, *exc: object) -> None:
        if self._proc is not None and self._proc.returncode is None:
            self._proc.terminate()
            await self._proc.wait()
        if self._task is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    async def wait_for(
        self, pred: Callable[[list[tuple[str, str]]], bool], timeout: float = 20.0
    ) -> list[tuple[str, str]]:
        async def loop() -> None:
            while not pred(self.lines):
                self._changed.clear()
                if self._task is not None and self._task.done():
                    err = b""
                    if self._proc is not None and self._proc.stderr is not None:
                        err = await self._proc.stderr.read()
                    raise AssertionError(f"mosquitto_sub ended: {err.decode()}")
                await self._changed.wait()

        try:
            await asyncio.wait_for(loop(), timeout)
        except TimeoutError:
            raise AssertionError(
                f"timed out after {timeout} s; {len(self.lines)} lines, last: {self.lines[-5:]!r}"
            ) from None
        return self.lines
