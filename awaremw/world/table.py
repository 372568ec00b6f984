"""A deployment's ``[world]`` table (docs/world.md): its shape and the :class:`World` it makes.

The table's shape is declared here as msgspec Structs (:class:`WorldTable`); the
deployment reader (:mod:`awaremw.runtime.deployment`) converts a file's
``[world]`` into one, with the rest of the file, and :func:`build_world` turns
the typed table into a :class:`World` (seeded), raising :class:`WorldError`
for keyframes that cannot be completed. :func:`world_from_table` does both for
a raw table. Apart from :mod:`fields`, which the compiled build compiles: mypyc
does not build msgspec Structs.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

from msgspec import Meta, Struct

from awaremw.protocol.validation import Finite, Invalid, convert
from awaremw.world.fields import Keyframe, Source, World, WorldError


def world_from_table(table: Mapping[str, Any] | None, seed: int = 0) -> World:
    """Build a world from a raw ``[world]`` table (None: all ambient); keys the
    table does not name are kept in ``World.extra``."""
    t = dict(table or {})
    try:
        doc = convert(t, WorldTable)
    except Invalid as e:
        raise WorldError(f"world.{e}") from None
    extra = {k: v for k, v in t.items() if k not in WorldTable.__struct_fields__}
    return build_world(doc, seed, extra)


def build_world(doc: WorldTable, seed: int = 0, extra: Mapping[str, Any] | None = None) -> World:
    """The world of a typed ``[world]`` table, seeded by ``seed`` unless the table
    names its own. Raises :class:`WorldError` (a keyframe that cannot be completed,
    a source's times out of order)."""
    kw = {k: v for k in _SCALARS if (v := getattr(doc, k)) is not None}
    kw["seed"] = seed if doc.seed is None else int(doc.seed)
    return World(
        fires=_sources(doc.fires, "fires"),
        gas_sources=_sources(doc.gas, "gas"),
        lights=_sources(doc.lights, "lights"),
        extra=dict(extra or {}),
        **kw,
    )


# The [world] table's shape (docs/world.md); keys it does not name are kept for others.
_Positive = Annotated[float, Meta(gt=0)]


class _Keyframe(Struct, forbid_unknown_fields=True, frozen=True):
    t: Finite
    x: Finite | None = None  # omitted: the previous keyframe's
    y: Finite | None = None
    radius: Finite | None = None
    peak: Finite | None = None


class _Source(Struct, forbid_unknown_fields=True, frozen=True):
    keyframes: Annotated[tuple[_Keyframe, ...], Meta(min_length=1)]
    name: str | None = None
    edge: Finite = 1.0
    hold: bool = True
    gas: Finite = 0.0
    light: Finite = 0.0


class WorldTable(Struct, frozen=True):
    """A ``[world]`` table, typed (None: World's default; keys it does not name are ignored)."""

    ambient_temperature: Finite | None = None
    ambient_humidity: Finite | None = None
    ambient_light: Finite | None = None
    ambient_gas: Finite | None = None
    variation: Finite | None = None
    variation_scale: _Positive | None = None
    noise_step: _Positive | None = None
    seed: Finite | None = None
    fires: tuple[_Source, ...] = ()
    gas: tuple[_Source, ...] = ()
    lights: tuple[_Source, ...] = ()


_SCALARS = [k for k in WorldTable.__struct_fields__ if k not in ("seed", "fires", "gas", "lights")]


def _sources(docs: tuple[_Source, ...], kind: str) -> tuple[Source, ...]:
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
