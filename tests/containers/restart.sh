#!/usr/bin/env bash
# Restart scenario in containers (tests/containers/two-networks.yml, secure as
# docker-compose.yml): two fleets on two networks joined only through the Zenoh router; a group and a channel
# defined over MQTT; the gateway container restarted mid-run
# (`podman-compose restart gateway`). Passes when records resume after the
# restart, the definitions survive it (still retained, still applied: the
# channel's epochs go on instead of starting again), and the two fleets' networks
# cannot reach each other directly. Prints `records received: N` last.
# Same engines, caches and exit codes as run.sh.
set -euo pipefail
source "$(dirname "$0")/lib.sh"

TIMEOUT="${AWAREMW_RECORDS_TIMEOUT:-120}"
PROJECT="${AWAREMW_COMPOSE_PROJECT:-awaremw-restart}"
FILE="$REPO/tests/containers/two-networks.yml"

check_kernel
install_tools
prepare_host
export AWARE_MQTT_PORT="${AWARE_MQTT_PORT:-$(free_port)}"
export AWARE_START_AT=$(( $(date +%s) + 8 ))   # set again just before `up`
cd "$REPO"
t0=$SECONDS
N=0
UP=0
OK=0
teardown() {
    local code=$?
    if [ "$OK" != 1 ] && [ "$UP" = 1 ]; then
        log "failed: the services' last log lines"
        compose -f "$FILE" -p "$PROJECT" logs --tail 25 >&2 2>&1 || true
    fi
    compose_down "$FILE" "$PROJECT"
    echo "records received: $N"
    if [ "$OK" != 1 ] && [ "$code" -eq 0 ]; then code=1; fi
    exit "$code"
}
trap teardown EXIT
trap 'exit 130' INT TERM

build_base_images
build_project_image
compose_down "$FILE" "$PROJECT"   # leftovers of an interrupted run

# Max of a numeric field over "topic {json}" lines.
max_field() { # FIELD
    python3 -c 'import json, sys
vals = [json.loads(l.split(" ", 1)[1])[sys.argv[1]] for l in sys.stdin if l.startswith("aware/data/")]
print(max(vals) if vals else -1)' "$1"
}
export AWARE_START_AT=$(( $(date +%s) + 8 ))
log "up: router on three networks, broker + gateway (core), fleet-west (west), fleet-east (east)"
UP=1
compose -f "$FILE" -p "$PROJECT" up -d --no-build > "$CACHE/$PROJECT-up.log" 2>&1 \
    || { cat "$CACHE/$PROJECT-up.log" >&2; die "compose up failed"; }
load_mqtt_secrets "$PROJECT" 90
wait_status online 90 || die "the gateway never said online"
router_log="$(compose -f "$FILE" -p "$PROJECT" logs router 2>&1 || true)"   # no pipe: pipefail + grep -q
grep -q 'authenticated, access control by role' <<<"$router_log" \
    || die "the router does not run with the secrets (authentication, access control)"

can_connect "$PROJECT" fleet-west router 7447 && can_connect "$PROJECT" fleet-east router 7447 \
    || die "a fleet cannot reach the router"
for ip in $(addresses_of "$PROJECT" fleet-east); do
    ! can_connect "$PROJECT" fleet-west "$ip" 7448 \
        || die "fleet-west reaches fleet-east ($ip) directly: they must meet only at the router"
done
for ip in $(addresses_of "$PROJECT" fleet-west); do
    ! can_connect "$PROJECT" fleet-east "$ip" 7448 \
        || die "fleet-east reaches fleet-west ($ip) directly: they must meet only at the router"
done
log "fleets isolated from each other, both reach the router"

mqtt_pub operator aware/def/group/1 \
    '{"conditions": [{"attr": "temperature", "op": ">", "value": 15}]}'
mqtt_pub operator aware/def/channel/1 \
    '{"attr": "temperature", "group_type": 1, "group_id": "*", "period_s": 2.0, "agg": "avg"}'
before="$(mqtt_sub viewer 'aware/data/1/#' 3 "$TIMEOUT")"
n1="$(printf '%s\n' "$before" | grep -c '^aware/data/' || true)"
[ "$n1" -ge 1 ] || die "no record before the restart"
N=$n1
epoch1="$(printf '%s\n' "$before" | max_field epoch)"
count1="$(printf '%s\n' "$before" | max_field count)"
log "before the restart: $n1 records, last epoch $epoch1, up to $count1 motes per record"

log "restarting the gateway container"
started0="$("$ENGINE" inspect -f '{{.State.StartedAt}}' "$(container_of "$PROJECT" gateway)")"
compose -f "$FILE" -p "$PROJECT" restart gateway > "$CACHE/$PROJECT-restart.log" 2>&1 \
    || { cat "$CACHE/$PROJECT-restart.log" >&2; die "compose restart gateway failed"; }
started1="$("$ENGINE" inspect -f '{{.State.StartedAt}}' "$(container_of "$PROJECT" gateway)")"
[ "$started1" != "$started0" ] || die "the gateway container was not restarted"
wait_status online 90 || die "the gateway did not come back online"
after="$(mqtt_sub viewer 'aware/data/1/#' 3 "$TIMEOUT")"
n2="$(printf '%s\n' "$after" | grep -c '^aware/data/' || true)"
N=$((n1 + n2))
[ "$n2" -ge 1 ] || die "records did not resume after the gateway restarted"
epoch2="$(printf '%s\n' "$after" | max_field epoch)"
count2="$(printf '%s\n' "$after" | max_field count)"
log "after the restart: $n2 records, last epoch $epoch2, up to $count2 motes per record"
[ "$epoch2" -gt "$epoch1" ] \
    || die "epochs started again after the restart ($epoch2 <= $epoch1): the channel was redefined"
defs="$(mqtt_sub operator 'aware/def/#' 2 5)"
[ "$(printf '%s\n' "$defs" | grep -c '^aware/def/')" -eq 2 ] \
    || die "the retained definitions did not survive: $defs"
errors="$(mqtt_sub viewer aware/errors 1 2)"
[ -z "$errors" ] || die "the gateway reported: $errors"
printf '%s\n' "$after" | head -2 >&2
OK=1
log "records resumed, definitions kept; scenario took $((SECONDS - t0)) s"
