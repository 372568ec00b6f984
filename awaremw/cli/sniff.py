"""``awaremw sniff --connect ENDPOINT --pcap FILE``: capture the emulated radio live.

Subscribes to the radio's key expressions (``<prefix>/radio/**``) like a mote
would and writes every frame on the air to FILE as pcapng with link type IEEE
802.15.4 (no FCS), until Ctrl-C / SIGTERM (or ``--timeout`` wall seconds);
the file is flushed every second and on exit. With ``--secrets DIR`` it joins
through the router with the fleet role, checks every frame's MIC with the
network key and writes the payload without counter and MIC. ``--dissector``
prints the path of the shipped Wireshark Lua dissector::

    awaremw sniff --connect tcp/127.0.0.1:7447 --pcap radio.pcapng
    tshark -X lua_script:$(awaremw sniff --dissector) -r radio.pcapng

See docs/capture.md.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
from pathlib import Path
from typing import Any

from awaremw.cli.friendly import add_secrets_option, load_secrets, refuse, stop_event
from awaremw.cli.helptext import add_log_format, add_verb, add_wall_timeout

DISSECTOR = Path(__file__).resolve().parent.parent / "wireshark" / "awaremw.lua"


def dissector_path() -> Path:
    """The Wireshark Lua dissector shipped in the package."""
    return DISSECTOR


def register(sub: Any) -> None:
    p = add_verb(
        sub,
        "sniff",
        "capture the emulated radio live to a pcapng file",
        """\
Subscribe to the radio's key expressions (<prefix>/radio/**) like a mote and
write every frame on the air to FILE as pcapng (IEEE 802.15.4, no FCS), until
Ctrl-C / SIGTERM or --timeout S. With --secrets DIR it checks every frame's MIC
with the network key. --dissector prints the path of the shipped Wireshark Lua
dissector. See docs/capture.md.""",
        [
            "awaremw sniff --connect tcp/127.0.0.1:7447 --pcap radio.pcapng",
            "tshark -X lua_script:$(awaremw sniff --dissector) -r radio.pcapng",
        ],
    )
    p.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="Zenoh endpoint"
    )
    p.add_argument("--pcap", default=None, metavar="FILE", help="capture file (pcapng)")
    p.add_argument("--prefix", default="aware", help="Zenoh key prefix of the radio")
    add_secrets_option(p, "verify and strip the MIC (keys init DIR)")
    add_wall_timeout(p, "stop")
    p.add_argument(
        "--dissector", action="store_true", help="print the Wireshark dissector's path and exit"
    )
    add_log_format(p)
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    if args.dissector:
        print(dissector_path())
        return 0
    if args.pcap is None or not args.connect:
        return refuse("awaremw sniff", "--connect ENDPOINT and --pcap FILE are needed")
    if args.timeout is not None and args.timeout <= 0:
        return refuse("awaremw sniff", "--timeout must be > 0")
    from awaremw.runtime.zenoh_session import SessionSettings

    security = None
    settings = SessionSettings("peer", tuple(args.connect))
    if args.secrets is not None:
        from awaremw.security.material import load_radio_security
        from awaremw.security.zenoh_acl import role_settings

        loaded = load_secrets(
            "awaremw sniff",
            args.secrets,
            lambda d: (role_settings(d, "fleet", args.connect), load_radio_security(d)),
        )
        if loaded is None:
            return 2
        settings, security = loaded
    try:
        return asyncio.run(_sniff(args, settings, security))
    except KeyboardInterrupt:
        return 130


async def _sniff(args: argparse.Namespace, settings: Any, security: Any) -> int:
    from awaremw.radio.capture import Capture
    from awaremw.radio.sniffer import Sniffer
    from awaremw.runtime.zenoh_session import close_quietly, open_session

    stop = stop_event()
    try:
        capture = Capture.to_file(args.pcap, receptions=False)
    except OSError as e:
        return refuse("awaremw sniff", f"cannot write {args.pcap}: {e}")
    session = await asyncio.to_thread(open_session, settings)
    sniffer = Sniffer(session, capture, prefix=args.prefix, security=security)
    try:
        sniffer.start()
        print(
            f"awaremw sniff: {sniffer.key} via {', '.join(args.connect)} -> {args.pcap}",
            file=sys.stderr,
            flush=True,
        )
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), args.timeout)
    finally:
        sniffer.close()
        await asyncio.to_thread(close_quietly, session)
    st = sniffer.stats
    mic = "" if security is None else f", MIC ok {st.mic_ok} bad {st.mic_bad}"
    print(
        f"awaremw sniff: {capture.packets} packets to {args.pcap} "
        f"({st.frames} frames, {st.acks} ACKs, {st.malformed} malformed{mic})",
        file=sys.stderr,
        flush=True,
    )
    return 0
