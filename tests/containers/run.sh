#!/usr/bin/env bash
# Integration test in containers: docker-compose.yml for real.
#
#   bash tests/containers/run.sh                 # podman + podman-compose (root, Debian)
#   CONTAINER_ENGINE=docker bash tests/containers/run.sh
#
# Installs what it needs, builds the base images (cached) and the project's
# image, brings the secure stack up (throw-away secrets, router, broker, gateway,
# AWARE_FLEETS fleets), defines a group and a channel over MQTT with TLS from the
# host on the published broker port (the generated operator and viewer accounts
# and CA, read from the project's `secrets` volume), waits for records, tears everything down (also on failure) and prints
# `records received: N` last. Exits 1 when no record came, 77 when the kernel
# refuses containers. See docs/containers.md.
set -euo pipefail
source "$(dirname "$0")/lib.sh"

TIMEOUT="${AWAREMW_RECORDS_TIMEOUT:-120}"   # s to wait for records
WANT="${AWAREMW_RECORDS_WANT:-3}"           # stop waiting after this many
PROJECT="${AWAREMW_COMPOSE_PROJECT:-awaremw-it}"

check_kernel
install_tools
prepare_host
export AWARE_MQTT_PORT="${AWARE_MQTT_PORT:-$(free_port)}"
export AWARE_FLEETS="${AWARE_FLEETS:-2}"
export AWARE_START_AT=$(( $(date +%s) + 8 ))   # set again just before `up`
cd "$REPO"
t0=$SECONDS
N=0
UP=0
teardown() {
    local code=$?
    if [ "$N" -eq 0 ] && [ "$UP" = 1 ]; then
        log "no record: the services' last log lines"
        compose -p "$PROJECT" logs --tail 25 >&2 2>&1 || true
    fi
    compose_down "$REPO/docker-compose.yml" "$PROJECT"
    echo "records received: $N"
    if [ "$N" -eq 0 ] && [ "$code" -eq 0 ]; then code=1; fi
    exit "$code"
}
trap teardown EXIT
trap 'exit 130' INT TERM

build_base_images
build_project_image
compose_down "$REPO/docker-compose.yml" "$PROJECT"   # leftovers of an interrupted run
log "images ready in $((SECONDS - t0)) s"

export AWARE_START_AT=$(( $(date +%s) + 8 ))
log "up: keys, router, broker, gateway, $AWARE_FLEETS fleets (broker TLS on 127.0.0.1:$AWARE_MQTT_PORT)"
UP=1
# The services by name: podman-compose 1.0 ignores `profiles` (the `monitoring`
# profile's Prometheus is not started here).
compose -p "$PROJECT" up -d --no-build keys router broker gateway fleet > "$CACHE/$PROJECT-up.log" 2>&1 \
    || { cat "$CACHE/$PROJECT-up.log" >&2; die "compose up failed"; }
load_mqtt_secrets "$PROJECT" 90
wait_status online 90 || die "the gateway never said online on aware/gateway/status"
router_log="$(compose -p "$PROJECT" logs router 2>&1 || true)"   # no pipe: pipefail + grep -q
grep -q 'authenticated, access control by role' <<<"$router_log" \
    || die "the router does not run with the secrets (authentication, access control)"
# Each service's health check (/readyz of its --metrics port) passes.
for c in "${PROJECT}_router_1" "${PROJECT}_gateway_1" "${PROJECT}_fleet_1"; do
    [ "$ENGINE" = podman ] || c="${c//_/-}"   # Docker Compose v2 names PROJECT-SERVICE-N
    wait_healthy "$c" 60 || die "$c never became healthy (its /readyz)"
done
log "router, gateway and fleet healthy (/readyz)"
log "gateway online, router authenticating; defining group type 1 and channel 1 as the operator"
mqtt_pub operator aware/def/group/1 \
    '{"conditions": [{"attr": "temperature", "op": ">", "value": 15}]}'
mqtt_pub operator aware/def/channel/1 \
    '{"attr": "temperature", "group_type": 1, "group_id": "*", "period_s": 2.0, "agg": "avg"}'
records="$(mqtt_sub viewer 'aware/data/1/#' "$WANT" "$TIMEOUT")"
N="$(printf '%s' "$records" | grep -c '^aware/data/' || true)"
printf '%s\n' "$records" | head -3 >&2
log "stack ran $((SECONDS - t0)) s in all"
