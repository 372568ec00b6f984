"""Deployment files: TOML -> typed, validated, frozen specs.

A deployment says which motes stand where (or move how), with which radio,
and which world, groups and channels a scenario starts with. The format is
documented in ``docs/deployments.md``. Loading never half-works: any problem
raises :class:`DeploymentError` whose message names the file, the entry
(``nodes[3] (id 17)``, ``grid[0]``) and what is wrong.

The ``world``, ``groups``, ``channels`` and ``middleware`` tables are passed
through raw (their owners validate them); unknown top-level *tables* are kept
in ``Deployment.extra``; unknown top-level *values* are errors (typos).
"""

from __future__ import annotations

import math
import random
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path as FsPath
from typing import Any

from awaremw.protocol.frames import MAX_NODE_ID
from awaremw.radio.mac import COLLISION_MODES, MAC_KINDS
from awaremw.radio.model import PRESETS, RadioModel, RadioPreset
from awaremw.world.mobility import Mobility, Path, Static

Point = tuple[float, float]

DEFAULT_RADIO = "cc2420"

# The keys a deployment file may have (docs/deployments.md lists each; a test
# holds the two equal): top-level values, raw tables, node and grid entries.
TOP_KEYS = frozenset({
    "name", "description", "radio", "seed", "tx_power_dbm", "area", "nodes", "grid", "mac",
    "collisions",
})  # fmt: skip
RAW_TABLES = ("world", "groups", "channels", "middleware")
NODE_KEYS = frozenset({
    "id",
    "kind",
    "position",
    "path",
    "speed_mps",
    "start_s",
    "loop",
    "pause_s",
    "tx_power_dbm",
    "battery_mj",
    "boot_s",
})
_PATH_ONLY = ("speed_mps", "start_s", "loop", "pause_s")
GRID_KEYS = frozenset({
    "origin",
    "spacing",
    "cols",
    "rows",
    "first_id",
    "kind",
    "jitter_m",
    "tx_power_dbm",
    "battery_mj",
    "boot_s",
})


class DeploymentError(ValueError):
    """A deployment file that cannot be used; the message says where and why."""


@dataclass(frozen=True)
class NodeSpec:
    """One mote of a deployment.

    ``position`` is where a static mote stands, or the first waypoint of a
    ``path`` (then it moves at ``speed_mps`` from ``start_s``, pausing
    ``pause_s`` at waypoints, looping if ``loop``). ``boot_s`` is when it is
    switched on. ``tx_power_dbm`` None means the deployment's. ``extra`` holds
    the entry's other keys, for the node kind (e.g. its config overrides).
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
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def is_mobile(self) -> bool:
        return self.path is not None

    def mobility(self) -> Mobility:
        if self.path is None:
            return Static(*self.position)
        return Path(self.path, self.speed_mps, self.start_s, self.loop, self.pause_s)


@dataclass(frozen=True)
class Deployment:
    name: str
    area: Point  # (width, height) in m; positions lie in [0, w] x [0, h]
    radio: str  # a key of radio.model.PRESETS
    seed: int
    tx_power_dbm: float
    nodes: tuple[NodeSpec, ...]  # sorted by id
    world: Mapping[str, Any] = field(default_factory=dict)
    groups: Any = None  # raw: table or array of tables, as written
    channels: Any = None
    middleware: Mapping[str, Any] = field(default_factory=dict)
    description: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)  # other top-level tables
    path: FsPath | None = None
    mac: str = "csma"  # radio/mac.py MAC_KINDS: "csma" (the preset's CSMA/CA) or "aloha"
    collisions: str = "sinr"  # radio/mac.py COLLISION_MODES: "sinr" or "none"

    @property
    def preset(self) -> RadioPreset:
        return PRESETS[self.radio]

    def radio_model(self, symmetric: bool = True) -> RadioModel:
        return RadioModel(self.preset, self.seed, symmetric)

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

    # ------------------------------------------------------------ typed getters

    def _number(
        self, where: str, t: Mapping[str, Any], key: str, default: float | None = None
    ) -> float:
        if key not in t:
            if default is None:
                raise self._fail(where, f"missing key {key!r}")
            return default
        v = t[key]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self._fail(where, f"{key!r} must be a number, got {v!r}")
        return float(v)

    def _opt_number(self, where: str, t: Mapping[str, Any], key: str) -> float | None:
        return self._number(where, t, key) if key in t else None

    def _integer(
        self, where: str, t: Mapping[str, Any], key: str, default: int | None = None
    ) -> int:
        if key not in t:
            if default is None:
                raise self._fail(where, f"missing key {key!r}")
            return default
        v = t[key]
        if isinstance(v, bool) or not isinstance(v, int):
            raise self._fail(where, f"{key!r} must be an integer, got {v!r}")
        return v

    def _string(
        self, where: str, t: Mapping[str, Any], key: str, default: str | None = None
    ) -> str:
        if key not in t:
            if default is None:
                raise self._fail(where, f"missing key {key!r}")
            return default
        v = t[key]
        if not isinstance(v, str) or not v:
            raise self._fail(where, f"{key!r} must be a non-empty string, got {v!r}")
        return v

    def _boolean(self, where: str, t: Mapping[str, Any], key: str, default: bool) -> bool:
        v = t.get(key, default)
        if not isinstance(v, bool):
            raise self._fail(where, f"{key!r} must be true or false, got {v!r}")
        return v

    def _point(self, where: str, v: Any, what: str) -> Point:
        if (
            not isinstance(v, list)
            or len(v) != 2
            or any(isinstance(c, bool) or not isinstance(c, int | float) for c in v)
            or not all(math.isfinite(c) for c in v)
        ):
            raise self._fail(where, f"{what} must be [x, y] in metres, got {v!r}")
        return float(v[0]), float(v[1])

    def _table(self, where: str, v: Any) -> Mapping[str, Any]:
        if not isinstance(v, dict):
            raise self._fail(where, f"must be a table, got {type(v).__name__}")
        return v

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

    def _check_battery(self, where: str, mj: float | None) -> None:
        if mj is not None and not mj > 0:
            raise self._fail(where, f"'battery_mj' must be > 0, got {mj:g}")

    def _check_nonneg(self, where: str, key: str, v: float) -> None:
        if v < 0:
            raise self._fail(where, f"{key!r} must be >= 0, got {v:g}")

    # ------------------------------------------------------------ parse

    def parse(self) -> Deployment:
        d = self.data
        extra: dict[str, Any] = {}
        for k, v in d.items():
            if k in TOP_KEYS or k in RAW_TABLES:
                continue
            if isinstance(v, dict):
                extra[k] = v
            else:
                raise self._fail("", f"unknown key {k!r}")
        default_name = self.path.stem if self.path is not None else "deployment"
        name = self._string("", d, "name", default_name)
        description = d.get("description", "")
        if not isinstance(description, str):
            raise self._fail("", "'description' must be a string")
        radio = self._string("", d, "radio", DEFAULT_RADIO)
        if radio not in PRESETS:
            raise self._fail("", f"unknown radio preset {radio!r} (known: {', '.join(PRESETS)})")
        self.preset = PRESETS[radio]
        seed = self._integer("", d, "seed", 0)
        mac = self._string("", d, "mac", "csma")
        if mac not in MAC_KINDS:
            raise self._fail("", f"unknown mac {mac!r} (known: {', '.join(MAC_KINDS)})")
        collisions = self._string("", d, "collisions", "sinr")
        if collisions not in COLLISION_MODES:
            raise self._fail(
                "", f"unknown collisions {collisions!r} (known: {', '.join(COLLISION_MODES)})"
            )
        tx_power = self._number("", d, "tx_power_dbm", self.preset.tx_power_dbm)
        self._check_power("", tx_power)
        if "area" not in d:
            raise self._fail("", "missing key 'area' ([width, height] in metres)")
        self.area = self._point("", d["area"], "'area'")
        if not (self.area[0] > 0 and self.area[1] > 0):
            raise self._fail("", f"'area' must be positive, got {d['area']!r}")
        self.seed = seed

        raw: dict[str, Any] = {}
        for key in RAW_TABLES:
            v = d.get(key)
            if v is not None and not isinstance(v, dict | list):
                raise self._fail("", f"{key!r} must be a table or an array of tables")
            if key in ("world", "middleware") and v is not None and not isinstance(v, dict):
                raise self._fail("", f"{key!r} must be a table ([{key}])")
            raw[key] = v

        specs: dict[int, tuple[NodeSpec, str]] = {}

        def put(spec: NodeSpec, where: str) -> None:
            if spec.id in specs:
                raise self._fail(where, f"duplicate id {spec.id} (also {specs[spec.id][1]})")
            specs[spec.id] = (spec, where.split(" (")[0])

        nodes = d.get("nodes", [])
        if not isinstance(nodes, list):
            raise self._fail("", "'nodes' must be an array of tables ([[nodes]])")
        for i, entry in enumerate(nodes):
            spec, where = self._node(i, entry)
            put(spec, where)
        grids = d.get("grid", [])
        if not isinstance(grids, list):
            raise self._fail("", "'grid' must be an array of tables ([[grid]])")
        for i, entry in enumerate(grids):
            for spec, where in self._grid(i, entry):
                put(spec, where)
        if not specs:
            raise self._fail("", "no nodes (add [[nodes]] or [[grid]] entries)")

        return Deployment(
            name=name,
            area=self.area,
            radio=radio,
            seed=seed,
            tx_power_dbm=tx_power,
            nodes=tuple(s for _, (s, _) in sorted(specs.items())),
            world=raw["world"] or {},
            groups=raw["groups"],
            channels=raw["channels"],
            middleware=raw["middleware"] or {},
            description=description,
            extra=extra,
            path=self.path,
            mac=mac,
            collisions=collisions,
        )

    def _node(self, i: int, entry: Any) -> tuple[NodeSpec, str]:
        where = f"nodes[{i}]"
        t = self._table(where, entry)
        node_id = self._integer(where, t, "id")
        where = f"nodes[{i}] (id {node_id})"
        self._check_id(where, node_id)
        kind = self._string(where, t, "kind")
        self._check_kind(where, kind)
        has_pos, has_path = "position" in t, "path" in t
        if has_pos == has_path:
            raise self._fail(where, "give exactly one of 'position' or 'path'")
        path: tuple[Point, ...] | None = None
        if has_path:
            raw = t["path"]
            if not isinstance(raw, list) or not raw:
                raise self._fail(where, "'path' must be a non-empty array of [x, y] waypoints")
            path = tuple(self._point(where, p, f"path[{k}]") for k, p in enumerate(raw))
            for k, p in enumerate(path):
                self._check_inside(where, p, f"path[{k}]")
            position = path[0]
        else:
            for key in _PATH_ONLY:
                if key in t:
                    raise self._fail(where, f"{key!r} only makes sense with a 'path'")
            position = self._point(where, t["position"], "'position'")
            self._check_inside(where, position, "position")
        speed = self._number(where, t, "speed_mps", 1.0)
        if not speed > 0:
            raise self._fail(where, f"'speed_mps' must be > 0, got {speed:g}")
        start_s = self._number(where, t, "start_s", 0.0)
        pause_s = self._number(where, t, "pause_s", 0.0)
        boot_s = self._number(where, t, "boot_s", 0.0)
        for key, v in (("start_s", start_s), ("pause_s", pause_s), ("boot_s", boot_s)):
            self._check_nonneg(where, key, v)
        loop = self._boolean(where, t, "loop", False)
        tx_power = self._opt_number(where, t, "tx_power_dbm")
        self._check_power(where, tx_power)
        battery = self._opt_number(where, t, "battery_mj")
        self._check_battery(where, battery)
        extra = {k: v for k, v in t.items() if k not in NODE_KEYS}
        spec = NodeSpec(
            id=node_id,
            kind=kind,
            position=position,
            path=path,
            speed_mps=speed,
            start_s=start_s,
            loop=loop,
            pause_s=pause_s,
            tx_power_dbm=tx_power,
            battery_mj=battery,
            boot_s=boot_s,
            extra=extra,
        )
        return spec, where

    def _grid(self, i: int, entry: Any) -> list[tuple[NodeSpec, str]]:
        where = f"grid[{i}]"
        t = self._table(where, entry)
        origin = self._point(where, t["origin"], "'origin'") if "origin" in t else (0.0, 0.0)
        if "spacing" not in t:
            raise self._fail(where, "missing key 'spacing'")
        sp = t["spacing"]
        if isinstance(sp, list):
            spacing = self._point(where, sp, "'spacing'")
        else:
            s = self._number(where, t, "spacing")
            spacing = (s, s)
        if not (spacing[0] > 0 and spacing[1] > 0):
            raise self._fail(where, f"'spacing' must be > 0, got {sp!r}")
        cols = self._integer(where, t, "cols")
        rows = self._integer(where, t, "rows")
        if cols < 1 or rows < 1:
            raise self._fail(where, f"'cols' and 'rows' must be >= 1, got {cols} x {rows}")
        first = self._integer(where, t, "first_id")
        last = first + cols * rows - 1
        where = f"grid[{i}] (ids {first}..{last})"
        self._check_id(where, first)
        self._check_id(where, last)
        kind = self._string(where, t, "kind")
        self._check_kind(where, kind)
        jitter = self._number(where, t, "jitter_m", 0.0)
        self._check_nonneg(where, "jitter_m", jitter)
        tx_power = self._opt_number(where, t, "tx_power_dbm")
        self._check_power(where, tx_power)
        battery = self._opt_number(where, t, "battery_mj")
        self._check_battery(where, battery)
        boot_s = self._number(where, t, "boot_s", 0.0)
        self._check_nonneg(where, "boot_s", boot_s)
        extra = {k: v for k, v in t.items() if k not in GRID_KEYS}
        # Jitter from the deployment's seed and the grid's index: the same
        # positions in every process that loads the file.
        rng = random.Random(self.seed * 1_000_003 + i)
        w, h = self.area
        out: list[tuple[NodeSpec, str]] = []
        for r in range(rows):
            for c in range(cols):
                node_id = first + r * cols + c
                x = origin[0] + c * spacing[0]
                y = origin[1] + r * spacing[1]
                self._check_inside(where, (x, y), f"position of id {node_id}")
                if jitter:
                    x = min(w, max(0.0, x + rng.uniform(-jitter, jitter)))
                    y = min(h, max(0.0, y + rng.uniform(-jitter, jitter)))
                spec = NodeSpec(
                    id=node_id,
                    kind=kind,
                    position=(x, y),
                    tx_power_dbm=tx_power,
                    battery_mj=battery,
                    boot_s=boot_s,
                    extra=extra,
                )
                out.append((spec, f"{where}: id {node_id}"))
        return out
