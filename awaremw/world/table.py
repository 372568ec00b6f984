"""A deployment's ``[world]`` table (docs/world.md) -> :class:`World`.

The table's shape is declared as msgspec Structs and refused through the shared
adapter (:mod:`awaremw.protocol.validation`). Apart from :mod:`fields`, which
the compiled build compiles: mypyc does not build msgspec Structs.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

from msgspec import Meta, Struct

from awaremw.protocol.validation import Finite, Invalid, convert
from awaremw.world.fields import Keyframe, Source, World, WorldError


def world_from_table(table: Mapping[str, Any] | None, seed: int = 0) -> World:
    """Build a world from a deployment's ``[world]`` table (None: all ambient)."""
    t = dict(table or {})
    try:
        doc = convert(t, _WorldTable)
    except Invalid as e:
        raise WorldError(f"world.{e}") from None
    kw = {k: v for k in _SCALARS if (v := getattr(doc, k)) is not None}
    kw["seed"] = seed if doc.seed is None else int(doc.seed)
    return World(
        fires=_sources(doc.fires, "fires"),
        gas_sources=_sources(doc.gas, "gas"),
        lights=_sources(doc.lights, "lights"),
        extra={k: v for k, v in t.items() if k not in _WorldTable.__struct_fields__},
        **kw,
    )


# The [world] table's shape (docs/world.md); keys it does not name are kept for others.
_Positive = Annotated[float, Meta(gt=0)]


class _Keyframe(Struct, forbid_unknown_fields=True):
    t: Finite
    x: Finite | None = None  # omitted: the previous keyframe's
    y: Finite | None = None
    radius: Finite | None = None
    peak: Finite | None = None


class _Source(Struct, forbid_unknown_fields=True):
    keyframes: Annotated[list[_Keyframe], Meta(min_length=1)]
    name: str | None = None
    edge: Finite = 1.0
    hold: bool = True
    gas: Finite = 0.0
    light: Finite = 0.0


class _WorldTable(Struct):  # None: World's default
    ambient_temperature: Finite | None = None
    ambient_humidity: Finite | None = None
    ambient_light: Finite | None = None
    ambient_gas: Finite | None = None
    variation: Finite | None = None
    variation_scale: _Positive | None = None
    noise_step: _Positive | None = None
    seed: Finite | None = None
    fires: list[_Source] = []
    gas: list[_Source] = []
    lights: list[_Source] = []


_SCALARS = [k for k in _WorldTable.__struct_fields__ if k not in ("seed", "fires", "gas", "lights")]


def _sources(docs: list[_Source], kind: str) -> tuple[Source, ...]:
    out: list[Source] = []
    for i, d in enumerate(docs):
        name = f"{kind}{i}" if d.name is None else d.name
        frames: list[Keyframe] = []
        prev: dict[str, float] = {"radius": 0.0}
        for j, k in enumerate(d.keyframes):
            # Omitted values carry over from the previous keyframe.
            cur = prev | {f: v for f in k.__struct_fields__ if (v := getattr(k, f)) is not None}
            missing = [n for n in ("x", "y", "peak") if n not in cur]
            if missing:
                raise WorldError(f"world.{kind}[{name}].keyframes[{j}] needs {', '.join(missing)}")
            frames.append(Keyframe(cur["t"], cur["x"], cur["y"], cur["radius"], cur["peak"]))
            prev = cur
        out.append(Source(name, tuple(frames), d.edge, d.hold, d.gas, d.light))
    return tuple(out)
