"""How real the radio is: noise, hardware variance, measured links, in one value.

A deployment's top-level keys ``noise``, ``hardware_variance`` and ``links``
(docs/deployments.md) become a :class:`RadioSettings`; :func:`environment`
turns the settings into the :class:`RadioEnvironment` a
:class:`~awaremw.radio.model.RadioModel` takes (None when the settings are
today's textbook radio: white noise, identical motes, links from positions).
Both media read the environment through the model only, so they take the
same decisions from the same settings.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from awaremw.radio.links import LinkFile, LinkTable, load_links
from awaremw.radio.model import RadioModel, RadioPreset
from awaremw.radio.noise import (
    HardwareVariance,
    LineNoise,
    NoiseSource,
    TraceNoise,
    WhiteNoise,
    load_trace,
)

WHITE = "white"


@dataclass(frozen=True)
class RadioSettings:
    """``noise``: ``"white"`` (the preset's constant floor), a shipped trace's
    name (``"meyer-heavy"``) or a trace file's path; ``hardware_variance``:
    per-mote output power and noise floor offsets; ``links``: a links file's
    path or a shipped name (None: links from positions)."""

    noise: str = WHITE
    hardware_variance: bool = False
    links: str | None = None

    @property
    def textbook(self) -> bool:
        return self.noise == WHITE and not self.hardware_variance and self.links is None

    def check(self, links: LinkFile | None = None) -> None:
        """ValueError if the settings contradict each other, or ``links`` (the
        links file, once read) contradicts them."""
        if self.links is not None and self.hardware_variance:
            raise ValueError(
                "hardware_variance applies to links derived from positions: a links "
                "file's gains (and noise lines) already carry its motes' differences"
            )
        if links is not None and links.probabilities and self.noise != WHITE:
            raise ValueError(
                f"{links.path}: delivery probabilities were measured over the floor's real "
                f"noise; noise = {self.noise!r} would count it twice (use 'white', or "
                "a file of gains)"
            )

    def describe(self) -> str:
        parts = [f"noise {self.noise}"]
        if self.hardware_variance:
            parts.append("hardware variance")
        if self.links is not None:
            parts.append(f"links {self.links}")
        return ", ".join(parts)


@dataclass(frozen=True)
class RadioEnvironment:
    """What the model needs of the settings (:class:`~awaremw.radio.model.Realism`):
    a noise source (None: the preset's floor), hardware offsets, a link table
    (None: links from positions)."""

    noise: NoiseSource | None
    hardware: HardwareVariance | None
    links: LinkTable | None
    settings: RadioSettings

    @property
    def noise_at(self) -> Callable[[int, float], float] | None:
        return None if self.noise is None else self.noise.at

    @property
    def noise_over(self) -> Callable[[int, float, float], float] | None:
        return None if self.noise is None else self.noise.over

    @property
    def tx_offset(self) -> Callable[[int], float] | None:
        return None if self.hardware is None else self.hardware.tx_offset

    @property
    def tx_sigma_db(self) -> float:
        return 0.0 if self.hardware is None else self.hardware.tx_sigma_db

    @property
    def gains(self) -> dict[tuple[int, int], float] | None:
        return None if self.links is None else self.links.gains


def environment(
    preset: RadioPreset, seed: int, settings: RadioSettings, links: LinkFile | None = None
) -> RadioEnvironment | None:
    """The environment of ``settings`` (None for the textbook radio).

    ``links``: the links file already read (else ``settings.links`` is read
    here). Raises ValueError (:class:`~awaremw.radio.noise.NoiseTraceError`,
    :class:`~awaremw.radio.links.LinksError`) naming what is wrong.
    """
    settings.check()
    if settings.textbook:
        return None
    hw = HardwareVariance(seed) if settings.hardware_variance else None
    table = None
    floors: dict[int, tuple[float, float]] = {}
    if settings.links is not None:
        f = links if links is not None else load_links(settings.links)
        settings.check(f)
        table = LinkTable(f, RadioModel(preset, seed))
        floors = dict(f.noise)
    noise: NoiseSource | None
    if settings.noise == WHITE:
        if floors:
            noise = LineNoise(seed, floors, (preset.noise_floor_dbm, 0.0))
        else:
            noise = None if hw is None else WhiteNoise(preset.noise_floor_dbm, hw)
    else:
        trace = load_trace(settings.noise)
        levels = {n: mean for n, (mean, _) in floors.items()}
        noise = TraceNoise(trace, seed, preset.noise_floor_dbm, hw, levels)
    return RadioEnvironment(noise, hw, table, settings)


def radio_model(
    preset: RadioPreset,
    seed: int,
    settings: RadioSettings | None = None,
    symmetric: bool = True,
    links: LinkFile | None = None,
) -> RadioModel:
    """A model with the realism ``settings`` ask for (None: the textbook radio)."""
    env = None if settings is None else environment(preset, seed, settings, links)
    return RadioModel(preset, seed, symmetric, env)


def environment_of(model: RadioModel) -> RadioEnvironment | None:
    """The environment a model was built with (None: the textbook radio)."""
    env = model.env
    return env if isinstance(env, RadioEnvironment) else None
