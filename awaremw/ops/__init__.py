"""Operating awaremw as a service: the metrics, health and readiness endpoint
(:mod:`awaremw.ops.endpoint`), what the gateway and the fleet show there
(:mod:`awaremw.ops.metrics`), structured logs (:mod:`awaremw.ops.logs`).
docs/monitoring.md is the operator's page."""
