"""Deployment files: TOML -> one typed, validated, frozen :class:`Deployment`.

A deployment says which motes stand where (or move how), with which radio,
and which world, middleware settings, groups, channels and experiment settings
a scenario starts with. The format is documented in ``docs/deployments.md``.

This module is the one place that reads a deployment file: every table is
checked here, once, against its msgspec Struct (the ``[world]`` table's is
:class:`~awaremw.world.table.WorldTable`; the middleware overrides are checked
against :class:`~awaremw.protocol.config.MiddlewareConfig`'s annotations), and
the runtime, the world, the node kinds and the experiments only read the value
it returns. Loading never half-works: any problem raises
:class:`DeploymentError` whose message names the file, the entry
(``nodes[3] (id 17)``, ``grid[0]``, ``node 17``) and what is wrong.

What is left to others: the node kinds' names (``known_kinds``, passed in by
the layer that knows them), and the ``[[groups]]`` / ``[[channels]]``
payloads, which the gateway's schema checks as it checks MQTT payloads (its
limits follow the gateway mote's configuration). Unknown top-level *tables* are
kept in ``Deployment.extra``; unknown top-level *values* are errors (typos).
"""

from __future__ import annotations

import math
import random
import sys
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path as FsPath
from typing import Annotated, Any, TypeVar

import msgspec
from msgspec import Meta, Struct

from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.frames import MAX_NODE_ID
from awaremw.protocol.validation import Finite, Invalid, convert
from awaremw.radio.environment import WHITE, RadioSettings, radio_model
from awaremw.radio.links import SHIPPED as SHIPPED_LINKS
from awaremw.radio.links import LinkFile, LinksError, load_links
from awaremw.radio.mac import COLLISION_MODES, MAC_KINDS
from awaremw.radio.model import PRESETS, RadioModel, RadioPreset
from awaremw.radio.noise import SHIPPED as SHIPPED_TRACES
from awaremw.radio.noise import NoiseTraceError, load_trace
from awaremw.world.fields import World, WorldError
from awaremw.world.mobility import Mobility, Path, Static
from awaremw.world.table import WorldTable, build_world

Point = tuple[float, float]
T = TypeVar("T")

DEFAULT_RADIO = "cc2420"

# The shapes of a deployment file (docs/deployments.md lists each key; a test
# holds the two equal). A node or grid entry may add ENTRY_EXTRA_KEYS, checked
# here into NodeSpec.middleware and NodeSpec.noise, and nothing else; a top-level
# key not named here must be a table.
_Point = tuple[Finite, Finite]
_Name = Annotated[str, Meta(min_length=1)]
_NonNeg = Annotated[float, Meta(ge=0, le=sys.float_info.max)]
_Positive = Annotated[float, Meta(gt=0, le=sys.float_info.max)]
_Raw = dict[str, Any] | list[Any] | None


class _File(Struct):
    area: tuple[_Positive, _Positive]  # (width, height) in m
    name: _Name | None = None
    description: str = ""
    radio: _Name = DEFAULT_RADIO
    seed: int = 0
    tx_power_dbm: Finite | None = None  # None: the preset's
    mac: _Name = "csma"
    collisions: _Name = "sinr"
    noise: _Name = WHITE  # "white", a shipped trace's name, or a trace file (radio/noise.py)
    hardware_variance: bool = False
    links: _Name | None = None  # a links file, or a shipped name (radio/links.py)
    nodes: list[dict[str, Any]] = []
    grid: list[dict[str, Any]] = []
    world: WorldTable = msgspec.field(default_factory=WorldTable)
    middleware: dict[str, Any] = {}  # checked per mote, with the mote's own (its errors name it)
    groups: _Raw = None
    channels: _Raw = None


class _Mote(Struct, kw_only=True):  # what a node and a grid entry share
    kind: _Name
    tx_power_dbm: Finite | None = None
    battery_mj: _Positive | None = None
    boot_s: _NonNeg = 0.0


class _Node(_Mote):
    id: int
    position: _Point | None = None
    path: Annotated[list[_Point], Meta(min_length=1)] | None = None
    speed_mps: _Positive = 1.0
    start_s: _NonNeg = 0.0
    loop: bool = False
    pause_s: _NonNeg = 0.0


class _Grid(_Mote):
    # Plain floats: msgspec 0.22 corrupts memory on a constrained float in a union with a tuple.
    spacing: float | tuple[float, float]
    cols: Annotated[int, Meta(ge=1)]
    rows: Annotated[int, Meta(ge=1)]
    first_id: int
    origin: _Point = (0.0, 0.0)
    jitter_m: _NonNeg = 0.0


# Tables whose keys are not the file's own: the world's, the middleware's, and
# the gateway's payloads.
RAW_TABLES = ("world", "groups", "channels", "middleware")
TOP_KEYS = frozenset(_File.__struct_fields__) - set(RAW_TABLES)
NODE_KEYS = frozenset(_Node.__struct_fields__)
GRID_KEYS = frozenset(_Grid.__struct_fields__)
# Keys a node or grid entry may add for its node kind (docs/deployments.md): its
# middleware overrides and its sensors' noise (checked by _Parser._tables).
ENTRY_EXTRA_KEYS = frozenset({"middleware", "noise"})
_PATH_ONLY = ("speed_mps", "start_s", "loop", "pause_s")
# The settings a ``middleware`` table may override (protocol/config.py).
MIDDLEWARE_SETTINGS = frozenset(f.name for f in fields(MiddlewareConfig))
# [[groups]] / [[channels]] entries: the MQTT payload plus the key of its topic.
DEFINITION_KEYS = {"groups": "type", "channels": "id"}
# The [experiment] table (docs/experiments.md): each key and what it holds.
EXPERIMENT_KEYS: dict[str, str] = {
    "robot": "int",
    "gateway": "int",
    "tracking_group": "int",
    "channel": "int",
    "define_at_s": "num",
    "duration_s": "num",
    "rssi_motes": "ints",
    "snapshots_s": "nums",
    "field": "nums4",
    "two_fires_s": "nums2",
    "merged_s": "nums2",
    "split_s": "nums2",
    "kill_at_s": "num",
    "analysis": "name",
}


class DeploymentError(ValueError):
    """A deployment file that cannot be used; the message says where and why."""


@dataclass(frozen=True)
class NodeSpec:
    """One mote of a deployment.

    ``position`` is where a static mote stands, or the first waypoint of a
    ``path`` (then it moves at ``speed_mps`` from ``start_s``, pausing
    ``pause_s`` at waypoints, looping if ``loop``). ``boot_s`` is when it is
    switched on. ``tx_power_dbm`` None means the deployment's. ``middleware``
    holds the entry's own :class:`~awaremw.protocol.config.MiddlewareConfig`
    overrides (checked, converted), ``noise`` its sensors' noise sigma overrides.
    """

    id: int
    kind: str
    position: Point
    path: tuple[Point, ...] | None = None
    speed_mps: float = 1.0
    start_s: float = 0.0
    loop: bool = False
    pause_s: float = 0.0
    tx_power_dbm: float | None = None
    battery_mj: float | None = None
    boot_s: float = 0.0
    middleware: Mapping[str, Any] = field(default_factory=dict)
    noise: Mapping[str, float] = field(default_factory=dict)

    @property
    def is_mobile(self) -> bool:
        return self.path is not None

    def mobility(self) -> Mobility:
        if self.path is None:
            return Static(*self.position)
        return Path(self.path, self.speed_mps, self.start_s, self.loop, self.pause_s)


@dataclass(frozen=True)
class Deployment:
    """A deployment file, read and checked: what every other module reads.

    ``world`` is the typed ``[world]`` table (:meth:`world_model` makes the
    seeded :class:`World`, as :meth:`radio_model` makes the radio's);
    ``middleware`` the ``[middleware]`` overrides (checked, converted);
    ``groups`` / ``channels`` the ``[[groups]]`` / ``[[channels]]`` entries
    (tables with an integer ``type`` / ``id``: the gateway's payloads);
    ``experiment`` the ``[experiment]`` table (checked against
    :data:`EXPERIMENT_KEYS`); ``extra`` the other top-level tables.
    """

    name: str
    area: Point  # (width, height) in m; positions lie in [0, w] x [0, h]
    radio: str  # a key of radio.model.PRESETS
    seed: int
    tx_power_dbm: float
    nodes: tuple[NodeSpec, ...]  # sorted by id
    world: WorldTable = field(default_factory=WorldTable)
    groups: tuple[Mapping[str, Any], ...] = ()
    channels: tuple[Mapping[str, Any], ...] = ()
    middleware: Mapping[str, Any] = field(default_factory=dict)
    experiment: Mapping[str, Any] = field(default_factory=dict)
    description: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)  # other top-level tables
    path: FsPath | None = None
    mac: str = "csma"  # radio/mac.py MAC_KINDS: "csma" (the preset's CSMA/CA) or "aloha"
    collisions: str = "sinr"  # radio/mac.py COLLISION_MODES: "sinr" or "none"
    # How real the radio is (radio/environment.py): noise, hardware variance, and a
    # links file (resolved: a shipped name or an absolute path), read once here.
    radio_settings: RadioSettings = field(default_factory=RadioSettings)
    link_file: LinkFile | None = None

    @property
    def preset(self) -> RadioPreset:
        return PRESETS[self.radio]

    def radio_model(self, symmetric: bool = True) -> RadioModel:
        return radio_model(self.preset, self.seed, self.radio_settings, symmetric, self.link_file)

    def world_model(self) -> World:
        """The world the motes sense: the ``[world]`` table, seeded by the
        deployment's seed unless the table names its own (checked when read)."""
        return build_world(self.world, self.seed)

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(n.id for n in self.nodes)

    def node(self, node_id: int) -> NodeSpec:
        for n in self.nodes:
            if n.id == node_id:
                return n
        raise KeyError(f"no node {node_id} in deployment {self.name!r}")

    def of_kind(self, kind: str) -> tuple[NodeSpec, ...]:
        return tuple(n for n in self.nodes if n.kind == kind)

    def tx_power_of(self, spec: NodeSpec) -> float:
        return self.tx_power_dbm if spec.tx_power_dbm is None else spec.tx_power_dbm


# --------------------------------------------------------------------------- loading


def shipped_dir() -> FsPath:
    """The folder of the deployments shipped with the package: the top-level
    ``nodes/*.toml`` of the source tree, installed as the package data of
    ``awaremw.deployments`` and found through :mod:`importlib.resources`."""
    return FsPath(str(resources.files("awaremw.deployments")))


def shipped_names() -> list[str]:
    """The names of the shipped deployments (``romeo4r``, ``fire``, ...)."""
    return sorted(p.stem for p in shipped_dir().glob("*.toml"))


def find_deployment(name_or_path: str | FsPath) -> FsPath:
    """Resolve a deployment: an existing path is returned as it is; a name such
    as ``"romeo4r"`` is ``./romeo4r.toml`` when the working directory has one
    (a local file overrides the shipped one), else the shipped deployment."""
    p = FsPath(name_or_path)
    if p.is_file():
        return p
    fname = p.name if p.suffix == ".toml" else p.name + ".toml"
    tried: list[FsPath] = []
    candidates = [FsPath.cwd() / p, shipped_dir() / fname]
    if p.suffix != ".toml":
        candidates.insert(1, FsPath.cwd() / (str(p) + ".toml"))
    for c in candidates:
        if c not in tried:
            tried.append(c)
            if c.is_file():
                return c
    raise DeploymentError(
        f"{name_or_path}: no such deployment (tried {', '.join(map(str, tried))}); "
        f"shipped: {', '.join(shipped_names()) or 'none'}"
    )


def load(name_or_path: str | FsPath, known_kinds: Iterable[str] | None = None) -> Deployment:
    """:func:`find_deployment` then :func:`load_deployment`."""
    return load_deployment(find_deployment(name_or_path), known_kinds)


def load_deployment(path: str | FsPath, known_kinds: Iterable[str] | None = None) -> Deployment:
    """Read and validate a deployment file. Raises :class:`DeploymentError`."""
    fp = FsPath(path)
    try:
        text = fp.read_text(encoding="utf-8")
    except OSError as e:
        raise DeploymentError(f"{fp}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise DeploymentError(f"{fp}: not UTF-8 text: {e}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise DeploymentError(f"{fp}: invalid TOML: {e}") from None
    return parse_deployment(data, fp, known_kinds)


def parse_deployment(
    data: Mapping[str, Any],
    path: FsPath | None = None,
    known_kinds: Iterable[str] | None = None,
) -> Deployment:
    """Validate an already parsed TOML document (see :func:`load_deployment`)."""
    return _Parser(data, path, None if known_kinds is None else set(known_kinds)).parse()


class _Parser:
    def __init__(self, data: Mapping[str, Any], path: FsPath | None, kinds: set[str] | None):
        self.data = data
        self.path = path
        self.file = str(path) if path is not None else "<deployment>"
        self.kinds = kinds

    def _fail(self, where: str, what: str) -> DeploymentError:
        return DeploymentError(f"{self.file}: {where}: {what}" if where else f"{self.file}: {what}")

    def _convert(self, where: str, doc: Any, type_: type[T]) -> T:
        try:
            return convert(doc, type_)
        except Invalid as e:
            if e.path.startswith("world."):  # the [world] table's own form (docs/world.md)
                raise self._fail(where, f"{e.path}: {e.why}") from None
            raise self._fail(where, f"{e.path!r} {e.why}" if e.path else e.why) from None

    # ------------------------------------------------------------ checks

    def _check_kind(self, where: str, kind: str) -> None:
        if self.kinds is not None and kind not in self.kinds:
            known = ", ".join(sorted(self.kinds))
            raise self._fail(where, f"unknown kind {kind!r} (known: {known})")

    def _check_inside(self, where: str, p: Point, what: str) -> None:
        w, h = self.area
        if not (0.0 <= p[0] <= w and 0.0 <= p[1] <= h):
            raise self._fail(
                where, f"{what} ({p[0]:g}, {p[1]:g}) is outside the area {w:g} x {h:g} m"
            )

    def _check_power(self, where: str, dbm: float | None) -> None:
        if dbm is None:
            return
        try:
            self.preset.check_tx_power(dbm)
        except ValueError as e:
            raise self._fail(where, str(e)) from None

    def _check_id(self, where: str, node_id: int) -> None:
        if not 0 <= node_id <= MAX_NODE_ID:
            raise self._fail(
                where,
                f"id {node_id} is outside 0..{MAX_NODE_ID} (IEEE 802.15.4 short "
                "addresses; 0xFFFE and 0xFFFF are reserved)",
            )

    def _check_mote(self, where: str, m: _Mote) -> None:
        self._check_kind(where, m.kind)
        self._check_power(where, m.tx_power_dbm)

    # ------------------------------------------------------------ parse

    def parse(self) -> Deployment:
        d = self.data
        if "area" not in d:
            raise self._fail("", "missing key 'area' ([width, height] in metres)")
        f = self._convert("", d, _File)
        extra: dict[str, Any] = {}
        for k, v in d.items():
            if k in _File.__struct_fields__:
                continue
            if not isinstance(v, dict):
                raise self._fail("", f"unknown key {k!r}")
            extra[k] = v
        if f.radio not in PRESETS:
            raise self._fail("", f"unknown radio preset {f.radio!r} (known: {', '.join(PRESETS)})")
        self.preset = PRESETS[f.radio]
        if f.mac not in MAC_KINDS:
            raise self._fail("", f"unknown mac {f.mac!r} (known: {', '.join(MAC_KINDS)})")
        if f.collisions not in COLLISION_MODES:
            raise self._fail(
                "", f"unknown collisions {f.collisions!r} (known: {', '.join(COLLISION_MODES)})"
            )
        tx_power = self.preset.tx_power_dbm if f.tx_power_dbm is None else f.tx_power_dbm
        self._check_power("", tx_power)
        self.area, self.seed = f.area, f.seed
        settings, link_file = self._radio_settings(f)

        specs: dict[int, tuple[NodeSpec, str, Mapping[str, Any]]] = {}

        def put(spec: NodeSpec, where: str, entry: Mapping[str, Any]) -> None:
            if spec.id in specs:
                raise self._fail(where, f"duplicate id {spec.id} (also {specs[spec.id][1]})")
            specs[spec.id] = (spec, where.split(" (")[0], entry)

        for i, entry in enumerate(f.nodes):
            spec, where = self._node(i, entry)
            put(spec, where, entry)
        for i, entry in enumerate(f.grid):
            for spec, where in self._grid(i, entry):
                put(spec, where, entry)
        if not specs:
            raise self._fail("", "no nodes (add [[nodes]] or [[grid]] entries)")
        link_file = self._check_links(link_file, specs)
        try:
            build_world(f.world, f.seed)  # keyframes completed, sources in order
        except WorldError as e:
            raise self._fail("", str(e)) from None
        nodes, middleware = self._tables(specs, f.middleware)

        return Deployment(
            name=f.name or (self.path.stem if self.path is not None else "deployment"),
            area=f.area,
            radio=f.radio,
            seed=f.seed,
            tx_power_dbm=tx_power,
            nodes=nodes,
            world=f.world,
            groups=self._definitions("groups", f.groups),
            channels=self._definitions("channels", f.channels),
            middleware=middleware,
            experiment=self._experiment(extra.pop("experiment", {})),
            description=f.description,
            extra=extra,
            path=self.path,
            mac=f.mac,
            collisions=f.collisions,
            radio_settings=settings,
            link_file=link_file,
        )

    # ------------------------------------------------------------ the motes' own tables

    def _tables(
        self, specs: Mapping[int, tuple[NodeSpec, str, Mapping[str, Any]]], common: Any
    ) -> tuple[tuple[NodeSpec, ...], dict[str, Any]]:
        """The motes, sorted by id, with their entry's ``noise`` and ``middleware``
        tables checked, and the deployment's ``[middleware]`` (``common``): an
        error names the first mote, by id, that the bad table reaches."""
        checked: dict[int, tuple[dict[str, float], dict[str, Any]]] = {}  # by entry
        out: list[NodeSpec] = []
        overrides: dict[str, Any] = {}
        for node_id in sorted(specs):
            spec, _, entry = specs[node_id]
            tables = checked.get(id(entry))
            if tables is None:
                where = f"node {node_id}"
                noise = self._noise(where, entry.get("noise", {}))
                if not checked:
                    overrides = self._middleware(where, common)
                tables = noise, self._middleware(where, entry.get("middleware", {}))
                checked[id(entry)] = tables
            if tables[0] or tables[1]:
                spec = replace(spec, noise=tables[0], middleware=tables[1])
            out.append(spec)
        return tuple(out), overrides

    def _noise(self, where: str, table: Any) -> dict[str, float]:
        if not isinstance(table, Mapping):
            raise self._fail(where, "'noise' must be a table")
        noise: dict[str, float] = {}
        for sensor, sigma in table.items():
            if isinstance(sigma, bool) or not isinstance(sigma, int | float) or sigma < 0:
                raise self._fail(where, f"noise.{sensor} must be a number >= 0")
            noise[str(sensor)] = float(sigma)
        return noise

    def _middleware(self, where: str, table: Any) -> dict[str, Any]:
        """A ``middleware`` table's overrides, checked against MiddlewareConfig's
        annotations (strictly, as :meth:`MiddlewareConfig.with_overrides` does)."""
        if not isinstance(table, Mapping):
            raise self._fail(where, "'middleware' must be a table")
        unknown = sorted(set(table) - MIDDLEWARE_SETTINGS)
        if unknown:
            raise self._fail(where, f"unknown middleware settings: {', '.join(unknown)}")
        try:
            config = convert(dict(table), MiddlewareConfig)
        except Invalid as e:
            raise self._fail(where, f"middleware setting {e.path!r}: {e.why}") from None
        return {k: getattr(config, k) for k in table}

    # ------------------------------------------------------------ definitions, experiment

    def _definitions(self, kind: str, raw: Any) -> tuple[Mapping[str, Any], ...]:
        """``[[groups]]`` / ``[[channels]]`` entries (one table is one entry), each
        with its integer ``type`` / ``id``; their payloads are the gateway's to check."""
        if raw is None:
            return ()
        if isinstance(raw, Mapping):
            raw = [raw]
        if not isinstance(raw, list) or not all(isinstance(e, Mapping) for e in raw):
            raise self._fail("", f"{kind} must be an array of tables ([[{kind}]])")
        key = DEFINITION_KEYS[kind]
        for i, entry in enumerate(raw):
            if key not in entry:
                raise self._fail(f"{kind}[{i}]", f"missing key {key!r}")
            ident = entry[key]
            if isinstance(ident, bool) or not isinstance(ident, int):
                raise self._fail(f"{kind}[{i}]", f"{key!r} must be an integer")
        return tuple(raw)

    def _experiment(self, table: Mapping[str, Any]) -> dict[str, Any]:
        def num(v: Any) -> bool:
            return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)

        for k, v in table.items():
            kind = EXPERIMENT_KEYS.get(k)
            if kind is None:
                raise self._fail(
                    "", f"experiment.{k}: unknown key (known: {', '.join(EXPERIMENT_KEYS)})"
                )
            ok = {
                "int": isinstance(v, int) and not isinstance(v, bool),
                "num": num(v),
                "ints": isinstance(v, list) and all(isinstance(x, int) for x in v),
                "nums": isinstance(v, list) and all(num(x) for x in v),
                "nums4": isinstance(v, list) and len(v) == 4 and all(num(x) for x in v),
                "nums2": isinstance(v, list) and len(v) == 2 and all(num(x) for x in v),
                "name": isinstance(v, str) and bool(v),
            }[kind]
            if not ok:
                raise self._fail("", f"experiment.{k}: expected {kind}, got {v!r}")
        return dict(table)

    # ------------------------------------------------------------ the radio's files

    def _relative(self, value: str) -> FsPath:
        p = FsPath(value).expanduser()
        if not p.is_absolute() and self.path is not None:
            p = self.path.parent / p
        return p

    def _radio_settings(self, f: _File) -> tuple[RadioSettings, LinkFile | None]:
        """The radio's realism keys, checked and their files read (errors name the key)."""
        noise = f.noise
        if noise != WHITE and noise not in SHIPPED_TRACES:
            noise = str(self._relative(noise))
            try:
                load_trace(noise)
            except NoiseTraceError as e:
                raise self._fail("noise", f"{e} (or 'white', or a shipped trace: "
                                 f"{', '.join(SHIPPED_TRACES)})") from None  # fmt: skip
        links = f.links
        link_file = None
        if links is not None:
            if links not in SHIPPED_LINKS:
                links = str(self._relative(links))
            try:
                link_file = load_links(links)
            except LinksError as e:
                raise self._fail("links", f"{e} (shipped: {', '.join(SHIPPED_LINKS)})") from None
        settings = RadioSettings(noise, f.hardware_variance, links)
        try:
            settings.check(link_file)
        except ValueError as e:
            raise self._fail("", str(e)) from None
        return settings, link_file

    def _check_links(
        self, link_file: LinkFile | None, specs: Mapping[int, tuple[NodeSpec, str, Any]]
    ) -> LinkFile | None:
        if link_file is None:
            return None
        for spec, where, _ in specs.values():
            if spec.path is not None:
                raise self._fail(
                    where, "moves (path), but a links file fixes every link: give it a position"
                )
        named = link_file.nodes()
        missing = sorted(set(specs) - named)
        if missing:
            raise self._fail(
                "links", f"{link_file.path} has no link of mote(s) {', '.join(map(str, missing))}"
            )
        return link_file

    def _check_keys(self, where: str, t: Mapping[str, Any], keys: frozenset[str]) -> None:
        """A key an entry cannot have is refused as such, with every key it can."""
        allowed = keys | ENTRY_EXTRA_KEYS
        unknown = sorted(k for k in t if k not in allowed)
        if unknown:
            raise self._fail(
                where,
                f"unknown key(s) {', '.join(map(repr, unknown))} "
                f"(allowed: {', '.join(sorted(allowed))})",
            )

    def _node(self, i: int, t: dict[str, Any]) -> tuple[NodeSpec, str]:
        ident = t.get("id")
        where = f"nodes[{i}] (id {ident})" if type(ident) is int else f"nodes[{i}]"
        self._check_keys(where, t, NODE_KEYS)
        n = self._convert(where, t, _Node)
        self._check_id(where, n.id)
        self._check_mote(where, n)
        if n.path is not None and n.position is None:
            for k, p in enumerate(n.path):
                self._check_inside(where, p, f"path[{k}]")
            position, path = n.path[0], tuple(n.path)
        elif n.position is not None and n.path is None:
            for key in _PATH_ONLY:
                if key in t:
                    raise self._fail(where, f"{key!r} only makes sense with a 'path'")
            self._check_inside(where, n.position, "position")
            position, path = n.position, None
        else:
            raise self._fail(where, "give exactly one of 'position' or 'path'")
        spec = NodeSpec(
            id=n.id,
            kind=n.kind,
            position=position,
            path=path,
            speed_mps=n.speed_mps,
            start_s=n.start_s,
            loop=n.loop,
            pause_s=n.pause_s,
            tx_power_dbm=n.tx_power_dbm,
            battery_mj=n.battery_mj,
            boot_s=n.boot_s,
        )
        return spec, where

    def _grid(self, i: int, t: dict[str, Any]) -> list[tuple[NodeSpec, str]]:
        self._check_keys(f"grid[{i}]", t, GRID_KEYS)
        g = self._convert(f"grid[{i}]", t, _Grid)
        spacing = g.spacing if isinstance(g.spacing, tuple) else (g.spacing, g.spacing)
        if not all(0 < s < math.inf for s in spacing):
            raise self._fail(f"grid[{i}]", f"'spacing' must be > 0, got {t['spacing']!r}")
        last = g.first_id + g.cols * g.rows - 1
        where = f"grid[{i}] (ids {g.first_id}..{last})"
        self._check_id(where, g.first_id)
        self._check_id(where, last)
        self._check_mote(where, g)
        # Jitter from the deployment's seed and the grid's index: the same
        # positions in every process that loads the file.
        rng = random.Random(self.seed * 1_000_003 + i)
        w, h = self.area
        jitter = g.jitter_m
        out: list[tuple[NodeSpec, str]] = []
        for r in range(g.rows):
            for c in range(g.cols):
                node_id = g.first_id + r * g.cols + c
                x = g.origin[0] + c * spacing[0]
                y = g.origin[1] + r * spacing[1]
                self._check_inside(where, (x, y), f"position of id {node_id}")
                if jitter:
                    x = min(w, max(0.0, x + rng.uniform(-jitter, jitter)))
                    y = min(h, max(0.0, y + rng.uniform(-jitter, jitter)))
                spec = NodeSpec(
                    id=node_id,
                    kind=g.kind,
                    position=(x, y),
                    tx_power_dbm=g.tx_power_dbm,
                    battery_mj=g.battery_mj,
                    boot_s=g.boot_s,
                )
                out.append((spec, f"{where}: id {node_id}"))
        return out
