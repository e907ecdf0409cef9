#!/usr/bin/env bash
# make image-check: build the Dockerfile and run the image as a user would.
#
#   1. a container engine: the one `docker info` reaches, else a private dockerd (installed
#      from Debian's packages when missing; root), stopped by its PID at the end;
#   2. the base image: python:3.11-slim-bookworm, or, when no image registry answers, a local
#      stand-in (debootstrap bookworm + `docker import` + Debian's python3.11);
#   3. torch's CPU wheel: its index, or, when unreachable, the wheel that pip finds on this
#      machine, served on 127.0.0.1 for the build;
#   4. builds the image (and its render variant), then runs it: --help; `train --max-seconds
#      60` to reward >= 90, exit 0; `docker stop` of a live run (graceful, a checkpoint);
#      another uid; the one-line errors of a root-owned results dir, of xvfb-run in the
#      headless image and of an unreachable torch index;
#   5. stops everything it started; images and the stand-in stay cached in IMAGE_CHECK_DIR.
#
# Machine-specific workarounds (this machine's CA certificates, the local wheel index) live
# here, never in the Dockerfile. Environment: IMAGE_CHECK_DIR (cache and logs),
# IMAGE_CHECK_RENDER=0 (skip the render variant), DEBIAN_MIRROR (for debootstrap).
set -euo pipefail
cd "$(dirname "$0")/.."

WORK=${IMAGE_CHECK_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/unity-rollout-image-check}
IMAGE=unity-rollout:check
STANDIN=local/python:3.11-slim-bookworm-standin
HOST_PYTHON=$(command -v python3.11 || command -v python3)
mkdir -p "$WORK"
LOGS=$WORK/logs/$(date +%Y%m%d-%H%M%S)
mkdir -p "$LOGS"
STARTED=$(date +%s)

pids=()        # processes this script started, stopped in reverse order
containers=()  # named containers, removed at exit
cleanup() {
    local status=$? pid
    for name in "${containers[@]}"; do docker rm -f "$name" >/dev/null 2>&1 || true; done
    for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
        pid=${pids[i]}
        kill "$pid" 2>/dev/null || true
        for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
        kill -9 "$pid" 2>/dev/null || true
    done
    wait 2>/dev/null || true
    if ((status == 0)); then
        echo "image-check: passed in $(($(date +%s) - STARTED)) s (logs: $LOGS)"
    else
        echo "image-check: FAILED (logs: $LOGS)" >&2
    fi
}
trap cleanup EXIT
trap 'exit 143' TERM INT  # so that the EXIT trap stops what was started

step() { printf '== %s (%s s)\n' "$*" "$(($(date +%s) - STARTED))"; }
fail() {
    echo "image-check: $*" >&2
    exit 1
}

# ---- 1. the engine
start_engine() {
    if docker info >/dev/null 2>&1; then
        step "engine: the running daemon"
        return
    fi
    ((EUID == 0)) || fail "no container engine answers 'docker info', and starting one needs root"
    if ! command -v dockerd >/dev/null || ! command -v docker >/dev/null; then
        command -v apt-get >/dev/null || fail "no container engine: install Docker"
        step "engine: installing Debian's docker.io"
        apt-get update -qq >"$LOGS/apt.log" 2>&1
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
            docker.io iptables debootstrap >>"$LOGS/apt.log" 2>&1 || fail "apt-get: see $LOGS/apt.log"
    fi
    step "engine: a private dockerd (no bridge, no iptables rules on the host)"
    local socket=$WORK/docker.sock
    dockerd --data-root "$WORK/docker" --exec-root "$WORK/run" --pidfile "$WORK/dockerd.pid" \
        -H "unix://$socket" --iptables=false --ip-forward=false --bridge=none \
        >"$LOGS/dockerd.log" 2>&1 &
    pids+=($!)
    export DOCKER_HOST=unix://$socket
    for _ in $(seq 120); do
        docker info >/dev/null 2>&1 && return
        kill -0 "${pids[-1]}" 2>/dev/null || fail "dockerd exited: see $LOGS/dockerd.log"
        sleep 0.5
    done
    fail "dockerd did not answer in 60 s: see $LOGS/dockerd.log"
}

# ---- 2. the base image
debian_mirror() {
    [[ -n "${DEBIAN_MIRROR:-}" ]] && { echo "$DEBIAN_MIRROR"; return; }
    cat /etc/apt/sources.list /etc/apt/sources.list.d/* 2>/dev/null |
        grep -oE '(deb |URIs: )https?://[^ ]+' | grep -v security | head -1 | awk '{print $2}' || true
}

stand_in_base() {
    if ! docker image inspect local/debian:bookworm-minbase >/dev/null 2>&1; then
        debootstrap_base
    fi
    local context=$WORK/standin
    rm -rf "$context"
    mkdir -p "$context/ca"
    # This machine's extra CA certificates (a TLS-intercepting proxy): the stand-in trusts
    # them, as the host does; the product's Dockerfile never sees them.
    cp /usr/local/share/ca-certificates/*.crt "$context/ca/" 2>/dev/null || true
    # As Debian's official images: apt keeps no package caches in image layers.
    cat >"$context/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
EOF
    cat >"$context/Dockerfile" <<'EOF'
FROM local/debian:bookworm-minbase
COPY docker-clean /etc/apt/apt.conf.d/docker-clean
COPY ca/ /usr/local/share/ca-certificates/
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3.11 python3.11-venv libpython3.11-dev \
        ca-certificates netbase \
    && update-ca-certificates \
    && ln -s /usr/bin/python3.11 /usr/local/bin/python3 \
    && ln -s /usr/bin/python3.11 /usr/local/bin/python \
    && printf '[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n' > /etc/pip.conf \
    && rm -rf /var/lib/apt/lists/*
ENV LANG=C.UTF-8
CMD ["python3"]
EOF
    docker build --network=host -t "$STANDIN" "$context" >"$LOGS/standin.log" 2>&1 ||
        fail "stand-in base: see $LOGS/standin.log"
    step "base: no image registry; the stand-in $STANDIN"
    BASE=$STANDIN
}

debootstrap_base() {  # local/debian:bookworm-minbase, from Debian's packages
    local mirror rootfs=$WORK/rootfs
    mirror=$(debian_mirror)
    [[ -n "$mirror" ]] || fail "no Debian mirror in /etc/apt: set DEBIAN_MIRROR"
    command -v debootstrap >/dev/null || {
        apt-get update -qq >"$LOGS/apt.log" 2>&1
        apt-get install -y -qq --no-install-recommends debootstrap >>"$LOGS/apt.log" 2>&1
    }
    step "base: no image registry; debootstrap bookworm ($mirror)"
    rm -rf "$rootfs"
    debootstrap --variant=minbase bookworm "$rootfs" "$mirror" >"$LOGS/debootstrap.log" 2>&1 ||
        fail "debootstrap: see $LOGS/debootstrap.log"
    local security=${mirror%/debian}/debian-security
    cat >"$rootfs/etc/apt/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: $mirror
Suites: bookworm bookworm-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: $security
Suites: bookworm-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
    rm -f "$rootfs/etc/apt/sources.list"
    rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/*.bin "$rootfs"/var/cache/apt/archives/*.deb
    tar -C "$rootfs" --numeric-owner -c . |
        docker import --change 'CMD ["bash"]' - local/debian:bookworm-minbase >/dev/null
    rm -rf "$rootfs"
}

pick_base() {
    BASE=python:3.11-slim-bookworm
    if docker image inspect "$BASE" >/dev/null 2>&1; then
        step "base: $BASE (present)"
    elif timeout 120 docker pull -q "$BASE" >"$LOGS/pull.log" 2>&1; then
        step "base: $BASE (pulled)"
    else
        stand_in_base
    fi
}

# ---- 3. torch's CPU wheel
torch_index() {
    INDEX=https://download.pytorch.org/whl/cpu
    if "$HOST_PYTHON" scripts/check-torch-index.py "$INDEX" >"$LOGS/torch-index.log" 2>&1; then
        step "torch: its CPU index answers"
        return
    fi
    local wheels=$WORK/whl/cpu/torch version port
    version=$(sed -n 's/^torch==//p' constraints.txt)
    if ! compgen -G "$wheels/torch-$version+cpu-*.whl" >/dev/null; then
        mkdir -p "$wheels"
        "$HOST_PYTHON" -m pip download -q --no-deps --only-binary=:all: --dest "$wheels" \
            "torch==$version" >>"$LOGS/torch-index.log" 2>&1 || true
    fi
    compgen -G "$wheels/torch-$version+cpu-*.whl" >/dev/null ||
        fail "torch's CPU index is unreachable and pip here finds no torch-$version+cpu wheel"
    port=$("$HOST_PYTHON" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
    "$HOST_PYTHON" -m http.server "$port" --bind 127.0.0.1 --directory "$WORK/whl" \
        >"$LOGS/wheel-server.log" 2>&1 &
    pids+=($!)
    INDEX=http://127.0.0.1:$port/cpu  # plain http: pip accepts it from loopback only
    for _ in $(seq 50); do
        "$HOST_PYTHON" scripts/check-torch-index.py "$INDEX" >/dev/null 2>&1 && break
        sleep 0.2
    done
    step "torch: its CPU index is unreachable; this machine's wheel served at $INDEX"
}

# ---- 4. build and run
build() {  # build TAG LOG [--build-arg ...]
    local tag=$1 log=$2
    shift 2
    local t0=$SECONDS
    docker build --network=host -t "$tag" --build-arg "BASE=$BASE" \
        --build-arg "PIP_EXTRA_INDEX_URL=$INDEX" "$@" . >"$LOGS/$log" 2>&1 ||
        fail "docker build $tag: see $LOGS/$log"
    step "built $tag in $((SECONDS - t0)) s: $(size "$tag")"
}

size() { docker image inspect -f '{{.Size}}' "$1" | awk '{printf "%.2f GB", $1 / 1e9}'; }

results_dir() {  # results_dir NAME OWNER MODE: a fresh host directory to mount
    local dir=$WORK/results/$1
    rm -rf "$dir"
    mkdir -p "$dir"
    chown "$2" "$dir"
    chmod "$3" "$dir"
    echo "$dir"
}

expect() {  # expect LOG PATTERN WHAT
    grep -qE "$2" "$LOGS/$1" || fail "$3: no /$2/ in $LOGS/$1"
}

expect_no() {
    if grep -qE "$2" "$LOGS/$1"; then fail "$3: /$2/ in $LOGS/$1"; fi
}

reward() {  # the mean reward in a run's summary.json
    "$HOST_PYTHON" -c 'import json, sys
summary = json.load(open(sys.argv[1]))
print(min(b.get("mean_reward") or 0 for b in summary["behaviors"].values()))' "$1/run/summary.json"
}

run_checks() {
    local dir status
    docker run --rm --network=none "$IMAGE" --help >"$LOGS/help.log" 2>&1 || fail "--help failed"
    expect help.log "train" "--help"
    step "--help: ok"

    dir=$(results_dir root-owned root 755)
    status=0
    docker run --rm --network=none -v "$dir:/workspace/results" "$IMAGE" train \
        --max-seconds 5 >"$LOGS/root-owned.log" 2>&1 || status=$?
    ((status == 2)) || fail "a root-owned results dir: exit $status, wanted 2"
    expect root-owned.log "^error: --results-dir: cannot write results/run as uid 1000" "root-owned"
    expect_no root-owned.log "Traceback" "root-owned results dir"
    step "a root-owned results dir: one line, exit 2"

    dir=$(results_dir train 1000 755)
    docker run --rm --network=none --shm-size=2g -v "$dir:/workspace/results" "$IMAGE" \
        train --max-seconds 60 >"$LOGS/train.log" 2>&1 || fail "train --max-seconds 60 failed"
    expect train.log "^finished: " "train (no TTY): 'finished:' starts its own line"
    expect_no train.log "Traceback" "train"
    expect_no train.log "instead of /dev/shm" "train: the object store fits --shm-size=2g"
    local mean
    mean=$(reward "$dir")
    "$HOST_PYTHON" -c "import sys; sys.exit(float(sys.argv[1]) < 90)" "$mean" ||
        fail "train --max-seconds 60 reached mean reward $mean, wanted >= 90"
    step "train --max-seconds 60: exit 0, mean reward $mean"

    dir=$(results_dir stop 1000 755)
    containers+=(unity-rollout-check-stop)
    docker run -d --name unity-rollout-check-stop --network=none --shm-size=2g \
        -v "$dir:/workspace/results" "$IMAGE" >/dev/null
    for _ in $(seq 240); do
        docker logs unity-rollout-check-stop 2>&1 | grep -q "Step:" && break
        sleep 0.5
    done
    local t0=$SECONDS
    docker stop -t 30 unity-rollout-check-stop >/dev/null
    status=$(docker wait unity-rollout-check-stop)
    local took=$((SECONDS - t0))
    docker logs unity-rollout-check-stop >"$LOGS/stop.log" 2>&1
    ((status == 0)) || fail "docker stop: exit $status, wanted 0 (see $LOGS/stop.log)"
    expect stop.log "^stopped by SIGINT/SIGTERM: " "docker stop"
    grep -q '"interrupted": "SIGTERM"' "$dir/run/summary.json" || fail "docker stop: summary.json"
    compgen -G "$dir/run/checkpoints/*/step-*.pt" >/dev/null || fail "docker stop: no checkpoint"
    step "docker stop: graceful in $took s, exit 0, checkpoint written"

    dir=$(results_dir other-uid 12345 700)
    docker run --rm --network=none --shm-size=2g --user 12345:12345 \
        -v "$dir:/workspace/results" "$IMAGE" train --max-seconds 15 \
        >"$LOGS/other-uid.log" 2>&1 || fail "--user 12345:12345 failed (see $LOGS/other-uid.log)"
    [[ -f "$dir/run/summary.json" ]] || fail "--user 12345:12345: no summary.json"
    step "--user 12345:12345: exit 0"

    status=0
    docker run --rm --network=none "$IMAGE" xvfb-run -a unity-rollout --help \
        >"$LOGS/xvfb-headless.log" 2>&1 || status=$?
    ((status == 2)) || fail "xvfb-run in the headless image: exit $status, wanted 2"
    expect xvfb-headless.log "^error: xvfb-run is only in the render variant" "xvfb-run"
    step "xvfb-run in the headless image: one line naming the render variant"
}

render_checks() {
    build "$IMAGE-render" build-render.log --build-arg RENDER=1
    local dir
    dir=$(results_dir render 1000 755)
    docker run --rm --network=none --shm-size=2g -v "$dir:/workspace/results" \
        "$IMAGE-render" xvfb-run -a unity-rollout train --max-seconds 15 \
        >"$LOGS/render.log" 2>&1 || fail "xvfb-run in the render variant failed"
    expect render.log "^finished: " "render variant"
    step "render variant: xvfb-run -a unity-rollout train: exit 0"
}

unreachable_torch_index() {
    local status=0
    docker build --network=host -t unity-rollout:check-bad-index --build-arg "BASE=$BASE" \
        --build-arg PIP_EXTRA_INDEX_URL=http://127.0.0.1:9/cpu . \
        >"$LOGS/bad-index.log" 2>&1 || status=$?
    ((status != 0)) || fail "a build with an unreachable torch index succeeded"
    expect bad-index.log "error: torch's CPU build is asked for \(TORCH=cpu\) but .* is unreachable" \
        "unreachable torch index"
    step "an unreachable torch CPU index: the build stops with one line"
}

layers() {  # the size of each layer, newest first
    docker history --format '{{.Size}}\t{{.CreatedBy}}' "$1" | cut -c1-150
}

start_engine
pick_base
torch_index
build "$IMAGE" build.log
run_checks
if [[ "${IMAGE_CHECK_RENDER:-1}" != 0 ]]; then render_checks; fi
unreachable_torch_index
{
    echo "base $BASE: $(size "$BASE")"
    echo "$IMAGE: $(size "$IMAGE")"
    layers "$IMAGE"
    if docker image inspect "$IMAGE-render" >/dev/null 2>&1; then
        echo "$IMAGE-render: $(size "$IMAGE-render")"
        layers "$IMAGE-render"
    fi
} | tee "$LOGS/sizes.txt"
