"""Client verbs: ``define``, ``delete``, ``command``, ``watch`` (an IP device over MQTT).

Payloads are validated locally with the gateway's own schema before they are
sent (so most mistakes are reported at once); the gateway validates again and
reports refusals on ``<prefix>/errors``. A retained payload is read back: one
the broker did not keep (an ACL refusal) exits 1. ``--wait S`` then waits up to
S seconds for the gateway: a definition until its version shows on the retained
topic (the gateway republishes what it took, with the version), a deletion or a
command for a refusal; a refusal, or a definition nobody took, exits 1.

Without ``--mqtt`` the verbs talk to the embedded broker of a gateway on this
machine, with the account it keeps (:mod:`awaremw.gateway.local_broker`); a
loopback URL without an account gets that account too.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import re
import secrets
import sys
import time
from dataclasses import dataclass, replace
from typing import Any

import aiomqtt

from awaremw.cli.friendly import refuse
from awaremw.cli.helptext import add_verb, add_wall_timeout
from awaremw.gateway import schema
from awaremw.gateway.local_broker import LOOPBACK, find_local_broker, state_base
from awaremw.gateway.mqtt import AckedClient, BadMqttUrl, MqttSettings, speaks_mqtt5
from awaremw.nodes.kinds import COMMANDS
from awaremw.security.redact import mask_url, redact

DEFAULT_URL = "mqtt://127.0.0.1:1883"
# The gateway's own checks, with the commands motes accept.
LIMITS = schema.Limits(commands=frozenset(COMMANDS))
# How long `delete` waits for the retained definition it removes (brokers send
# retained messages right after the subscription is acknowledged).
RETAINED_WAIT_S = 1.0
_COND_RE = re.compile(r"^\s*(\S+?)\s*(<=|>=|==|!=|<|>)\s*(\S+)\s*$")
_SPLIT_RE = re.compile(r"\s*(?:,|&&|\band\b)\s*")


class UsageError(ValueError):
    """A command line the client cannot turn into a payload."""


# --------------------------------------------------------------------------- registration


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--mqtt",
        default=None,
        metavar="URL",
        help="broker, mqtt[s]://[user:pass@]host:port (default: the embedded broker of a "
        f"gateway on this machine, with its account; else {DEFAULT_URL})",
    )
    p.add_argument("--prefix", default="aware", help="topic prefix (default aware)")
    p.add_argument("--client-id", default=None, help="MQTT client id (default: random)")
    p.add_argument("--ca-file", default=None, help="CA bundle for mqtts://")


def _wait_opt(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--wait",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for the gateway: a definition until it shows with its "
        "version, anything else for a refusal on <prefix>/errors (exit 1 if refused or "
        "not taken)",
    )


def _commands_text() -> str:
    width = max(len(n) for n in COMMANDS)
    return "\n".join(f"  {n:<{width}}  {doc}" for n, doc in sorted(COMMANDS.items()))


_BROKER_NOTE = (
    "Without --mqtt: the embedded broker of a gateway on this machine, with the account\n"
    "it keeps under ~/.local/state/awaremw; else --mqtt mqtt://USER:PASS@HOST:PORT."
)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    d = add_verb(
        sub,
        "define",
        "define a group type or a channel (retained MQTT message)",
        "Publish a definition on the MQTT contract (<prefix>/def/...), checked first\n"
        "with the gateway's own rules.\n\n" + _BROKER_NOTE,
        [
            'awaremw define group 1 "temperature > 45" --hysteresis 1',
            'awaremw define group 2 "rssi:100 > -89"',
            "awaremw define channel 1 --attr temperature --group-type 1 --period 2 --agg avg",
        ],
    )
    dsub = d.add_subparsers(dest="what", metavar="group|channel", required=True)
    g = add_verb(
        dsub,
        "group",
        'define a group type: TYPE "attr op value"...',
        "A group type: motes whose readings meet every condition form groups of this\n"
        "type (retained on <prefix>/def/group/TYPE).\n\n" + _BROKER_NOTE,
        [
            'awaremw define group 1 "temperature > 45" --hysteresis 1',
            'awaremw define group 2 "rssi:100 > -89" "x < 20"',
        ],
    )
    g.add_argument("type", metavar="TYPE", help="group type id (0..254)")
    g.add_argument(
        "conditions",
        nargs="+",
        metavar="CONDITION",
        help='e.g. "temperature > 45"; several are ANDed',
    )
    g.add_argument("--hysteresis", type=float, default=0.0, help="membership hysteresis")
    _common(g)
    _wait_opt(g)
    g.set_defaults(func=cmd_define_group)

    c = add_verb(
        dsub,
        "channel",
        "define a channel",
        "A channel: an attribute sampled by the members of groups, aggregated in the\n"
        "network and published on <prefix>/data/ID/TYPE/GROUP.\n\n" + _BROKER_NOTE,
        [
            "awaremw define channel 1 --attr temperature --group-type 1 --period 2 --agg avg",
            "awaremw define channel 2 --attr light --period 5 --agg max",
        ],
    )
    c.add_argument("id", metavar="ID", help="channel id (0..255)")
    c.add_argument("--attr", required=True, help="attribute, e.g. temperature, rssi:100")
    c.add_argument("--group-type", default="*", help='group type or "*" (default *)')
    c.add_argument("--group-id", default="*", help='group id or "*" (default *)')
    c.add_argument("--period", type=float, required=True, metavar="S", help="sampling period, s")
    c.add_argument("--agg", default="avg", choices=sorted(schema.AGG_NAMES), help="aggregation")
    _common(c)
    _wait_opt(c)
    c.set_defaults(func=cmd_define_channel)

    x = add_verb(
        sub,
        "delete",
        "delete a group type or a channel",
        "Clear a retained definition; the gateway spreads the deletion to the motes.\n\n"
        + _BROKER_NOTE,
        ["awaremw delete channel 1", "awaremw delete group 1"],
    )
    x.add_argument("what", choices=("group", "channel"))
    x.add_argument("id", metavar="ID")
    _common(x)
    _wait_opt(x)
    x.set_defaults(func=cmd_delete)

    m = add_verb(
        sub,
        "command",
        "send a command to motes",
        "Send a command on <prefix>/cmd/NAME; the motes it targets run it.\n\n"
        "Commands motes accept (any other name is refused):\n"
        + _commands_text()
        + "\n\n"
        + _BROKER_NOTE,
        [
            "awaremw command led --target all --arg state=on",
            "awaremw command set_rate --target group:1/* --arg period_s=5",
            "awaremw command beep --target node:7 --arg duration_ms=200 --wait 5",
        ],
    )
    m.add_argument("name", metavar="NAME", help=f"one of: {', '.join(sorted(COMMANDS))}")
    m.add_argument(
        "--target", default="all", help="all | node:ID | group:TYPE/ID (ID may be *) (default all)"
    )
    m.add_argument(
        "--arg",
        action="append",
        default=[],
        metavar="K=V",
        help="argument (number, true/false or text); repeatable",
    )
    _common(m)
    _wait_opt(m)
    m.set_defaults(func=cmd_command)

    w = add_verb(
        sub,
        "watch",
        "print what arrives on a topic (default <prefix>/#)",
        "Subscribe and print one line per message: topic and payload (or JSON).\n\n" + _BROKER_NOTE,
        [
            "awaremw watch 'aware/data/#' --count 3",
            "awaremw watch aware/errors --json --timeout 60",
        ],
    )
    w.add_argument("topic", nargs="?", default=None, metavar="TOPIC")
    w.add_argument("--count", type=int, default=0, help="exit after N messages")
    add_wall_timeout(w, "exit")
    w.add_argument("--json", action="store_true", help="one JSON object per line")
    _common(w)
    w.set_defaults(func=cmd_watch)


# --------------------------------------------------------------------------- payload builders


def parse_conditions(args: list[str]) -> list[dict[str, Any]]:
    """``["temperature > 45", "x<3"]`` or ``["temperature", ">", "45"]`` -> condition objects."""
    parts = [a for a in args if a.strip()]
    if not parts or not all(_COND_RE.match(p) for p in parts):
        parts = [p for p in _SPLIT_RE.split(" ".join(args)) if p]
    out = []
    for p in parts:
        m = _COND_RE.match(p)
        if m is None:
            raise UsageError(f'cannot read condition {p!r}; write it like "temperature > 45"')
        attr, op, value = m.groups()
        try:
            v = float(value)
        except ValueError:
            raise UsageError(f"condition {p!r}: {value!r} is not a number") from None
        out.append({"attr": attr, "op": op, "value": int(v) if v.is_integer() else v})
    return out


def _id_or_any(text: str, what: str) -> int | str:
    if text == "*":
        return "*"
    try:
        return int(text)
    except ValueError:
        raise UsageError(f'{what} must be an integer or "*", got {text!r}') from None


def parse_target(text: str) -> Any:
    if text == "all":
        return "all"
    kind, _, rest = text.partition(":")
    if kind == "node" and rest.isdigit():
        return {"node": int(rest)}
    if kind == "group":
        gt, _, gid = rest.partition("/")
        if gt.isdigit() and gid:
            return {"group_type": int(gt), "group_id": _id_or_any(gid, "group id")}
    raise UsageError(f"bad target {text!r}: use all, node:ID or group:TYPE/ID")


def parse_arg(text: str) -> tuple[str, Any]:
    k, sep, v = text.partition("=")
    if not sep or not k:
        raise UsageError(f"bad argument {text!r}: use KEY=VALUE")
    if v.lower() in ("true", "false"):
        return k, v.lower() == "true"
    for conv in (int, float):
        try:
            return k, conv(v)
        except ValueError:
            pass
    return k, v


# --------------------------------------------------------------------------- MQTT


def _settings(args: argparse.Namespace) -> MqttSettings:
    """The broker of ``--mqtt``; on this machine without an account, the embedded
    broker's own (found in its state directory)."""
    if args.mqtt is None:
        local = find_local_broker()
        url = DEFAULT_URL if local is None else local.url
        return MqttSettings.from_url(url, prefix=args.prefix, ca_file=args.ca_file)
    s = MqttSettings.from_url(args.mqtt, prefix=args.prefix, ca_file=args.ca_file)
    if s.username is None and not s.tls and s.host in LOOPBACK:
        local = find_local_broker(s.port)
        if local is not None:
            s = replace(s, username=local.username, password=local.password)
    return s


def _client(
    s: MqttSettings,
    client_id: str | None,
    protocol: aiomqtt.ProtocolVersion = aiomqtt.ProtocolVersion.V311,
) -> AckedClient:
    # A random id, never the empty one: amqtt gives every client that sends an
    # empty id the same session, subscriptions included.
    client_id = client_id or f"awaremw-cli-{secrets.token_hex(4)}"
    return s.client(client_id, timeout=10, protocol=protocol)


async def _publishing_protocol(s: MqttSettings) -> aiomqtt.ProtocolVersion:
    """MQTT 5 where the broker speaks it (its PUBACK says why a publish was refused),
    else 3.1.1; an unreachable broker is left to the connection to report."""
    if s.protocol != "auto":
        return aiomqtt.ProtocolVersion.V5 if s.protocol == "5" else aiomqtt.ProtocolVersion.V311
    try:
        five = await speaks_mqtt5(s)
    except (OSError, TimeoutError):
        five = False
    return aiomqtt.ProtocolVersion.V5 if five else aiomqtt.ProtocolVersion.V311


@dataclass(frozen=True, slots=True)
class Answer:
    """What publishing a payload came to.

    ``error``: a refusal (the gateway's document from ``<prefix>/errors``, or the
    client's own ``not_retained`` / ``not_taken``); ``warning``: the gateway's note
    on a payload it took; ``version``: the version the gateway gave a definition,
    seen on the retained topic (None when not waited for, or not a definition).
    """

    error: dict[str, Any] | None = None
    warning: dict[str, Any] | None = None
    version: int | None = None


async def publish(
    s: MqttSettings,
    rel_topic: str,
    payload: bytes,
    *,
    retain: bool,
    wait: float = 0.0,
    client_id: str | None = None,
    defined: list[bool] | None = None,
    check: str | None = None,
) -> Answer:
    """Publish (QoS 1); a retained payload is read back (an MQTT 3.1.1 broker
    acknowledges a publish its ACL refuses and drops it: reading it back is how a
    client can tell). With ``wait``, listen that long on ``<prefix>/errors`` for
    the gateway's refusal, and for a definition, until the gateway has taken it
    (its version on the retained topic): neither within ``wait`` is ``not_taken``.

    With ``defined`` (a list), first look for a retained message on ``check``
    (relative; default the topic itself) and append whether there was one (a
    delete of something never defined, a channel on an undefined group type).
    """
    topic = s.topic(rel_topic)
    async with _client(s, client_id, await _publishing_protocol(s)) as client:
        if defined is not None:
            defined.append(await _has_retained(client, s.topic(check or rel_topic)))
        listen = _Listener(s, rel_topic, payload)
        if retain or wait > 0:
            await client.subscribe(s.topic("errors"), qos=1)
        await client.publish(topic, payload, qos=1, retain=retain)
        if client.refusals:  # MQTT 5: the broker said why
            return Answer(error={
                "error": f"the broker refused {topic} from {_who(s)}: {client.refusals[-1]}",
                "code": "refused_by_broker",
            })  # fmt: skip
        if retain:
            await client.subscribe(topic, qos=1)  # the retained message comes back
        expect = check is not None and defined == [False]  # the gateway warns then
        return await listen.run(client, retain=retain, wait=wait, expect_warning=expect)


class _Listener:
    """Reads what comes back after a publish: the retained message the broker kept,
    the gateway's republication with a version, refusals and warnings for the topic."""

    def __init__(self, s: MqttSettings, rel_topic: str, payload: bytes) -> None:
        self.s, self.rel, self.payload = s, rel_topic, payload
        self.topic = s.topic(rel_topic)
        self.kept: bool | None = None  # None: not read back yet
        self.version: int | None = None
        self.warning: dict[str, Any] | None = None
        self.error: dict[str, Any] | None = None

    async def run(
        self, client: aiomqtt.Client, *, retain: bool, wait: float, expect_warning: bool = False
    ) -> Answer:
        loop = asyncio.get_running_loop()
        start = loop.time()
        read_by = start + RETAINED_WAIT_S  # brokers send the retained message after the SUBACK
        if not retain:
            self.kept = True
        definition = retain and bool(self.payload) and self.rel.startswith("def/")
        while self.error is None:
            now = loop.time()
            if self.kept is None and now >= read_by:
                self.kept = not self.payload  # nothing retained: right for a deletion only
            if self.kept is None:
                until = read_by
            elif not self.kept:
                until = read_by + RETAINED_WAIT_S  # the gateway's refusal explains it, if any
            elif definition and wait > 0:
                missing = self.version is None or (expect_warning and self.warning is None)
                until = start + wait if missing else now
            else:
                until = start + wait  # a refusal, if one comes
            if now >= until:
                break
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout_at(until):
                    async for m in client.messages:
                        if self._take(m):
                            break
        return self._answer(definition, wait)

    def _take(self, m: aiomqtt.Message) -> bool:
        """One message; True when it changed what is known."""
        body = m.payload if isinstance(m.payload, bytes) else b""
        if m.topic.matches(self.s.topic("errors")):
            with contextlib.suppress(ValueError, TypeError):
                doc = json.loads(body)
                if isinstance(doc, dict) and doc.get("topic") == self.topic:
                    if doc.get("level") == "warning":
                        self.warning = doc
                    else:
                        self.error = doc
                    return True
            return False
        if not m.topic.matches(self.topic):
            return False
        version = _copy_version(self.rel, body, self.payload)
        if self.kept is None and m.retain:
            self.kept = body == self.payload or version is not None
        if version is not None:
            self.version = version
            return True
        return self.kept is not None and m.retain

    def _answer(self, definition: bool, wait: float) -> Answer:
        if self.error is not None:
            return Answer(error=self.error)
        if not self.kept:
            who = _who(self.s)
            return Answer(error={
                "error": f"the broker did not keep {self.topic} from {who}: refused (its ACL "
                "does not let the account publish there), or the account may not read it back",
                "code": "not_retained",
            })  # fmt: skip
        if definition and wait > 0 and self.version is None:
            return Answer(error={
                "error": f"no gateway took {self.topic} within {wait:g} s (no version on the "
                f"retained topic, no error on {self.s.topic('errors')}): is `awaremw gateway` "
                f"running on this broker with prefix {self.s.prefix!r}?",
                "code": "not_taken",
            })  # fmt: skip
        return Answer(warning=self.warning, version=self.version)


def _who(s: MqttSettings) -> str:
    return f"the account {s.username!r}" if s.username else "an anonymous client"


# Bodies are compared whatever the gateway's deployment allows (its MTU, periods).
_ANY_LIMITS = replace(LIMITS, mtu=1 << 16, min_period_s=0.0)


def _copy_version(rel_topic: str, held: bytes, sent: bytes) -> int | None:
    """The version of ``held`` when it is the gateway's copy of the definition ``sent``
    (the same body in canonical form, with the version the gateway gave it)."""
    if not held or not sent:
        return None
    try:
        copy = schema.parse_definition(rel_topic, held, _ANY_LIMITS)
        ours = schema.parse_definition(rel_topic, sent, _ANY_LIMITS)
    except schema.SchemaError:
        return None
    return copy.version if copy.body == ours.body else None


async def _retained(client: aiomqtt.Client, topic: str) -> bytes:
    """The retained message the broker holds on ``topic`` (sent right after the
    SUBACK); empty if none comes within ``RETAINED_WAIT_S``."""
    await client.subscribe(topic, qos=1)
    try:
        async with asyncio.timeout(RETAINED_WAIT_S):
            async for m in client.messages:
                if m.topic.matches(topic) and m.retain:
                    return m.payload if isinstance(m.payload, bytes) else b""
    except TimeoutError:
        return b""
    finally:
        await client.unsubscribe(topic)
    return b""


async def _has_retained(client: aiomqtt.Client, topic: str) -> bool:
    """Whether the broker holds a retained message on ``topic``."""
    return bool(await _retained(client, topic))


def _send(
    args: argparse.Namespace, rel: str, payload: bytes, retain: bool, needs: str | None = None
) -> int:
    """Publish; a delete checks that there was something to delete, a definition
    that ``needs`` another (a channel's group type) that it exists."""
    s = _settings(args)
    defined: list[bool] | None = [] if not payload or needs else None
    answer = asyncio.run(
        publish(s, rel, payload, retain=retain, wait=args.wait, client_id=args.client_id,
                defined=defined, check=needs)
    )  # fmt: skip
    err, warning = answer.error, answer.warning
    if needs is not None and defined == [False] and err is None and warning is None:
        print(
            f"warning: {s.topic(needs)} is not defined: the channel waits for its group type "
            "and produces no data until then (waits_for_group_type)",
            file=sys.stderr,
        )
    if err is not None and err.get("code") in ("not_retained", "not_taken", "refused_by_broker"):
        print(f"awaremw: {err.get('error')}", file=sys.stderr)
        return 1
    if err is not None:
        print(f"refused by the gateway: {err.get('error')} ({err.get('code')})", file=sys.stderr)
        return 1
    if warning is not None:
        print(f"warning from the gateway: {warning.get('error')} ({warning.get('code')})",
              file=sys.stderr)  # fmt: skip
    if not payload and defined == [False]:
        print(f"{s.topic(rel)} was not defined (no retained definition on the broker)")
        return 0
    # The version only when waited for: without --wait the gateway may not have taken it yet.
    taken = "" if answer.version is None or args.wait <= 0 else f" (version {answer.version})"
    print(f"{s.topic(rel)} {payload.decode() if payload else '(deleted)'}{taken}")
    return 0


def _run(fn: Any, args: argparse.Namespace) -> int:
    try:
        return int(fn(args))
    except (UsageError, schema.SchemaError, BadMqttUrl) as e:
        return refuse("awaremw", e)
    except aiomqtt.MqttError as e:
        url = args.mqtt or DEFAULT_URL
        why = redact(str(e))
        hint = ""
        if "authorized" in why.lower() and (args.mqtt is None or "@" not in args.mqtt):
            hint = (
                f"; no embedded broker account found under {state_base()} (is a gateway "
                "running here?): give --mqtt mqtt://USER:PASS@HOST:PORT"
            )
        elif "refused" in why.lower() and args.mqtt is None:
            hint = (
                "; no broker answers there: start `awaremw gateway DEPLOYMENT` (it runs the "
                "embedded broker), or give --mqtt mqtt://USER:PASS@HOST:PORT"
            )
        print(f"awaremw: MQTT {mask_url(url)}: {why}{hint}", file=sys.stderr)
        return 1


# --------------------------------------------------------------------------- verbs


def cmd_define_group(args: argparse.Namespace) -> int:
    def go(args: argparse.Namespace) -> int:
        doc = {"conditions": parse_conditions(args.conditions), "hysteresis": args.hysteresis}
        payload = json.dumps(doc).encode()
        schema.parse_group_type(args.type, payload, LIMITS)  # refuse early
        return _send(args, f"def/group/{args.type}", payload, retain=True)

    return _run(go, args)


def cmd_define_channel(args: argparse.Namespace) -> int:
    def go(args: argparse.Namespace) -> int:
        doc = {
            "attr": args.attr,
            "group_type": _id_or_any(args.group_type, "--group-type"),
            "group_id": _id_or_any(args.group_id, "--group-id"),
            "period_s": args.period,
            "agg": args.agg,
        }
        payload = json.dumps(doc).encode()
        schema.parse_channel(args.id, payload, LIMITS)
        gt = doc["group_type"]
        needs = None if gt == "*" else f"def/group/{gt}"
        return _send(args, f"def/channel/{args.id}", payload, retain=True, needs=needs)

    return _run(go, args)


def cmd_delete(args: argparse.Namespace) -> int:
    def go(args: argparse.Namespace) -> int:
        lim = LIMITS
        if args.what == "group":
            schema.group_type_id(args.id, lim)
        else:
            schema.channel_id(args.id, lim)
        return _send(args, f"def/{args.what}/{args.id}", b"", retain=True)

    return _run(go, args)


def cmd_command(args: argparse.Namespace) -> int:
    def go(args: argparse.Namespace) -> int:
        doc = {"target": parse_target(args.target), "args": dict(parse_arg(a) for a in args.arg)}
        payload = json.dumps(doc).encode()
        schema.parse_command(args.name, payload, LIMITS)
        return _send(args, f"cmd/{args.name}", payload, retain=False)

    return _run(go, args)


def cmd_watch(args: argparse.Namespace) -> int:
    def go(args: argparse.Namespace) -> int:
        s = _settings(args)
        topic = args.topic or s.topic("#")
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(watch(s, topic, args.count, args.timeout or 0.0, args.json, args.client_id))
        return 0

    return _run(go, args)


async def watch(
    s: MqttSettings,
    topic: str,
    count: int = 0,
    duration: float = 0.0,
    as_json: bool = False,
    client_id: str | None = None,
) -> None:
    """Print ``topic payload`` lines (or JSON lines) until ``count``/``duration``."""
    n = 0
    deadline = time.monotonic() + duration if duration > 0 else None
    async with _client(s, client_id) as client:
        await client.subscribe(topic, qos=1)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout_at(
                None if deadline is None else asyncio.get_running_loop().time() + duration
            ):
                async for m in client.messages:
                    if not m.topic.matches(topic):
                        continue  # amqtt 0.12 also sends retained messages of others' filters
                    raw = m.payload if isinstance(m.payload, bytes) else b""
                    text = raw.decode("utf-8", errors="replace")
                    if as_json:
                        try:
                            value: Any = json.loads(text) if text else None
                        except ValueError:
                            value = text
                        line = json.dumps(
                            {"topic": m.topic.value, "payload": value, "retain": bool(m.retain)},
                            ensure_ascii=False,  # °C as °C: stdout is text, not a wire
                        )
                    else:
                        line = f"{m.topic.value} {text}"
                    print(line, flush=True)
                    n += 1
                    if count and n >= count:
                        return
