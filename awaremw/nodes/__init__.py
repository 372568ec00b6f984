"""The application layer: node kinds, and building a mote's core from a deployment.

:func:`build_core` is what every driver (virtual clock, fleet processes,
gateway) calls to turn a :class:`~awaremw.runtime.deployment.NodeSpec` into the
mote it runs: the kind's application (sensors over the world, commands) inside
an :class:`~awaremw.protocol.mote.AwareMote` configured by, from weakest to
strongest, the radio preset (MTU), the kind (a robot beacons, a gateway is a
collection root), the deployment's ``[middleware]`` overrides and the node
entry's own; with a secured radio (:class:`RadioSecurity`) the MTU is the
preset's payload MTU less the security overhead and the motes verify
dissemination items with the gateway's public key.

Nothing here reads a deployment file: :mod:`awaremw.runtime.deployment` has
checked every table (the overrides against MiddlewareConfig, the sensors' noise
overrides, the world), and the node kinds only read its typed value.
"""

from __future__ import annotations

import random
from dataclasses import replace
from typing import Any

from awaremw.nodes.kinds import (
    ALIASES,
    KINDS,
    CommandAction,
    KindInfo,
    NodeApp,
    SensorNoise,
    kind_info,
)
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.core import MoteCore
from awaremw.protocol.mote import AwareMote
from awaremw.protocol.signing import ItemSigner
from awaremw.radio.security import RadioSecurity
from awaremw.runtime.deployment import ENTRY_EXTRA_KEYS, Deployment, DeploymentError, NodeSpec
from awaremw.world.fields import World

__all__ = [
    "ALIASES",
    "KINDS",
    "CommandAction",
    "KindInfo",
    "KindsFactory",
    "NodeApp",
    "app_of",
    "build_app",
    "build_core",
    "config_for",
    "kind_names",
    "mote_rng",
    "world_of",
]

# Keys a node or grid entry may add to the deployment keys (docs/deployments.md;
# the parser refuses any other, runtime/deployment.py).
NODE_EXTRA_KEYS = ENTRY_EXTRA_KEYS


def kind_names() -> list[str]:
    """Every name a deployment may use as ``kind`` (for ``load(known_kinds=...)``)."""
    return [*KINDS, *ALIASES]


def world_of(deployment: Deployment) -> World:
    """The deployment's world (its ``[world]`` table, seeded by its seed)."""
    return deployment.world_model()


def _file(deployment: Deployment) -> str:
    return str(deployment.path) if deployment.path is not None else deployment.name


def config_for(
    spec: NodeSpec, deployment: Deployment, security: RadioSecurity | None = None
) -> MiddlewareConfig:
    """The middleware configuration of one mote (see the module docstring).

    With ``security`` the MTU is at most the secured payload MTU (a deployment
    may set a smaller one) and ``gateway_public_key`` is the security's."""
    info = kind_info(spec.kind)
    layers: dict[str, Any] = {"mtu": deployment.preset.mtu}
    layers.update(info.config)
    layers.update(deployment.middleware)
    layers.update(spec.middleware)
    if security is not None:
        layers["mtu"] = min(int(layers["mtu"]), security.payload_mtu(deployment.preset.mtu))
        layers["gateway_public_key"] = security.gateway_public_key
    return replace(_DEFAULT_CONFIG, **layers)


_DEFAULT_CONFIG = MiddlewareConfig()


def mote_rng(spec: NodeSpec, deployment: Deployment) -> random.Random:
    """The mote's own seeded generator: the same in every process."""
    return random.Random(f"awaremw:{deployment.seed}:{spec.id}")


def build_app(spec: NodeSpec, deployment: Deployment, world: World | None = None) -> NodeApp:
    """The node kind's application for ``spec``."""
    try:
        info = kind_info(spec.kind)
    except KeyError as e:
        raise DeploymentError(f"{_file(deployment)}: node {spec.id}: {e.args[0]}") from None
    noise = {sensor: SensorNoise(sigma) for sensor, sigma in spec.noise.items()}
    w = world if world is not None else deployment.world_model()
    return info.app(spec.id, spec.mobility().position, w, noise=noise)


def build_core(
    spec: NodeSpec,
    deployment: Deployment,
    world: World | None,
    security: RadioSecurity | None = None,
    signer: ItemSigner | None = None,
) -> MoteCore:
    """The :class:`AwareMote` for ``spec`` with its kind's application.

    ``world`` None builds it from the deployment (pass one shared world when
    building many motes). ``security``: a secured radio (see :func:`config_for`);
    ``signer``: the gateway's item signer, given to collection roots (gateway
    motes) only. Raises :class:`DeploymentError` for a bad entry.
    """
    app = build_app(spec, deployment, world)
    config = config_for(spec, deployment, security)
    mote = AwareMote(spec.id, app, config, mote_rng(spec, deployment))
    if signer is not None and config.is_root:
        mote.dissemination.signer = signer
    return mote


class KindsFactory:
    """The fleet's core factory for the node kinds: ``factory(spec, deployment)``
    is :func:`build_core` with one world shared by every mote it builds.

    The runtime below does not import the node kinds: callers (the CLI, the
    experiments) pass one of these to :class:`~awaremw.runtime.fleet.Fleet` and
    :class:`~awaremw.runtime.fleet.FleetLauncher`. Picklable, so a launcher can
    hand it to its worker processes. ``kinds`` are the names a control-plane
    ``add`` may use.

    ``security``: the radio is secured (the motes get the payload MTU and verify
    items with its gateway public key). ``signing_key``: the gateway's Ed25519
    private key (32 raw bytes), for the gateway process only: its collection
    roots sign the items they inject. A fleet's factory never holds it.
    """

    __slots__ = ("_signer", "_signing_key", "_world", "security")

    def __init__(
        self,
        world: World | None = None,
        *,
        security: RadioSecurity | None = None,
        signing_key: bytes | None = None,
    ) -> None:
        if signing_key is not None and security is None:
            raise ValueError("a signing key needs the radio security (the motes' public key)")
        self._world = world  # None: built from the first deployment seen
        self.security = security
        self._signing_key = signing_key
        self._signer: ItemSigner | None = None

    @property
    def kinds(self) -> frozenset[str]:
        return frozenset(kind_names())

    @property
    def signs(self) -> bool:
        """Whether the gateway motes this factory builds sign their items."""
        return self._signing_key is not None

    def __call__(self, spec: NodeSpec, deployment: Deployment) -> MoteCore:
        if self._world is None:
            self._world = deployment.world_model()
        if self._signing_key is not None and self._signer is None:
            from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

            self._signer = ItemSigner(Ed25519PrivateKey.from_private_bytes(self._signing_key))
        return build_core(spec, deployment, self._world, self.security, self._signer)

    def __repr__(self) -> str:
        return f"KindsFactory(secured={self.security is not None}, signs={self.signs})"

    def __getstate__(self) -> tuple[World | None, RadioSecurity | None, bytes | None]:
        return self._world, self.security, self._signing_key

    def __setstate__(self, state: tuple[World | None, RadioSecurity | None, bytes | None]) -> None:
        self._world, self.security, self._signing_key = state
        self._signer = None


def app_of(core: MoteCore) -> NodeApp | None:
    """The node kind's application inside a core built by :func:`build_core`."""
    if isinstance(core, AwareMote) and isinstance(core.ctx.app, NodeApp):
        return core.ctx.app
    return None
