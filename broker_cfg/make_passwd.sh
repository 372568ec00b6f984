#!/usr/bin/env bash
# Regenerate broker_cfg/passwd (Mosquitto password file, hashed).
#
#   broker_cfg/make_passwd.sh [OUT]                      the test accounts
#   AWARE_OPERATOR_PW=... AWARE_GATEWAY_PW=... AWARE_VIEWER_PW=... broker_cfg/make_passwd.sh
#
# The committed file holds the TEST accounts (operator/operator-pw,
# gateway/gateway-pw, viewer/viewer-pw): change them for any real deployment.
set -euo pipefail
out="${1:-$(dirname "$0")/passwd}"
mp="$(command -v mosquitto_passwd || echo /usr/bin/mosquitto_passwd)"
rm -f "$out"
touch "$out"
"$mp" -b "$out" operator "${AWARE_OPERATOR_PW:-operator-pw}"
"$mp" -b "$out" gateway "${AWARE_GATEWAY_PW:-gateway-pw}"
"$mp" -b "$out" viewer "${AWARE_VIEWER_PW:-viewer-pw}"
chmod 0640 "$out" 2>/dev/null || true
echo "wrote $out"
