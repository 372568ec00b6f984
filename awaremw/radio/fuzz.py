"""Mutations of captured radio envelopes, for the fuzz test and benchmark.

:func:`mutants` takes real envelopes (bytes heard on radio keys) and yields
mutated copies: every field set to extreme values (overflowing integers, huge,
NaN and infinite floats, wrong types), truncations, deep nesting, random
bytes, and frames mutated inside valid envelopes, including Drip items at
extreme versions for the definitions in use. Deterministic for a seed.
"""

from __future__ import annotations

import math
import random
from collections.abc import Iterator, Sequence
from typing import Any

import msgpack

from awaremw.protocol.frames import BROADCAST, ChannelDef, DripItem, ItemKind, encode

EXTREME: tuple[Any, ...] = (
    -1, 0x8000, 0xFFFF, 0x10000, 0xFFFFFFFF, 2**32, 2**63 - 1, -(2**63), 2**64 - 1,
    1e5, -1e5, 1e308, -1e308, math.inf, -math.inf, math.nan, 5e-324,
    True, None, "", "x" * 300, b"\x00" * 300, [], {}, [[[[]]]], {"a": 1},
)  # fmt: skip
VERSIONS = (0, 1, 2, 0x7FFFFFFF, 0x80000000, 0x80000001, 0xFFFFFFFE, 0xFFFFFFFF)


def _pack(obj: object) -> bytes:
    try:
        return bytes(msgpack.packb(obj, use_bin_type=True))
    except (OverflowError, ValueError, TypeError):
        return b"\xc1"


def _nested(depth: int) -> bytes:
    return b"\x91" * depth + b"\x00"


def mutants(
    captured: Sequence[tuple[str, bytes]],
    seed: int,
    items: Sequence[tuple[ItemKind, int]] = ((ItemKind.CHANNEL, 1),),
) -> Iterator[tuple[str, bytes, str]]:
    """Endless ``(key, payload, mutation)`` from captured ``(key, envelope)`` pairs."""
    if not captured:
        raise ValueError("nothing captured to mutate")
    rng = random.Random(seed)
    while True:
        key, data = rng.choice(captured)
        try:
            env = list(msgpack.unpackb(data, raw=False))
        except Exception:
            continue
        m = rng.randrange(8)
        if m == 0:  # one field set to an extreme value
            i = rng.randrange(len(env))
            env[i] = rng.choice(EXTREME)
            yield key, _pack(env), f"field{i}"
        elif m == 1:  # several fields at once
            for i in rng.sample(range(len(env)), 3):
                env[i] = rng.choice(EXTREME)
            yield key, _pack(env), "fields"
        elif m == 2:  # truncation
            yield key, data[: rng.randrange(len(data))], "truncated"
        elif m == 3:  # deep nesting, as the whole envelope or as its frame
            depth = rng.choice((50, 500, 5000, 100_000))
            if rng.random() < 0.5:
                yield key, _nested(depth), "nested"
            else:
                env[-1] = _nested(min(depth, 120))
                yield key, _pack(env), "nested frame"
        elif m == 4:  # random bytes, or flipped bytes
            if rng.random() < 0.5:
                yield key, rng.randbytes(rng.randrange(1, 300)), "random"
            else:
                b = bytearray(data)
                for _ in range(rng.randrange(1, 6)):
                    b[rng.randrange(len(b))] = rng.randrange(256)
                yield key, bytes(b), "flipped"
        elif m == 5:  # a frame field mutated inside a valid envelope
            try:
                frame = list(msgpack.unpackb(env[-1], raw=False))
            except Exception:
                continue
            if frame:
                frame[rng.randrange(len(frame))] = rng.choice(EXTREME)
            env[-1] = _pack(frame)
            yield key, _pack(env), "frame field"
        elif m == 6 and len(env) == 11 and isinstance(env[2], int):  # Drip item, extreme version
            kind, item_id = rng.choice(items)
            v = rng.choice(VERSIONS)
            period = rng.choice((500, 60_000, 0xFFFFFFFF))
            body = ChannelDef(1, 1, 0xFFFF, period, 0) if kind is ItemKind.CHANNEL else None
            try:
                env[-1] = encode(DripItem(env[2] & 0x7FFF, BROADCAST, kind, item_id, v, body))
            except ValueError:
                continue
            env[1], env[9] = 0, BROADCAST
            yield key, _pack(env), "drip version"
        else:  # a wrong-typed whole payload
            yield key, _pack(rng.choice(EXTREME)), "not an envelope"
