#!/bin/sh
# Starts Mosquitto on the secrets of `awaremw keys init` (docker-compose.yml):
#
#   sh /mosquitto/config/start-secure.sh [SECRETS_DIR]     (default /secrets)
#
# Waits for SECRETS_DIR/secrets.json (written last by keys init), copies
# SECRETS_DIR/mqtt/{passwd,acl,server.crt,server.key} to /mosquitto/secrets for
# the mosquitto user (mode 0600: the broker drops root before it reads them) and
# runs mosquitto with /mosquitto/config/mosquitto.conf (plain 1883, TLS 8883).
set -eu
src="${1:-/secrets}"
dst=/mosquitto/secrets
i=0
while [ ! -s "$src/secrets.json" ]; do
    if [ "$i" -ge 600 ]; then
        echo "start-secure: no secrets in $src after 120 s (did the keys service run?)" >&2
        exit 2
    fi
    i=$((i + 1))
    sleep 0.2
done
mkdir -p "$dst"
chown mosquitto "$dst"
chmod 0700 "$dst"
for f in passwd acl server.crt server.key; do
    install -o mosquitto -m 0600 "$src/mqtt/$f" "$dst/$f"
done
exec /usr/sbin/mosquitto -c /mosquitto/config/mosquitto.conf
