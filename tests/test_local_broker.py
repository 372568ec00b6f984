"""find_local_broker reads the embedded brokers' state directories: the one on
the asked port, else the one that answers, else the latest; bad files skipped."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

from awaremw.gateway.local_broker import find_local_broker


def state(base: Path, rel: str, account: str, port: int | None, mtime: float) -> Path:
    d = base / rel
    d.mkdir(parents=True)
    (d / "mqtt-account").write_text(account)
    if port is not None:
        (d / "broker.json").write_text(json.dumps({"port": port}))
    for f in d.iterdir():
        os.utime(f, (mtime, mtime))
    return d


def test_none_without_state(tmp_path: Path) -> None:
    assert find_local_broker(base=tmp_path / "nothing") is None
    assert find_local_broker(base=tmp_path) is None


def test_port_then_listening_then_latest(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        live = s.getsockname()[1]
        with socket.socket() as t:
            t.bind(("127.0.0.1", 0))
            dead = t.getsockname()[1]  # bound, not listening: refuses connections
            state(tmp_path, "broker", "awaremw:old\n", dead, 1_000)
            state(tmp_path, "romeo4r/broker", "awaremw:live\n", live, 2_000)
            state(tmp_path, "fire/broker", "awaremw:new\n", dead + 0, 3_000)
            state(tmp_path, "bad/broker", "no colon here\n", live, 4_000)
            state(tmp_path, "a/b/c/d/broker", "awaremw:too-deep\n", live, 5_000)
            b = find_local_broker(base=tmp_path)
            assert b is not None and b.password == "live" and b.port == live
            assert b.url == f"mqtt://awaremw:live@127.0.0.1:{live}"
            b = find_local_broker(dead, base=tmp_path)
            assert b is not None and b.password == "new"  # the latest on that port
            assert find_local_broker(1, base=tmp_path) is None


def test_default_port_without_a_port_file(tmp_path: Path) -> None:
    state(tmp_path, "broker", "u:p", None, 1_000)
    b = find_local_broker(base=tmp_path)
    assert b is not None and (b.port, b.username, b.password) == (1883, "u", "p")
