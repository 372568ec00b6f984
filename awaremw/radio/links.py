"""Measured topologies: a links file instead of links derived from positions.

Two formats, one a file (``docs/radio.md``, "Links files"):

* **TOSSIM's topology format**: ``gain SRC DST DBM`` (one line per direction:
  the received power of SRC's frames at DST when SRC sends at 0 dBm) and
  ``noise NODE MEAN_DBM RANGE_DB`` (the receiver's noise: uniform in
  ``MEAN +- RANGE`` per instant, TOSSIM's ``sim_gain_sample_noise``), as
  TOSSIM's ``LinkLayerModel`` writes them and its Python scripts read them.
* **Measured delivery**: ``SENDER RECEIVER PROBABILITY`` triples, such as the
  Intel Berkeley Research Lab's ``connectivity.txt``. A probability is the
  delivery of a reference frame (:data:`REFERENCE_BYTES`, ours) over the
  preset's white noise floor; :class:`DeliveryCurve` turns it into the
  gain that delivers exactly that on average (fading included), so that
  frames of other lengths, collisions, capture and RSSI follow from the
  radio model as for any other link.

Lines starting with ``%`` or ``#`` and blank lines are skipped. A pair with
no line, or with probability 0, is no link: the receiver never gets the
sender's frames (counted as ``dropped_loss``). A mote's link to itself is
ignored. Anything else malformed is refused with its line number.
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Final

from awaremw.protocol.frames import MAX_NODE_ID
from awaremw.radio.model import NORMAL, RadioModel
from awaremw.radio.textfile import read_bounded

MAX_LINKS_BYTES: Final = 64 << 20
MAX_LINKS: Final = 4_000_000
GAIN_RANGE: Final = (-250.0, 50.0)  # dB a gain line may hold
NOISE_RANGE: Final = (-200.0, 50.0)
MAX_NOISE_RANGE: Final = 50.0
# A delivery probability is the delivery of a frame of this many bytes (ours;
# the preset's PHY overhead is added on the air): bench links sends its beacons
# at exactly this length.
REFERENCE_BYTES: Final = 20
NO_LINK_DBM: Final = -1e9  # the mean RSSI of a pair without a link (never delivers)

SHIPPED: Final[dict[str, str]] = {"intel-lab": "intel-lab-connectivity.txt"}


class LinksError(ValueError):
    """A links file that cannot be used; the message names the file and the line."""


@dataclass(frozen=True)
class LinkFile:
    """A parsed links file: gains (dB at 0 dBm), or delivery probabilities, and
    the ``noise`` lines (mean, range) of a TOSSIM file."""

    path: str
    gains: Mapping[tuple[int, int], float]
    probabilities: Mapping[tuple[int, int], float]
    noise: Mapping[int, tuple[float, float]]

    def nodes(self) -> set[int]:
        """Every mote the file names."""
        out = set(self.noise)
        for a, b in (*self.gains, *self.probabilities):
            out.add(a)
            out.add(b)
        return out


def shipped_links_path(name: str) -> Path:
    return Path(str(resources.files("awaremw.radio") / "data" / SHIPPED[name]))


def _node(tok: str, where: str) -> int:
    try:
        v = int(tok)
    except ValueError:
        raise LinksError(f"{where}: {tok!r} is not a mote id") from None
    if not 0 <= v <= MAX_NODE_ID:
        raise LinksError(f"{where}: mote id {v} is outside 0..{MAX_NODE_ID}")
    return v


def _number(tok: str, where: str, what: str, lo: float, hi: float) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise LinksError(f"{where}: {what} {tok!r} is not a number") from None
    if not lo <= v <= hi:  # NaN fails too
        raise LinksError(f"{where}: {what} {v!r} is outside {lo:g}..{hi:g}")
    return v


def parse_links(text: str, name: str = "<links>") -> LinkFile:
    """Parse the text of a links file (see the module's docstring)."""
    gains: dict[tuple[int, int], float] = {}
    probs: dict[tuple[int, int], float] = {}
    noise: dict[int, tuple[float, float]] = {}
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s[0] in "%#":
            continue
        where = f"{name}: line {n}"
        tok = s.split()
        head = tok[0].lower()
        if head == "gain":
            if len(tok) != 4:
                raise LinksError(f"{where}: a gain line is 'gain SRC DST DBM', got {s[:60]!r}")
            a, b = _node(tok[1], where), _node(tok[2], where)
            g = _number(tok[3], where, "gain", *GAIN_RANGE)
            if (a, b) in gains:
                raise LinksError(f"{where}: a second gain for {a} -> {b}")
            if a != b:
                gains[(a, b)] = g
        elif head == "noise":
            if len(tok) != 4:
                raise LinksError(
                    f"{where}: a noise line is 'noise NODE MEAN RANGE', got {s[:60]!r}"
                )
            node = _node(tok[1], where)
            mean = _number(tok[2], where, "noise mean", *NOISE_RANGE)
            rng = _number(tok[3], where, "noise range", 0.0, MAX_NOISE_RANGE)
            if node in noise:
                raise LinksError(f"{where}: a second noise line for {node}")
            noise[node] = (mean, rng)
        elif len(tok) == 3:
            a, b = _node(tok[0], where), _node(tok[1], where)
            p = _number(tok[2], where, "probability", 0.0, 1.0)
            if (a, b) in probs:
                raise LinksError(f"{where}: a second probability for {a} -> {b}")
            if a != b:
                probs[(a, b)] = p
        else:
            raise LinksError(
                f"{where}: expected 'gain SRC DST DBM', 'noise NODE MEAN RANGE' or "
                f"'SENDER RECEIVER PROBABILITY', got {s[:60]!r}"
            )
        if len(gains) + len(probs) > MAX_LINKS:
            raise LinksError(f"{name}: more than {MAX_LINKS} links")
    if gains and probs:
        raise LinksError(f"{name}: gain lines and probability triples in one file: use one format")
    if probs and noise:
        raise LinksError(
            f"{name}: noise lines go with gain lines; probabilities already include the noise"
        )
    if not gains and not probs:
        raise LinksError(f"{name}: no links (no 'gain' line and no probability triple)")
    return LinkFile(name, gains, probs, noise)


def load_links(name_or_path: str | Path) -> LinkFile:
    """A shipped links file by name (``"intel-lab"``), or a path."""
    key = str(name_or_path)
    p = shipped_links_path(key) if key in SHIPPED else Path(key)
    return parse_links(read_bounded(p, MAX_LINKS_BYTES, LinksError, "a links file"), str(p))


# --------------------------------------------------------------------------- delivery -> gain

_QUANTILES: Final = 64  # points of the fading distribution averaged over
_STEP_DB: Final = 0.01


class DeliveryCurve:
    """Average delivery of a frame of ``nbytes`` against its mean RSSI, over
    the preset's fading, at a fixed noise floor: monotone, tabulated, inverted
    by bisection (:meth:`gain_for`)."""

    def __init__(self, model: RadioModel, nbytes: int, noise_dbm: float) -> None:
        p = model.preset
        bits = 8 * (nbytes + p.phy_overhead_bytes)
        step = len(NORMAL) // _QUANTILES
        zs = [NORMAL[i * step + step // 2] for i in range(_QUANTILES)]
        sf = p.fading_sigma_db
        lo = p.sensitivity_dbm - sf * 4.0
        hi = max(noise_dbm + model.one_snr_db, p.sensitivity_dbm) + sf * 4.0
        self.x: list[float] = []
        self.d: list[float] = []
        k = 0
        while True:
            mean = lo + k * _STEP_DB
            tot = 0.0
            for z in zs:
                rssi = mean - sf * z
                tot += model.prr_bits(rssi, bits, noise_dbm)
            self.x.append(mean)
            self.d.append(tot / len(zs))
            if mean >= hi:
                break
            k += 1

    def gain_for(self, p: float) -> float:
        """The smallest tabulated mean RSSI whose average delivery reaches ``p``."""
        i = bisect.bisect_left(self.d, p)
        return self.x[min(i, len(self.x) - 1)]


class LinkTable:
    """The links of a deployment: a gain (dB at 0 dBm) per directed pair."""

    __slots__ = ("_senders", "file", "gains")

    def __init__(self, f: LinkFile, model_for_curve: RadioModel | None = None) -> None:
        self.file = f
        if f.probabilities:
            if model_for_curve is None:
                raise ValueError("a table of probabilities needs the radio model")
            m = model_for_curve
            curve = DeliveryCurve(m, REFERENCE_BYTES, m.preset.noise_floor_dbm)
            base = m.preset.tx_power_dbm
            self.gains = {
                k: curve.gain_for(p) - base for k, p in f.probabilities.items() if p > 0.0
            }
        else:
            self.gains = dict(f.gains)
        by_dst: dict[int, set[int]] = {}
        for a, b in self.gains:
            by_dst.setdefault(b, set()).add(a)
        self._senders = {b: frozenset(s) for b, s in by_dst.items()}

    def senders_to(self, dst: int) -> frozenset[int]:
        """The motes ``dst`` has a link from (who it may hear)."""
        return self._senders.get(dst, frozenset())

    def given(self, src: int, dst: int) -> float | None:
        """What the file says of the pair: a probability or a gain (dB)."""
        f = self.file
        if f.probabilities:
            return f.probabilities.get((src, dst))
        return f.gains.get((src, dst))
