#!/bin/sh
# Entry point wrapper for the secure compose setup (docker-compose.yml):
#
#   awaremw-with-secrets DIR COMMAND [ARGS...]
#
# Waits (up to AWARE_SECRETS_WAIT_S, default 120 s) until the one-shot `keys`
# service has written DIR (`awaremw keys init DIR --exist-ok`; its manifest
# DIR/secrets.json is written last), then runs COMMAND ARGS. With
# AWARE_MQTT_ACCOUNT=USER and AWARE_MQTT_BROKER=HOST:PORT it appends
# `--mqtt mqtts://USER@HOST:PORT --mqtt-password-file FILE --ca-file
# DIR/mqtt/ca.crt`, FILE a new 0600 file under ${TMPDIR:-/tmp} holding USER's
# password from DIR/mqtt/accounts.json: the password is never in an argument
# list (`ps`, /proc/PID/cmdline).
set -eu
dir="${1:?usage: awaremw-with-secrets DIR COMMAND [ARGS...]}"
shift
wait_s="${AWARE_SECRETS_WAIT_S:-120}"
i=0
while [ ! -s "$dir/secrets.json" ]; do
    if [ "$i" -ge $((wait_s * 5)) ]; then
        echo "awaremw-with-secrets: no secrets in $dir after $wait_s s (did the keys service run?)" >&2
        exit 2
    fi
    i=$((i + 1))
    sleep 0.2
done
if [ -n "${AWARE_MQTT_ACCOUNT:-}" ]; then
    broker="${AWARE_MQTT_BROKER:?set AWARE_MQTT_BROKER=HOST:PORT}"
    pwfile="$(mktemp "${TMPDIR:-/tmp}/awaremw-mqtt-password.XXXXXX")"  # mode 0600
    python3 -c 'import json, sys; open(sys.argv[3], "w").write(json.load(open(sys.argv[1]))[sys.argv[2]] + "\n")' \
        "$dir/mqtt/accounts.json" "$AWARE_MQTT_ACCOUNT" "$pwfile"
    set -- "$@" --mqtt "mqtts://$AWARE_MQTT_ACCOUNT@$broker" --mqtt-password-file "$pwfile" \
        --ca-file "$dir/mqtt/ca.crt"
fi
exec "$@"
