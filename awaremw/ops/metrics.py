"""What a gateway and a fleet show on ``/metrics`` (docs/monitoring.md lists each
metric with its meaning), and when each is ready.

Both are prometheus-client *custom collectors*: nothing is counted twice, a
scrape reads the counters the process keeps anyway (the bridge's, the MQTT
side's, the fleet's snapshot) and renders them under Prometheus's conventions
(``awaremw_`` prefix, ``_total`` counters, base units: seconds, joules).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector, CollectorRegistry

from awaremw.ops.endpoint import OpsEndpoint, Readiness, metrics_password
from awaremw.runtime.fleet.figures import LAG_BUCKETS_S
from awaremw.runtime.fleet.stats import FleetSnapshot

# The fleet is ready while its timers are this late at most (p99 of the last window).
READY_LAG_S = 1.0


def _counter(name: str, doc: str, value: float, **labels: str) -> CounterMetricFamily:
    c = CounterMetricFamily(name, doc, labels=list(labels))
    c.add_metric(list(labels.values()), value)
    return c


def _gauge(name: str, doc: str, value: float) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, doc, value=value)


class GatewayMetrics(Collector):
    """The gateway's figures: records, definitions, refusals, transports.

    ``service`` is a :class:`~awaremw.gateway.service.GatewayService` (typed
    loosely: this module sits beside the gateway, not above it).
    """

    def __init__(self, service: Any) -> None:
        self.service = service

    def collect(self) -> Iterator[Metric]:
        svc = self.service
        st = svc.bridge.stats
        yield _counter(
            "awaremw_records_received",
            "Data records the gateway motes delivered, repeats included",
            st.records + st.duplicate_records,
        )
        yield _counter(
            "awaremw_records_delivered",
            "Data records handed to the IP side (MQTT and Zenoh), each once",
            st.records,
        )
        yield _counter(
            "awaremw_records_repeated",
            "Copies of a record already delivered (several roots, a retry whose ACK was lost)",
            st.duplicate_records,
        )
        defs = svc.bridge.definitions()
        held = GaugeMetricFamily(
            "awaremw_definitions", "Definitions the gateway holds, by kind", labels=["kind"]
        )
        version = GaugeMetricFamily(
            "awaremw_definition_version",
            "Version of each definition held",
            labels=["kind", "id"],
        )
        count = {"group": 0, "channel": 0}
        for rel, doc in defs.items():
            _, kind, ident = rel.split("/")
            count[kind] += 1
            version.add_metric([kind, ident], float(doc["version"]))
        for kind, n in count.items():
            held.add_metric([kind], n)
        yield held
        yield version
        errors = CounterMetricFamily(
            "awaremw_refusals", "Payloads the gateway refused, by error code", labels=["code"]
        )
        for code, n in sorted(st.refused_by_code.items()):
            errors.add_metric([code], n)
        yield errors
        yield _counter(
            "awaremw_definition_copies_stale",
            "Copies of a definition under an older version: ignored",
            st.stale,
        )
        yield _gauge(
            "awaremw_groups_live", "Groups the gateway hears report", len(svc.bridge.groups)
        )
        yield from self._transports()

    def _transports(self) -> Iterator[Metric]:
        svc = self.service
        mqtt = svc.mqtt
        yield _gauge(
            "awaremw_mqtt_connected",
            "1 while the gateway is connected to its broker and subscribed",
            1.0 if mqtt is not None and mqtt.subscribed.is_set() else 0.0,
        )
        if mqtt is not None:
            ms = mqtt.stats
            yield _counter("awaremw_mqtt_connects", "Connections made to the broker", ms.connects)
            yield _counter(
                "awaremw_mqtt_published", "Messages the broker acknowledged", ms.published
            )
            yield _counter(
                "awaremw_mqtt_dropped",
                "Messages dropped from the outage buffer (its bound)",
                ms.dropped,
            )
            yield _gauge("awaremw_mqtt_buffered", "Messages waiting for the broker", mqtt.backlog)
        hbn = svc.hbn
        yield _gauge(
            "awaremw_zenoh_connected",
            "1 while the gateway's Zenoh HBN API is open",
            0.0 if hbn is None else 1.0,
        )
        if hbn is not None:
            yield _counter("awaremw_zenoh_received", "Payloads put on aware/hbn/...", hbn.received)
            yield _counter("awaremw_zenoh_queries", "Gets answered", hbn.queries)


def gateway_readiness(service: Any) -> Readiness:
    """Ready once the gateway has subscribed (MQTT) or opened its Zenoh API, and
    holds its stored definitions (they are loaded before the transports open)."""
    if service.mqtt is not None and not service.mqtt.subscribed.is_set():
        return Readiness(False, f"not subscribed on {service.mqtt.settings.url} yet")
    if service.mqtt is None and service.hbn is None:
        return Readiness(False, "no transport open yet")
    return Readiness(True)


class FleetMetrics(Collector):
    """A fleet's figures, from its snapshot (one process, or a launcher's workers
    merged): motes on the air, frames by kind and fate, timer lag, records
    produced, radio energy by mote kind."""

    def __init__(self, snapshot: Callable[[], FleetSnapshot]) -> None:
        self.snapshot = snapshot

    def collect(self) -> Iterator[Metric]:
        s = self.snapshot()
        yield _gauge("awaremw_motes_alive", "Motes on the air", s.motes)
        yield _gauge("awaremw_emulated_seconds", "Emulated time of the fleet", s.t)
        yield _counter("awaremw_unicasts_acknowledged", "Unicasts acknowledged", s.unicast_ok)
        yield _counter(
            "awaremw_unicasts_failed", "Unicasts given up after the retries", s.unicast_failed
        )
        yield _counter("awaremw_frames_malformed", "Frames received but not decodable", s.malformed)
        f = s.figures
        if f is None:
            return
        sent = CounterMetricFamily(
            "awaremw_frames_sent",
            "Frames put on the air (retries included), by kind",
            labels=["kind"],
        )
        heard = CounterMetricFamily(
            "awaremw_frames_heard",
            "Receptions at each mote, by frame kind and fate (received, or lost: "
            "collision, path_loss, distance, mic, replay, duplicate)",
            labels=["kind", "fate"],
        )
        for kind, fate, n in f.frames:
            if fate == "sent":
                sent.add_metric([kind], n)
            else:
                heard.add_metric([kind, fate], n)
        yield sent
        yield heard
        buckets = [(_le(b), float(n)) for b, n in zip(LAG_BUCKETS_S, f.lag_buckets, strict=True)]
        buckets.append(("+Inf", float(f.lag_count)))
        yield HistogramMetricFamily(
            "awaremw_timer_lag_seconds",
            "How late the motes' timers fired (wall seconds)",
            buckets=buckets,
            sum_value=f.lag_sum_s,
        )
        yield _counter(
            "awaremw_records_produced", "Data records the leaders produced", f.records_produced
        )
        energy = CounterMetricFamily(
            "awaremw_radio_energy_joules",
            "Radio energy spent (airtime), by mote kind",
            labels=["kind"],
        )
        for kind, mj in f.energy_mj:
            energy.add_metric([kind], mj / 1000.0)
        yield energy


def _le(bound: float) -> str:
    return repr(float(bound))


def fleet_readiness(snapshot: Callable[[], FleetSnapshot]) -> Readiness:
    """Ready while the fleet's motes run (some on the air: every process has
    started) and its timers keep up (p99 lag of the last window within
    :data:`READY_LAG_S`)."""
    s = snapshot()
    if s.motes == 0:
        return Readiness(False, "no mote on the air yet")
    lag_s = s.lag_p99_ms / 1000.0
    if not math.isnan(lag_s) and lag_s > READY_LAG_S:
        return Readiness(False, f"timers {lag_s:.2f} s late (p99), more than {READY_LAG_S:g} s")
    return Readiness(True)


class RouterMetrics(Collector):
    """An embedded router's figures: that it runs, and who is linked to it
    (``peers``: a callable giving the Zenoh ids of linked peers/clients and routers)."""

    def __init__(self, linked: Callable[[], tuple[int, int]]) -> None:
        self.linked = linked

    def collect(self) -> Iterator[Metric]:
        yield _gauge("awaremw_router_up", "1 while the embedded Zenoh router runs", 1.0)
        peers, routers = self.linked()
        sessions = GaugeMetricFamily(
            "awaremw_router_sessions",
            "Zenoh sessions linked to the router, by their mode",
            labels=["mode"],
        )
        sessions.add_metric(["peer_or_client"], peers)
        sessions.add_metric(["router"], routers)
        yield sessions


def starting_endpoint(address: tuple[str, int]) -> OpsEndpoint:
    """An endpoint up before the gateway is: not ready ("starting") and no metrics,
    until :func:`show_gateway` gives it both."""
    return OpsEndpoint(
        *address, registry_of(), lambda: Readiness(False, "starting"), metrics_password()
    )


def show_gateway(
    ops: OpsEndpoint,
    service: Any,
    snapshot: Callable[[], FleetSnapshot],
    *,
    motes_ready: bool = False,
) -> None:
    """The gateway's figures and its motes' (``snapshot``) on ``ops``; ready with the
    gateway, and with ``motes_ready`` once the motes run too (:func:`fleet_readiness`)."""
    ops.registry.register(GatewayMetrics(service))
    ops.registry.register(FleetMetrics(snapshot))
    checks = [lambda: gateway_readiness(service)]
    if motes_ready:
        checks.append(lambda: fleet_readiness(snapshot))
    ops.ready = lambda: all_ready(*checks)


def all_ready(*checks: Callable[[], Readiness]) -> Readiness:
    """Ready when every check is (the first reason otherwise)."""
    for check in checks:
        r = check()
        if not r.ready:
            return r
    return Readiness(True)


def registry_of(*collectors: Collector) -> CollectorRegistry:
    """A registry of its own (not the process-wide default: tests run several)."""
    reg = CollectorRegistry(auto_describe=False)
    for c in collectors:
        reg.register(c)
    return reg
