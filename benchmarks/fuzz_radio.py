"""A longer fuzz run of the radio: ``awaremw fleet`` + ``awaremw gateway`` (its
embedded MQTT broker) as processes, mutated envelopes put on the radio keys.

    python benchmarks/fuzz_radio.py [--envelopes 50000] [--seed 1] [--deployment grid_small]

Captures real envelopes with a Zenoh client session, puts mutated copies back
(:mod:`awaremw.radio.fuzz`) in rounds, and after every round checks that both
processes are alive. Prints one JSON object:

* ``envelopes_tried``: mutated envelopes put on the radio keys;
* ``mutations``: how many of each kind of mutation;
* ``rejected``: per process (``fleet-ctl stats`` name), envelopes refused per
  reason (see ``awaremw/radio/envelope.py``, ``REASONS``);
* ``faults``: per process, exceptions contained by the last guards (bugs);
* ``crashes``: processes that died (name and exit code); ``crashes_found`` is
  their number plus the number of contained faults (0 is the expected figure);
* ``wall_s``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from typing import Any

import zenoh

from awaremw.cli.fleet import control_query
from awaremw.radio.fuzz import mutants
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envelopes", type=int, default=50_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--deployment", default="grid_small")
    ap.add_argument("--speed", type=float, default=4.0)
    ap.add_argument("--round", type=int, default=1000, help="envelopes between liveness checks")
    a = ap.parse_args(argv)

    ep = free_tcp_endpoint()
    t0 = time.perf_counter()
    speed = ["--speed", str(a.speed)]
    procs = {
        "fleet": subprocess.Popen(
            [sys.executable, "-m", "awaremw", "fleet", a.deployment, "--listen", ep,
             "--without-kind", "gateway", "--plain", *speed],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        ),
    }  # fmt: skip
    time.sleep(2.0)  # the fleet must listen before the gateway connects (no readiness signal)
    procs["gateway"] = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "gateway", a.deployment, "--connect", ep,
         "--define-initial", *speed],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    session = open_session(SessionSettings("client", (ep,)))
    captured: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def capture(sample: zenoh.Sample) -> None:
        with lock:
            if len(captured) < 500:
                captured.append((str(sample.key_expr), sample.payload.to_bytes()))

    out: dict[str, Any] = {}
    try:
        sub = session.declare_subscriber("aware/radio/**", capture)
        deadline = time.monotonic() + 60
        while len(captured) < 500 and time.monotonic() < deadline:
            time.sleep(0.1)
        sub.undeclare()  # type: ignore[no-untyped-call]
        gen = mutants(list(captured), a.seed)
        kinds: dict[str, int] = {}
        tried = 0
        crashes: list[dict[str, Any]] = []
        while tried < a.envelopes and not crashes:
            for _ in range(min(a.round, a.envelopes - tried)):
                key, payload, what = next(gen)
                kinds[what] = kinds.get(what, 0) + 1
                session.put(key, payload)
                tried += 1
            time.sleep(0.1)  # pacing, so the loops keep up (not a synchronisation)
            crashes = [
                {"process": n, "exit": p.returncode}
                for n, p in procs.items()
                if p.poll() is not None
            ]
        replies = control_query([ep], "aware", {"op": "stats"}, 5.0)
        snaps = {str(d.get("fleet")): d.get("snapshot", {}) for d in replies}
        faults = {n: s.get("faults", {}) for n, s in snaps.items()}
        out = {
            "envelopes_tried": tried,
            "mutations": dict(sorted(kinds.items())),
            "rejected": {n: s.get("rejected", {}) for n, s in snaps.items()},
            "faults": faults,
            "crashes": crashes,
            "crashes_found": len(crashes) + sum(sum(f.values()) for f in faults.values()),
            "answered": sorted(snaps),
            "wall_s": round(time.perf_counter() - t0, 1),
        }
    finally:
        close_quietly(session)
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
                p.wait(10)
    print(json.dumps(out))
    return 0 if out.get("crashes_found") == 0 and len(out.get("answered", [])) == 2 else 1


if __name__ == "__main__":
    sys.exit(main())
