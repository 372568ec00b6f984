# Shared by tests/containers/run.sh and restart.sh (sourced, not run).
#
# Engine: CONTAINER_ENGINE=podman (default; with podman-compose) or docker (with
# `docker compose` or docker-compose). Base images: built locally from Debian
# bookworm with debootstrap (no container registry is reachable on our machines)
# and cached; AWAREMW_UPSTREAM_IMAGES=1 uses python:3.11-slim and
# eclipse-mosquitto:2 from a registry instead. Caches live in AWAREMW_CONTAINER_CACHE
# (default /var/cache/awaremw-containers), never in the checkout.
#
# Exit status 77 means "this kernel refuses containers" (the caller may skip).

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
ENGINE="${CONTAINER_ENGINE:-podman}"
CACHE="${AWAREMW_CONTAINER_CACHE:-/var/cache/awaremw-containers}"
DEBIAN_MIRROR="${AWAREMW_DEBIAN_MIRROR:-}"
BASE_IMAGE=localhost/awaremw-debian:bookworm
export AWAREMW_IMAGE="${AWAREMW_IMAGE:-localhost/awaremw:latest}"
if [ "${AWAREMW_UPSTREAM_IMAGES:-0}" = 1 ]; then
    export PYTHON_IMAGE="${PYTHON_IMAGE:-python:3.11-slim}"
    export MOSQUITTO_IMAGE="${MOSQUITTO_IMAGE:-eclipse-mosquitto:2}"
else
    export PYTHON_IMAGE=localhost/awaremw-python:bookworm
    export MOSQUITTO_IMAGE=localhost/awaremw-mosquitto:bookworm
fi
BUILD_VOLUMES=()

log() { echo "[containers $(date +%T)] $*" >&2; }
die() { echo "[containers] FAIL: $*" >&2; exit 1; }

compose() {
    if [ "$ENGINE" = podman ]; then
        podman-compose --no-ansi "$@"
    elif docker compose version >/dev/null 2>&1; then
        docker compose "$@"
    else
        docker-compose "$@"
    fi
}

# The health check of container NAME, run now (exit 0: healthy). podman 4 without
# systemd does not run health checks by itself, so `podman healthcheck run` asks;
# Docker runs them: its last status is read.
healthy() { # CONTAINER
    if [ "$ENGINE" = podman ]; then
        podman healthcheck run "$1" >/dev/null 2>&1
    else
        [ "$(docker inspect --format '{{.State.Health.Status}}' "$1" 2>/dev/null)" = healthy ]
    fi
}

# Waits until container NAME is healthy, at most S seconds.
wait_healthy() { # CONTAINER S
    local i
    for ((i = 0; i < $2 * 2; i++)); do
        healthy "$1" && return 0
        sleep 0.5
    done
    return 1
}

# Stops and removes project PROJECT of compose FILE: containers, volumes and
# networks (podman-compose 1.0 leaves networks, which would keep stale settings).
compose_down() { # FILE PROJECT
    compose -f "$1" -p "$2" down -v >/dev/null 2>&1 || true
    rm -f "$CACHE/$2-ca.crt" "$CACHE/$2-accounts.json"   # copies of the throw-away secrets
    local nets
    nets="$("$ENGINE" network ls -q --filter "label=com.docker.compose.project=$2" 2>/dev/null || true)"
    [ -z "$nets" ] || "$ENGINE" network rm $nets >/dev/null 2>&1 || true
}

# Installs the engine and the tools the tests use (Debian packages), once.
install_tools() {
    local pkgs=()
    command -v mosquitto_sub >/dev/null 2>&1 || pkgs+=(mosquitto-clients)
    if [ "${AWAREMW_UPSTREAM_IMAGES:-0}" != 1 ]; then
        command -v debootstrap >/dev/null 2>&1 || [ -x /usr/sbin/debootstrap ] || pkgs+=(debootstrap)
    fi
    if [ "$ENGINE" = podman ]; then
        command -v podman >/dev/null 2>&1 || pkgs+=(podman)
        command -v podman-compose >/dev/null 2>&1 || pkgs+=(podman-compose)
    else
        command -v docker >/dev/null 2>&1 || die "CONTAINER_ENGINE=docker but no docker command"
        docker info >/dev/null 2>&1 || die "CONTAINER_ENGINE=docker but the Docker daemon does not answer"
    fi
    if [ "${#pkgs[@]}" -gt 0 ]; then
        [ "$(id -u)" = 0 ] || die "needs root to install ${pkgs[*]}"
        log "installing ${pkgs[*]}"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq
        apt-get install -y -qq "${pkgs[@]}" >/dev/null
    fi
    export PATH="/usr/sbin:/sbin:$PATH"
}

# Host settings podman's crun needs on our kernels (verified on the CI machine).
prepare_host() {
    [ "$ENGINE" = podman ] || return 0
    # Hybrid cgroup mode: crun wants the v1 hugetlb controller mounted too.
    if [ -d /sys/fs/cgroup/unified ] && [ ! -d /sys/fs/cgroup/hugetlb ] \
        && grep -qw hugetlb /proc/cgroups; then
        mkdir -p /sys/fs/cgroup/hugetlb 2>/dev/null || true
        mount -t cgroup -o hugetlb cgroup /sys/fs/cgroup/hugetlb 2>/dev/null \
            || log "could not mount the hugetlb cgroup (containers may fail to start)"
    fi
    # Limits a container may ask for: no higher than the host's hard limits.
    local conf=/etc/containers/containers.conf.d/awaremw.conf hard
    hard="$(ulimit -Hn)"
    if [ ! -f "$conf" ] || ! grep -q "nofile=$hard:$hard" "$conf"; then
        mkdir -p "$(dirname "$conf")"
        printf '# written by awaremw tests/containers/lib.sh\n[containers]\ndefault_ulimits = ["nofile=%s:%s", "nproc=4096:4096"]\n' \
            "$hard" "$hard" > "$conf"
    fi
}

# Does the kernel let us make containers at all (namespaces)? 77 when not.
check_kernel() {
    if ! unshare --mount --uts --ipc --net --pid --fork true 2>/dev/null; then
        echo "[containers] SKIP: this kernel refuses containers (namespaces unavailable)" >&2
        exit 77
    fi
}

_mirror() {
    if [ -n "$DEBIAN_MIRROR" ]; then echo "$DEBIAN_MIRROR"; return; fi
    local m
    m="$(grep -rhoE '^(deb|URIs:)[^#]*https?://[^ ]+/debian/?( |$)' /etc/apt/sources.list /etc/apt/sources.list.d/ 2>/dev/null \
        | grep -oE 'https?://[^ ]+/debian/?' | head -1)"
    echo "${m:-http://deb.debian.org/debian}"
}

# The host's pip settings as one [global] section (config files and PIP_* env).
_pip_conf() {
    echo "[global]"
    python3 -m pip config list 2>/dev/null | sed -nE "s/^(:env:|global|user|site)\.([a-z-]+)='(.*)'$/\2 = \3/p" \
        | awk -F' = ' '!seen[$1]++' | grep -vE '^(disable-pip-version-check|no-cache-dir) ' || true
}

_image_exists() { "$ENGINE" image inspect "$1" >/dev/null 2>&1; }

# Base images (cached): debootstrap'ed bookworm, then the Python and Mosquitto stand-ins.
build_base_images() {
    [ "${AWAREMW_UPSTREAM_IMAGES:-0}" = 1 ] && return 0
    mkdir -p "$CACHE"
    if ! _image_exists "$BASE_IMAGE"; then
        if [ ! -f "$CACHE/rootfs/.complete" ]; then
            log "debootstrap bookworm into $CACHE/rootfs ($(_mirror))"
            rm -rf "$CACHE/rootfs"
            debootstrap --variant=minbase --include=ca-certificates,python3,python3-venv,mosquitto \
                bookworm "$CACHE/rootfs" "$(_mirror)" > "$CACHE/debootstrap.log" 2>&1 \
                || { tail -20 "$CACHE/debootstrap.log" >&2; die "debootstrap failed"; }
            rm -rf "$CACHE/rootfs/var/cache/apt/archives/"*.deb
            touch "$CACHE/rootfs/.complete"
        fi
        log "importing $BASE_IMAGE"
        tar -C "$CACHE/rootfs" --exclude=./.complete -c . \
            | "$ENGINE" import --change 'CMD ["/bin/bash"]' - "$BASE_IMAGE" >/dev/null
        rm -rf "$CACHE/rootfs"   # the image is the cache from now on
    fi
    local ctx="$CACHE/python-context"
    rm -rf "$ctx" && mkdir -p "$ctx/ca"
    cp -L /usr/local/share/ca-certificates/*.crt "$ctx/ca/" 2>/dev/null || true
    _pip_conf > "$ctx/pip.conf"
    # pip settings that name local folders (find-links, file:// indexes) work
    # inside the build when those folders are mounted (podman only).
    local d
    for d in $(grep -oE '(file://)?/[^ ]+' "$ctx/pip.conf" | sed 's#^file://##' | grep -v '^/etc/ssl/'); do
        [ "$(basename "$d")" = simple ] && d="$(dirname "$d")"   # index pages link to ../files
        while [ ! -d "$d" ] && [ "$d" != / ]; do d="$(dirname "$d")"; done
        [ "$d" != / ] && [ "$ENGINE" = podman ] && BUILD_VOLUMES+=("--volume=$d:$d:ro")
    done
    if [ "$ENGINE" != podman ]; then
        grep -vE '(find-links|extra-index-url) = .*(file://)?/' "$ctx/pip.conf" > "$ctx/pip.conf.new" || true
        mv "$ctx/pip.conf.new" "$ctx/pip.conf"
    fi
    # Rebuilt when the certificates or pip settings change (layer cache otherwise).
    "$ENGINE" build -q --build-arg "BASE_IMAGE=$BASE_IMAGE" -t "$PYTHON_IMAGE" \
        -f "$REPO/tests/containers/base/python.Containerfile" "$ctx" >/dev/null \
        || die "building $PYTHON_IMAGE failed"
    _image_exists "$MOSQUITTO_IMAGE" || "$ENGINE" build -q --build-arg "BASE_IMAGE=$BASE_IMAGE" \
        -t "$MOSQUITTO_IMAGE" -f "$REPO/tests/containers/base/mosquitto.Containerfile" "$ctx" >/dev/null \
        || die "building $MOSQUITTO_IMAGE failed"
}

# The project's image from its Dockerfile (layer cache: warm runs take seconds).
build_project_image() {
    log "building $AWAREMW_IMAGE from Dockerfile"
    "$ENGINE" build -q "${BUILD_VOLUMES[@]}" --build-arg "PYTHON_IMAGE=$PYTHON_IMAGE" \
        -t "$AWAREMW_IMAGE" -f "$REPO/Dockerfile" "$REPO" >/dev/null \
        || die "building $AWAREMW_IMAGE failed"
}

# The container of SERVICE in compose project PROJECT (first replica).
container_of() { # PROJECT SERVICE
    "$ENGINE" ps -q --filter "label=com.docker.compose.project=$1" \
        --filter "label=com.docker.compose.service=$2" | head -1
}
# Can SERVICE open a TCP connection to HOST:PORT? (exit status of the attempt)
can_connect() { # PROJECT SERVICE HOST PORT
    "$ENGINE" exec "$(container_of "$1" "$2")" python3 -c 'import socket, sys
socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=3).close()' "$3" "$4" >/dev/null 2>&1
}
# The IP addresses of SERVICE's container, space-separated.
addresses_of() { # PROJECT SERVICE
    "$ENGINE" inspect -f '{{range .NetworkSettings.Networks}}{{.IPAddress}} {{end}}' \
        "$(container_of "$1" "$2")"
}

# A free TCP port on the host's loopback.
free_port() {
    python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# The secrets the compose project's one-shot `keys` service wrote in its
# `secrets` volume: sets MQTT_CA (a copy of mqtt/ca.crt) and MQTT_ACCOUNTS (a copy
# of mqtt/accounts.json), both 0600 under CACHE. Waits up to TIMEOUT_S for them.
load_mqtt_secrets() { # PROJECT TIMEOUT_S
    local vol="$1_secrets" end=$((SECONDS + $2)) mp
    MQTT_CA="$CACHE/$1-ca.crt"
    MQTT_ACCOUNTS="$CACHE/$1-accounts.json"
    rm -f "$MQTT_CA" "$MQTT_ACCOUNTS"
    (umask 077; while :; do
        mp="$("$ENGINE" volume inspect -f '{{.Mountpoint}}' "$vol" 2>/dev/null || true)"
        if [ -n "$mp" ] && [ -s "$mp/secrets.json" ]; then
            cp "$mp/mqtt/ca.crt" "$MQTT_CA" && cp "$mp/mqtt/accounts.json" "$MQTT_ACCOUNTS" && break
        elif [ -n "$mp" ] && [ ! -d "$mp" ]; then
            # the volume lives elsewhere (a remote Docker engine): read it through a container
            "$ENGINE" run --rm -v "$vol:/s:ro" --entrypoint cat "$AWAREMW_IMAGE" /s/mqtt/ca.crt \
                > "$MQTT_CA" 2>/dev/null \
                && "$ENGINE" run --rm -v "$vol:/s:ro" --entrypoint cat "$AWAREMW_IMAGE" \
                    /s/mqtt/accounts.json > "$MQTT_ACCOUNTS" 2>/dev/null \
                && [ -s "$MQTT_ACCOUNTS" ] && break
        fi
        [ "$SECONDS" -lt "$end" ] || exit 1
        sleep 1
    done) || die "no secrets in volume $vol after $2 s (the keys service's log: compose logs keys)"
}
# The password of MQTT account USER (operator, gateway, viewer) from MQTT_ACCOUNTS.
mqtt_password() { # USER
    python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])' \
        "$MQTT_ACCOUNTS" "$1"
}

# mosquitto_sub/pub on the published broker port: TLS, verified with the
# generated CA (the certificate names 127.0.0.1), the generated accounts.
_mqtt_args() { # USER
    echo -h 127.0.0.1 -p "$AWARE_MQTT_PORT" --cafile "$MQTT_CA" -u "$1"
}
mqtt_pub() { # USER TOPIC PAYLOAD (retained)
    mosquitto_pub $(_mqtt_args "$1") -P "$(mqtt_password "$1")" -q 1 -r -t "$2" -m "$3"
}
mqtt_sub() { # USER TOPIC COUNT TIMEOUT_S: prints "topic payload" lines
    mosquitto_sub $(_mqtt_args "$1") -P "$(mqtt_password "$1")" -q 1 -v \
        -t "$2" -C "$3" -W "$4" 2>/dev/null || true
}
# Subscribes until killed, one "unix-time topic payload" line per message (run it
# in the background: it execs mosquitto_sub, so $! is the subscriber itself).
mqtt_listen() { # USER TOPIC...
    local user="$1" args=() t
    shift
    for t in "$@"; do args+=(-t "$t"); done
    exec mosquitto_sub $(_mqtt_args "$user") -P "$(mqtt_password "$user")" -q 1 \
        -F '%U %t %p' "${args[@]}" 2>/dev/null
}
# Waits until the gateway's retained status is VALUE (online/offline).
wait_status() { # VALUE TIMEOUT_S
    local end=$((SECONDS + $2)) got pw
    pw="$(mqtt_password viewer)"
    while :; do
        got="$(mosquitto_sub $(_mqtt_args viewer) -P "$pw" \
            -t aware/gateway/status -C 1 -W 3 2>/dev/null || true)"
        [ "$got" = "$1" ] && return 0
        [ "$SECONDS" -lt "$end" ] || return 1
        sleep 1
    done
}
