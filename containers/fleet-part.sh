#!/bin/sh
# Entry point of the scalable `fleet` service (docker-compose.yml): each replica
# claims one stripe K of N of the deployment (N = AWARE_FLEETS) in a volume the
# replicas share, then runs `awaremw fleet ARGS... --part K/N`. A claim belongs to
# the container's hostname, so a restarted replica gets its own stripe back; the
# claims of one run live under its AWARE_START_AT, so a new run starts afresh.
set -eu
n="${AWARE_FLEETS:?AWARE_FLEETS (the number of fleet replicas) is not set}"
dir="/claims/${AWARE_START_AT:-run}"
me="$(hostname)"
mkdir -p "$dir"
part=""
k=1
while [ "$k" -le "$n" ]; do
    if [ "$(cat "$dir/$k/owner" 2>/dev/null || true)" = "$me" ]; then part=$k; break; fi
    k=$((k + 1))
done
k=1
while [ -z "$part" ] && [ "$k" -le "$n" ]; do
    if mkdir "$dir/$k" 2>/dev/null; then echo "$me" > "$dir/$k/owner"; part=$k; fi
    k=$((k + 1))
done
if [ -z "$part" ]; then
    echo "fleet-part: all $n stripes are taken: more replicas than AWARE_FLEETS=$n?" >&2
    exit 2
fi
echo "fleet-part: $me runs stripe $part/$n" >&2
exec awaremw fleet "$@" --part "$part/$n"
