#!/usr/bin/env bash
# Several hosts in containers (tests/containers/mesh.yml, docs/hosts.md): three
# sites on three networks, one Zenoh router each, the routers linked to each
# other over mutual TLS on a fourth network; a fleet part (stripe K of 3) behind
# each router, the gateway and the broker behind router a; secrets on everywhere.
#
# Three group types, one per site (motes whose x lies in one stripe only), and
# one channel over MQTT; then:
#   1. records come from motes behind every router (group types 1, 2, 3, each
#      record's leader in that site's stripe);
#   2. router c is killed (SIGKILL) and, after OUTAGE_S, started again: records
#      of sites a and b never stop (no gap above MAX_GAP_S), fleet c's process
#      is left alone and its part rejoins (site c's records come back);
#   3. nothing on aware/errors the whole time.
# The sites cannot reach each other except router to router (checked).
# Prints `records received: N` last. Same engines, caches and exit codes as
# run.sh.
set -euo pipefail
source "$(dirname "$0")/lib.sh"

TIMEOUT="${AWAREMW_RECORDS_TIMEOUT:-150}"   # s to wait for records of every site
OUTAGE_S="${AWAREMW_OUTAGE_S:-20}"          # s router c stays down
MAX_GAP_S="${AWAREMW_MAX_GAP_S:-12}"        # largest gap allowed in sites a and b (6 periods)
PROJECT="${AWAREMW_COMPOSE_PROJECT:-awaremw-mesh}"
FILE="$REPO/tests/containers/mesh.yml"
SITES=(a b c)

check_kernel
install_tools
prepare_host
export AWARE_MQTT_PORT="${AWARE_MQTT_PORT:-$(free_port)}"
export AWARE_DEPLOYMENT="${AWARE_DEPLOYMENT:-grid_small}"
export AWARE_START_AT=$(( $(date +%s) + 8 ))   # set again just before `up`
cd "$REPO"
t0=$SECONDS
N=0
UP=0
OK=0
SUB_PID=
RECORDS="$CACHE/$PROJECT-records.txt"
teardown() {
    local code=$?
    [ -z "$SUB_PID" ] || kill "$SUB_PID" 2>/dev/null || true
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

# Which site (1-3) runs each mote: the fleet's own partition of the deployment.
# (--workdir /: in /app the source tree would shadow the installed package, whose
# shipped deployments come from nodes/ through the wheel.)
PARTS="$("$ENGINE" run --rm --network none --workdir / --entrypoint python3 "$AWAREMW_IMAGE" -c '
import json, sys
from awaremw.runtime.deployment import load
from awaremw.runtime.partition import stripes
dep = load(sys.argv[1])
cut = stripes(dep, 3)
print(json.dumps({n.id: next(k for k, s in enumerate(cut, 1) if s(n)) for n in dep.nodes}))
' "$AWARE_DEPLOYMENT")" || die "cannot read the partition of $AWARE_DEPLOYMENT"

# Summary of the records file ("unix-time topic json" lines) as shell assignments:
# per group type T: n_T (records), new_T (records received after SINCE, a Unix
# time), bad_T (records whose leader is not in site T); errors (lines on aware/errors).
summary() { # [SINCE]
    python3 - "$RECORDS" "$PARTS" "${1:-0}" <<'EOF'
import json, sys
parts = {int(k): v for k, v in json.loads(sys.argv[2]).items()}
since = float(sys.argv[3])
n, new, bad, errors = {1: 0, 2: 0, 3: 0}, {1: 0, 2: 0, 3: 0}, {1: 0, 2: 0, 3: 0}, 0
for line in open(sys.argv[1], errors="replace"):
    fields = line.rstrip("\n").split(" ", 2)
    if len(fields) < 3:
        continue
    t, topic, payload = float(fields[0]), fields[1], fields[2]
    if topic.endswith("/errors"):
        errors += 1
        continue
    levels = topic.split("/")  # aware/data/<channel>/<type>/<group id>
    if len(levels) != 5 or levels[1] != "data" or not levels[3].isdigit():
        continue
    gt = int(levels[3])
    if gt not in n:
        continue
    n[gt] += 1
    new[gt] += t > since
    bad[gt] += parts.get(json.loads(payload).get("leader")) != gt
for gt in n:
    print(f"n_{gt}={n[gt]} new_{gt}={new[gt]} bad_{gt}={bad[gt]}")
print(f"errors={errors}")
EOF
}
# Records of group type T received in [FROM, TO]: "LARGEST-GAP COUNT", the gap in
# seconds counting the window's edges (no record at all: the whole window).
gap_of() { # T FROM TO
    python3 - "$RECORDS" "$@" <<'EOF'
import sys
path, gt, lo, hi = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
ts = []
for line in open(path, errors="replace"):
    fields = line.split(" ", 2)
    if len(fields) == 3 and fields[1].split("/")[3:4] == [gt] and lo <= float(fields[0]) <= hi:
        ts.append(float(fields[0]))
edges = [lo, *sorted(ts), hi]
print(f"{max(b - a for a, b in zip(edges, edges[1:])):.1f} {len(ts)}")
EOF
}
# Waits (up to TIMEOUT_S) until the summary since SINCE satisfies the shell test CONDITION.
wait_for() { # TIMEOUT_S SINCE CONDITION WHAT
    local end=$((SECONDS + $1))
    while :; do
        eval "$(summary "$2")"
        eval "$3" && return 0
        [ "$SECONDS" -lt "$end" ] || die "$4 (after $1 s)"
        sleep 1
    done
}
now() { date +%s.%N; }

export AWARE_START_AT=$(( $(date +%s) + 8 ))
log "up: routers a, b, c on sites a, b, c and the wan; broker + gateway (site a); fleets 1/3, 2/3, 3/3"
UP=1
compose -f "$FILE" -p "$PROJECT" up -d --no-build > "$CACHE/$PROJECT-up.log" 2>&1 \
    || { cat "$CACHE/$PROJECT-up.log" >&2; die "compose up failed"; }
load_mqtt_secrets "$PROJECT" 90
wait_status online 90 || die "the gateway never said online"
for s in "${SITES[@]}"; do
    router_log="$(compose -f "$FILE" -p "$PROJECT" logs "router-$s" 2>&1 || true)"   # no pipe: pipefail
    grep -q 'authenticated, access control by role' <<<"$router_log" \
        || die "router-$s does not run with the secrets (authentication, access control)"
done

# Each site reaches its own router and nothing of the other sites.
for s in "${SITES[@]}"; do
    can_connect "$PROJECT" "fleet-$s" "router-$s" 7447 || die "fleet-$s cannot reach router-$s"
    for o in "${SITES[@]}"; do
        [ "$o" = "$s" ] && continue
        for ip in $(addresses_of "$PROJECT" "router-$o") $(addresses_of "$PROJECT" "fleet-$o"); do
            ! can_connect "$PROJECT" "fleet-$s" "$ip" 7447 \
                || die "fleet-$s reaches site $o ($ip) directly: sites meet only router to router"
        done
    done
done
log "sites isolated from each other; each fleet reaches its own router"

# A background subscriber for the whole scenario: "unix-time topic payload" lines.
: > "$RECORDS"
mqtt_listen viewer 'aware/data/#' aware/errors > "$RECORDS" &
SUB_PID=$!
# One group type per site: the motes of one grid column each, inside one stripe
# (grid_small: x about 6, 30 and 54 m), and one channel over every group type.
mqtt_pub operator aware/def/group/1 '{"conditions": [{"attr": "x", "op": "<", "value": 12}]}'
mqtt_pub operator aware/def/group/2 \
    '{"conditions": [{"attr": "x", "op": ">", "value": 24}, {"attr": "x", "op": "<", "value": 36}]}'
mqtt_pub operator aware/def/group/3 '{"conditions": [{"attr": "x", "op": ">", "value": 48}]}'
mqtt_pub operator aware/def/channel/1 \
    '{"attr": "temperature", "group_type": "*", "group_id": "*", "period_s": 2.0, "agg": "avg"}'

wait_for "$TIMEOUT" 0 '[ "$n_1" -ge 1 ] && [ "$n_2" -ge 1 ] && [ "$n_3" -ge 1 ]' \
    "no records from motes behind every router"
eval "$(summary)"
N=$((n_1 + n_2 + n_3))
log "records from every site: a $n_1, b $n_2, c $n_3 ($((SECONDS - t0)) s in)"
[ "$bad_1" -eq 0 ] && [ "$bad_2" -eq 0 ] && [ "$bad_3" -eq 0 ] \
    || die "a record's leader is not in its site's stripe (bad: $bad_1 $bad_2 $bad_3)"

# Kill router c, leave it down OUTAGE_S, start it again.
router_c="$(container_of "$PROJECT" router-c)"
fleet_c="$(container_of "$PROJECT" fleet-c)"
fleet_c_started="$("$ENGINE" inspect -f '{{.State.StartedAt}}' "$fleet_c")"
t_kill="$(now)"
"$ENGINE" kill -s KILL "$router_c" >/dev/null || die "cannot kill router-c"
log "router-c killed; down for $OUTAGE_S s"
sleep "$OUTAGE_S"   # the outage itself (what is checked is the records meanwhile)
t_start="$(now)"
"$ENGINE" start "$router_c" >/dev/null || die "cannot start router-c again"
log "router-c started again"
wait_for 120 "$t_start" '[ "$new_3" -ge 1 ]' \
    "site c's records did not come back after router-c restarted"
t_back="$(now)"
log "site c rejoined: a record $(python3 -c 'import sys; print(f"{float(sys.argv[1]) - float(sys.argv[2]):.0f}")' "$t_back" "$t_start") s after the restart"
kill "$SUB_PID" 2>/dev/null || true
SUB_PID=

[ "$("$ENGINE" inspect -f '{{.State.StartedAt}}' "$fleet_c")" = "$fleet_c_started" ] \
    || die "fleet-c was restarted: the part should have rejoined on its own"
for gt in 1 2; do
    read -r gap count <<<"$(gap_of "$gt" "$t_kill" "$t_back")"
    log "site $( [ "$gt" = 1 ] && echo a || echo b) from the kill to site c's return: $count records, largest gap $gap s"
    [ "$count" -ge 1 ] || die "no record of group type $gt while router-c was down"
    python3 -c 'import sys; sys.exit(not float(sys.argv[1]) <= float(sys.argv[2]))' "$gap" "$MAX_GAP_S" \
        || die "group type $gt stopped delivering for $gap s (> $MAX_GAP_S s) around the router-c outage"
done
read -r _ count3 <<<"$(gap_of 3 "$t_kill" "$t_start")"
log "site c while its router was down: $count3 records"
eval "$(summary)"
N=$((n_1 + n_2 + n_3))
[ "$errors" -eq 0 ] || die "$errors message(s) on aware/errors: $(grep ' aware/errors ' "$RECORDS" | head -3)"
[ "$bad_1" -eq 0 ] && [ "$bad_2" -eq 0 ] && [ "$bad_3" -eq 0 ] \
    || die "a record's leader is not in its site's stripe (bad: $bad_1 $bad_2 $bad_3)"
OK=1
log "records a $n_1, b $n_2, c $n_3; nothing on aware/errors; scenario took $((SECONDS - t0)) s"
