"""Both media take the same decisions from a links file (docs/radio.md, "Links files").

The scripted frames of tests/test_mac_zenoh.py (broadcasts and unicasts, CSMA
and ALOHA, collisions) among eight motes whose links come from a file in
TOSSIM's format (gains, and each receiver's noise line), on the virtual medium
and on the Zenoh medium on loopback: the same receptions, counters and unicast
outcomes, as tests/test_mac_zenoh.py shows for links derived from positions.
Across processes, a process subscribes to the keys of the senders its motes
have a link from, and nothing else: a frame goes only towards the motes that
can hear it.
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_mac_zenoh import FIELDS, Media, run_virtual, run_zenoh, scripted, wait_for

from awaremw.protocol.frames import BROADCAST
from awaremw.radio.environment import RadioSettings, radio_model
from awaremw.radio.model import CC2420
from awaremw.radio.zenoh_medium import MacSettings
from awaremw.runtime.router import EmbeddedRouter
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)

pytestmark = pytest.mark.zenoh


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    ep = free_tcp_endpoint()
    with EmbeddedRouter([ep]):
        yield ep


def topology(path: Path, ids: list[int], seed: int) -> Path:
    """Gains between -60 and -97 dBm for most pairs (asymmetric), none for some,
    and a noise line (mean, range) per mote, in TOSSIM's format."""
    rnd = random.Random(seed)
    lines = []
    for a in ids:
        for b in ids:
            if a != b and rnd.random() < 0.8:
                lines.append(f"gain\t{a}\t{b}\t{rnd.uniform(-97.0, -60.0):.2f}")
    for a in ids:
        lines.append(f"noise\t{a}\t{rnd.uniform(-100.0, -92.0):.2f}\t{rnd.uniform(0.0, 4.0):.2f}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("mac", ["csma", "aloha"])
async def test_both_media_decide_the_same_from_a_links_file(
    router: str, tmp_path: Path, mac: str
) -> None:
    ids = list(range(8))
    path = topology(tmp_path / "linkgain.out", ids, 4)
    model = radio_model(CC2420, 11, RadioSettings(links=str(path)))
    # Positions far apart: with a links file they say nothing of who hears whom.
    pos = {i: (100.0 * i, 0.0) for i in ids}
    script = scripted(pos, 40, 3)
    v_got, v_counts, v_results = run_virtual(model, pos, script, mac)
    z_got, z_counts, z_results = await run_zenoh(router, model, pos, script, mac, f"links{mac}")
    total = {f: sum(c[FIELDS.index(f)] for c in v_counts.values()) for f in FIELDS}
    assert total["frames_rx"] >= 20 and total["dropped_loss"] >= 5  # links that lose
    assert total["collisions"] >= 3
    assert z_got == v_got
    assert z_counts == v_counts
    assert z_results == v_results


async def test_a_frame_goes_only_to_the_processes_whose_motes_can_hear_its_sender(
    router: str, tmp_path: Path
) -> None:
    # 1 -> 2 is a strong link; 3 has no link from 1 (but 1 hears 3).
    path = tmp_path / "topo.txt"
    path.write_text("gain 1 2 -60\ngain 3 1 -60\ngain 2 3 -70\n", encoding="utf-8")
    model = radio_model(CC2420, 2, RadioSettings(links=str(path)))
    sessions = [open_session(SessionSettings("peer", (router,))) for _ in range(3)]
    z = Media(model, sessions, "links-route", access=MacSettings("aloha", "sinr", 0.04))
    try:
        for m, i in enumerate((1, 2, 3)):
            z.attach(m, {i: (0.0, 0.0)})  # one place for all: positions say nothing
        assert [z.media[m].link_senders for m in range(3)] == [{3}, {1}, {2}]
        pub = z.radios[1].pub
        await wait_for(lambda: bool(getattr(pub.matching_status, "matching", False)))
        script = [(0.01 + 0.01 * k, 1, BROADCAST, k) for k in range(5)]
        t_end = z.play(script)
        await z.settle(t_end)
        await wait_for(lambda: z.media[1].stats.envelopes_rx == 5)
        assert {(1, 2, k) for k in range(5)} <= z.got
        assert z.media[2].stats.envelopes_rx == 0  # mote 3 cannot hear 1: nothing sent there
    finally:
        z.close()
        for s in sessions:
            close_quietly(s)
