"""Errors that help a new user (issue 16): one-line errors and exit codes, the
channel that waits for its group type, deletes of undefined items, units."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from mosquitto import Mosquitto, free_port, mosquitto_fixture  # noqa: F401

from awaremw.cli.demo import no_record_reason, summary_text
from awaremw.cli.friendly import zenoh_message
from awaremw.gateway import schema
from awaremw.gateway.bridge import GatewayBridge
from awaremw.gateway.store import VersionStore
from awaremw.protocol.attributes import attribute_id, unit_of
from awaremw.protocol.frames import DataRecord


def _cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "awaremw", *args],
        capture_output=True, text=True, timeout=timeout, check=False,
    )  # fmt: skip


def test_zenoh_message_drops_rust_source_paths() -> None:
    raw = (
        "Unable to connect to any of [Single(tcp/127.0.0.1:7999)]. Timeout! at "
        "/root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/cc83980/zenoh/src/net/runtime/"
        "orchestrator.rs:388."
    )
    assert zenoh_message(RuntimeError(raw)) == (
        "Unable to connect to any of [Single(tcp/127.0.0.1:7999)]. Timeout!"
    )
    assert zenoh_message(RuntimeError("a\n b at src/x.rs:3:7")) == "a b"


@pytest.mark.zenoh
def test_unreachable_router_is_one_line_without_rust_paths() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    for args in (
        ("fleet", "grid_small", "--connect", ep, "--duration", "1", "--plain"),
        ("gateway", "grid_small", "--connect", ep, "--mqtt", "mqtt://127.0.0.1:1"),
        ("fleet-ctl", "--connect", ep, "list"),
    ):
        p = _cli(*args)
        assert p.returncode != 0, (args, p.stdout)
        # The open-radio notice of a run without --secrets is its own line; the error is one.
        err = "\n".join(
            ln for ln in p.stderr.strip().splitlines() if ": warning: no --secrets" not in ln
        )
        assert err.count("\n") == 0 and ".rs:" not in err and "Traceback" not in err, (args, err)
        # Zenoh says "Unable to connect ... Timeout!" of a router down and of a
        # secured one that refused us; the line says which (nothing listens here).
        assert f"cannot reach {ep}: nothing listens there" in err


def test_demo_with_an_unreachable_broker_fails_at_once() -> None:
    p = _cli("demo", "--mqtt", f"mqtt://127.0.0.1:{free_port()}", "--plain")
    assert p.returncode == 1
    assert p.stderr.strip().startswith("awaremw demo: cannot connect to the MQTT broker")
    assert p.stderr.strip().count("\n") == 0


def test_demo_with_a_wrong_password_fails_at_once_and_masks_it(mosquitto: Mosquitto) -> None:
    url = f"mqtt://operator:not-the-pw@127.0.0.1:{mosquitto.port}"
    p = _cli("demo", "--mqtt", url, "--plain")
    assert p.returncode == 1 and "not-the-pw" not in p.stderr and "operator:***@" in p.stderr


def test_no_record_reasons_and_summary_file_text() -> None:
    s = {
        "deployment": "romeo4r", "emulated_s": 45.0, "speed": 10.0,
        "mqtt": "mqtt://operator:***@127.0.0.1:1884", "records_received": 0,
        "records_repeated": 0, "records_produced": 7, "delivery_ratio": 0.0, "groups": [5],
        "lasting_groups": [5], "handovers": 0, "elections": 1, "frames_per_mote": 1.0,
        "energy_mj_per_mote": 2.0, "errors": [],
    }  # fmt: skip
    assert "--robot-mqtt the operator's" in no_record_reason(s, external=True)
    assert "none of the 7" in no_record_reason(s, external=False)
    assert "no group formed" in no_record_reason({**s, "records_produced": 0}, external=False)
    # A deployment without group types: no longer --duration helps, and it says so.
    none = {**s, "records_produced": 0, "group_types": [], "channels": []}
    why = no_record_reason(none, external=False)
    assert "romeo4r defines no group type" in why and "--duration" not in why
    text = summary_text(s)
    assert "records received (MQTT): 0\n" in text and "***" in text
    assert "group ids lasting >= 4 s: 5\n" in text


@pytest.fixture
def bridge() -> Iterator[GatewayBridge]:
    store = VersionStore()
    yield GatewayBridge(store, schema.Limits())
    store.close()


def test_channel_on_an_undefined_group_type_is_accepted_with_a_warning(
    bridge: GatewayBridge,
) -> None:
    ch = json.dumps({"attr": "temperature", "group_type": 3, "period_s": 2}).encode()
    out = bridge.handle("def/channel/1", ch, source="aware/def/channel/1")
    assert out.accepted and out.error is not None
    assert out.error.code == "waits_for_group_type" and out.error.warning
    doc = json.loads(out.error.to_json())
    assert doc["level"] == "warning" and doc["topic"] == "aware/def/channel/1"
    assert "def/group/3" in doc["error"]
    assert bridge.stats.waiting_channels == 1 and bridge.stats.refused == 0
    # a command to that group type is still refused: it would be lost
    cmd = json.dumps({"target": {"group_type": 3, "group_id": "*"}, "args": {}}).encode()
    refused = bridge.handle("cmd/led", cmd, source="aware/cmd/led")
    assert not refused.accepted and refused.error is not None
    assert refused.error.code == "unknown_target" and not refused.error.warning
    assert "level" not in json.loads(refused.error.to_json())
    # once the type exists, a channel on it (or on any type) has no warning
    grp = json.dumps({"conditions": [{"attr": "temperature", "op": ">", "value": 1}]}).encode()
    assert bridge.handle("def/group/3", grp, source="aware/def/group/3").error is None
    ch2 = json.dumps({"attr": "light", "group_type": 3, "period_s": 2}).encode()
    assert bridge.handle("def/channel/2", ch2, source="aware/def/channel/2").error is None
    any_t = json.dumps({"attr": "light", "group_type": "*", "period_s": 2}).encode()
    assert bridge.handle("def/channel/4", any_t, source="aware/def/channel/4").error is None


def test_records_carry_their_unit(bridge: GatewayBridge) -> None:
    for i, (attr, agg) in enumerate((("temperature", "avg"), ("rssi:100", "max"),
                                     ("light", "count"))):  # fmt: skip
        ch = json.dumps({"attr": attr, "group_type": "*", "period_s": 2, "agg": agg}).encode()
        assert bridge.handle(f"def/channel/{i}", ch, source=f"aware/def/channel/{i}").accepted
    units = []
    for i, agg_id in enumerate((schema.AGG_NAMES["avg"], schema.AGG_NAMES["max"],
                                schema.AGG_NAMES["count"])):  # fmt: skip
        (pub,) = bridge.on_record(DataRecord(i, 1, 7, 3, agg_id, 21.5, 2, 4), 10.0)
        units.append(json.loads(pub.payload).get("unit"))
    assert units == ["°C", "dBm", None]
    assert unit_of("humidity") == "%RH" and unit_of("battery") == "V" and unit_of("x") == "m"
    assert unit_of("light", "count") == "" and unit_of(None) == ""
    attribute_id("gas")  # every unit-bearing name is an attribute the schema knows


def test_define_and_delete_say_what_is_not_defined(mosquitto: Mosquitto) -> None:
    url = mosquitto.url("operator")
    p = _cli("delete", "channel", "9", "--mqtt", url)
    assert p.returncode == 0 and "aware/def/channel/9 was not defined" in p.stdout, p
    p = _cli("define", "channel", "9", "--attr", "temperature", "--group-type", "5",
             "--period", "2", "--mqtt", url)  # fmt: skip
    assert p.returncode == 0 and "waits_for_group_type" in p.stderr, p
    p = _cli("delete", "channel", "9", "--mqtt", url)
    assert p.returncode == 0 and p.stdout.strip() == "aware/def/channel/9 (deleted)", p
    p = _cli("define", "group", "5", "temperature > 40", "--mqtt", url)
    assert p.returncode == 0
    p = _cli("define", "channel", "9", "--attr", "temperature", "--group-type", "5",
             "--period", "2", "--mqtt", url)  # fmt: skip
    assert p.returncode == 0 and "waits_for_group_type" not in p.stderr, p


@pytest.mark.slow
@pytest.mark.zenoh
def test_demo_on_a_deployment_without_group_types_says_so(tmp_path: Path) -> None:
    p = _cli("demo", "--deployment", "grid_small", "--duration", "10", "--speed", "5",
             "--plain", "--insecure", "--mqtt-port", "0",
             "--summary", str(tmp_path / "summary.txt"))  # fmt: skip
    assert p.returncode == 1, p.stderr[-2000:]
    last = p.stderr.strip().splitlines()[-1]
    assert "grid_small defines no group type" in last and "--duration" not in last, last
    assert "no group type defined by this deployment" in p.stdout
