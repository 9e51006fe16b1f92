#!/usr/bin/env bash
# The Docker compose stack of docker-compose.yml: place database on 127.0.0.1:8100, aligner on
# 127.0.0.1:8200 (FLEETMAP_BIND changes the address).
#   scripts/compose.sh up                build the images if needed, start both, return once
#                                        both are healthy
#   scripts/compose.sh down              stop and remove the containers (the place database's
#                                        data volume stays)
#   scripts/compose.sh restart SERVICE   restart one service (place-db keeps its data)
#   scripts/compose.sh prepare           only the engine, compose and the base image
#   scripts/compose.sh engine-stop       stop dockerd if this script started it
# FLEETMAP_STACK=postgres: the place database on PostgreSQL as two replicas (127.0.0.1:8100 and
# :8101) with a postgres service (docker-compose.postgres.yml over docker-compose.yml), as the
# compose project fleetmap-pg (the SQLite stack is project fleetmap; COMPOSE_PROJECT_NAME
# overrides either); `down`, `restart` take the same FLEETMAP_STACK.
# On a machine without a Docker engine it installs Debian's docker.io (and docker-compose where
# `docker compose` is missing) and starts dockerd in the background; `down` stops that dockerd
# again (FLEETMAP_KEEP_ENGINE=1 keeps it). Without an image registry it makes a local base
# image with debootstrap, once (the root file system is cached in FLEETMAP_DOCKER_CACHE). Where
# pip finds the CPU torch wheel on disk (its find-links), the build takes torch from there,
# through a PEP 503 index served on 127.0.0.1 during the build only.
set -euo pipefail
cd "$(dirname "$0")/.."

CACHE=${FLEETMAP_DOCKER_CACHE:-/var/cache/fleetmap-docker}
STATE=${FLEETMAP_DOCKER_STATE:-/run/fleetmap-compose}
LOCAL_BASE=fleetmap-base:bookworm
DEFAULT_BASE=python:3.11-slim-bookworm
INDEX_PORT=${FLEETMAP_INDEX_PORT:-38100}  # fixed: the index URL is part of the build cache key
SERVICES=(place-db aligner)
FILES=(-f docker-compose.yml)
PROJECT=fleetmap
if [ "${FLEETMAP_STACK:-sqlite}" = postgres ]; then
  # the place database on PostgreSQL, two replicas (8100, 8101): docker-compose.postgres.yml,
  # a project of its own (its volumes apart from the SQLite stack's)
  SERVICES=(postgres place-db place-db-2 aligner)
  FILES+=(-f docker-compose.postgres.yml)
  PROJECT=fleetmap-pg
fi
export COMPOSE_PROJECT_NAME=${COMPOSE_PROJECT_NAME:-$PROJECT}
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"

log() { echo "compose.sh: $*" >&2; }
die() {
  log "$*"
  exit 1
}

APT_UPDATED=0
apt_install() {
  log "installing Debian packages: $*"
  [ "$APT_UPDATED" = 1 ] || $SUDO apt-get update -qq
  APT_UPDATED=1
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

# --- the engine -------------------------------------------------------------------------
engine_running() { docker info >/dev/null 2>&1; }

engine_up() {
  engine_running && return 0
  if ! command -v dockerd >/dev/null || ! command -v docker >/dev/null; then
    # one apt run for all that a machine without an engine will need
    local pkgs=(docker.io)
    docker compose version >/dev/null 2>&1 || command -v docker-compose >/dev/null ||
      pkgs+=(docker-compose)
    command -v debootstrap >/dev/null || [ -s "$CACHE/fleetmap-base-bookworm.tar" ] ||
      pkgs+=(debootstrap)
    apt_install "${pkgs[@]}"
  fi
  $SUDO mkdir -p "$STATE"
  if engine_running; then # the package's own init script started it: ours to stop as well
    $SUDO cp /var/run/docker.pid "$STATE/dockerd.pid" 2>/dev/null || true
    return 0
  fi
  log "starting dockerd (log: /var/log/fleetmap-dockerd.log)"
  $SUDO sh -c 'setsid dockerd >/var/log/fleetmap-dockerd.log 2>&1 </dev/null & echo $! >"$1"' \
    sh "$STATE/dockerd.pid"
  for _ in $(seq 120); do
    engine_running && return 0
    kill -0 "$(cat "$STATE/dockerd.pid")" 2>/dev/null || break
    sleep 0.5
  done
  tail -20 /var/log/fleetmap-dockerd.log >&2 || true
  die "dockerd did not start"
}

# the dockerd this script started, if it still runs
our_dockerd() {
  local pid
  pid=$(cat "$STATE/dockerd.pid" 2>/dev/null) || return 1
  [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = dockerd ] && echo "$pid"
}

engine_stop() {
  local pid
  if ! pid=$(our_dockerd); then
    $SUDO rm -f "$STATE/dockerd.pid"
    return 0
  fi
  log "stopping the dockerd this script started (pid $pid)"
  $SUDO kill -TERM "$pid"
  for _ in $(seq 60); do
    kill -0 "$pid" 2>/dev/null || break
    sleep 0.5
  done
  kill -0 "$pid" 2>/dev/null && die "dockerd (pid $pid) did not stop"
  $SUDO rm -f "$STATE/dockerd.pid"
}

COMPOSE=()
compose_find() {
  if docker compose version >/dev/null 2>&1; then
    COMPOSE=(docker compose)
  else
    command -v docker-compose >/dev/null || apt_install docker-compose
    COMPOSE=(docker-compose)
  fi
}
compose() { "${COMPOSE[@]}" "${FILES[@]}" "$@"; }

# --- the base image -----------------------------------------------------------------------
# Debian bookworm (Python 3.11) with what the images need, and this machine's CA bundle so pip
# trusts the certificates this machine's network presents.
local_base() {
  docker image inspect "$LOCAL_BASE" >/dev/null 2>&1 && return 0
  local tarball="$CACHE/fleetmap-base-bookworm.tar"
  if [ ! -s "$tarball" ]; then
    command -v debootstrap >/dev/null || apt_install debootstrap
    local rootfs
    rootfs=$(mktemp -d /var/tmp/fleetmap-rootfs.XXXXXX)
    log "making the local base image with debootstrap (about a minute, once)"
    $SUDO debootstrap --variant=minbase \
      --include=python3,python3-venv,python3-pip,ca-certificates,libusb-1.0-0,libgl1,libegl1,libgomp1,libudev1 \
      bookworm "$rootfs" >"$CACHE/debootstrap.log" 2>&1 ||
      {
        tail -20 "$CACHE/debootstrap.log" >&2
        die "debootstrap failed"
      }
    $SUDO cp /etc/ssl/certs/ca-certificates.crt "$rootfs/etc/ssl/certs/ca-certificates.crt"
    $SUDO rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    $SUDO tar -C "$rootfs" -cf "$tarball.tmp" . && $SUDO mv "$tarball.tmp" "$tarball"
    $SUDO rm -rf --one-file-system "$rootfs"
  fi
  log "importing $LOCAL_BASE from $tarball"
  docker import \
    --change 'ENV LANG=C.UTF-8' \
    --change 'ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt' \
    --change 'ENV SSL_CERT_FILE=/etc/ssl/certs/ca-certificates.crt' \
    --change 'CMD ["/bin/bash"]' \
    "$tarball" "$LOCAL_BASE" >/dev/null
}

choose_base() {
  [ -n "${FLEETMAP_BASE_IMAGE:-}" ] && return 0
  if docker image inspect "$DEFAULT_BASE" >/dev/null 2>&1 ||
    timeout 60 docker pull -q "$DEFAULT_BASE" >/dev/null 2>&1; then
    FLEETMAP_BASE_IMAGE=$DEFAULT_BASE
  else
    log "no image registry: building on the local Debian base image $LOCAL_BASE"
    local_base
    FLEETMAP_BASE_IMAGE=$LOCAL_BASE
  fi
}

# --- torch from this machine's disk -------------------------------------------------------
local_torch_wheel() {
  local dirs d
  dirs=$(python3 -m pip config list 2>/dev/null | sed -n "s/^[a-z:]*\.find-links='\(.*\)'$/\1/p")
  for d in ${PIP_FIND_LINKS:-} $dirs; do
    d=${d#file://}
    [ -d "$d" ] || continue
    ls "$d"/torch-2.13.0+cpu-cp311-cp311-*"$(uname -m)".whl 2>/dev/null | head -1 && return 0
  done
  return 0
}

INDEX_PID=""
serve_torch_index() {
  local wheel="$1" dir="$CACHE/torch-index"
  if [ ! -s "$dir/files/$(basename "$wheel")" ] || [ ! -s "$dir/simple/index.html" ]; then
    $SUDO rm -rf "$dir"
    log "a local index of torch 2.13.0 CPU and its dependencies in $dir"
    $SUDO mkdir -p "$dir/files"
    $SUDO cp "$wheel" "$dir/files/"
    $SUDO python3 -m pip download -q --dest "$dir/files" "$wheel" 2>&1 |
      { grep -v "^WARNING: Location" || true; } >&2
    $SUDO python3 - "$dir" <<'EOF'
import re, sys
from pathlib import Path
root = Path(sys.argv[1])
names = {}
for f in sorted((root / "files").iterdir()):
    name = f.name.split("-")[0] if f.suffix == ".whl" else f.name.rsplit("-", 1)[0]
    names.setdefault(re.sub(r"[-_.]+", "-", name).lower(), []).append(f.name)
for name, files in names.items():
    d = root / "simple" / name
    d.mkdir(parents=True, exist_ok=True)
    links = "".join(f'<a href="../../files/{f}">{f}</a><br>\n' for f in files)
    (d / "index.html").write_text(f"<!DOCTYPE html><html><body>\n{links}</body></html>\n")
links = "".join(f'<a href="{n}/">{n}</a><br>\n' for n in names)
(root / "simple" / "index.html").write_text(f"<!DOCTYPE html><html><body>\n{links}</body></html>\n")
EOF
  fi
  if (exec 3<>"/dev/tcp/127.0.0.1/$INDEX_PORT") 2>/dev/null; then
    die "port $INDEX_PORT is taken: set FLEETMAP_INDEX_PORT to a free port"
  fi
  python3 -m http.server "$INDEX_PORT" --bind 127.0.0.1 --directory "$dir" \
    >"$CACHE/index-server.log" 2>&1 &
  INDEX_PID=$!
  for _ in $(seq 50); do
    (exec 3<>"/dev/tcp/127.0.0.1/$INDEX_PORT") 2>/dev/null && break
    sleep 0.1
  done
  FLEETMAP_TORCH_INDEX="http://127.0.0.1:$INDEX_PORT/simple/"
}

stop_torch_index() {
  if [ -n "$INDEX_PID" ]; then
    kill "$INDEX_PID" 2>/dev/null || true
    wait "$INDEX_PID" 2>/dev/null || true
    INDEX_PID=""
  fi
}
trap stop_torch_index EXIT

# --- the stack ----------------------------------------------------------------------------
prepare() {
  $SUDO mkdir -p "$CACHE"
  engine_up
  compose_find
  choose_base
  export FLEETMAP_BASE_IMAGE
  # builds reach the package index through the host's network (works with or without a bridge)
  export FLEETMAP_BUILD_NETWORK=${FLEETMAP_BUILD_NETWORK:-host}
}

build() {
  local wheel
  if [ -z "${FLEETMAP_TORCH_INDEX:-}" ]; then
    wheel=$(local_torch_wheel)
    [ -z "$wheel" ] || serve_torch_index "$wheel"
  fi
  [ -z "${FLEETMAP_TORCH_INDEX:-}" ] || export FLEETMAP_TORCH_INDEX
  log "building the images on ${FLEETMAP_BASE_IMAGE} (log: $CACHE/build.log)"
  local t0=$SECONDS
  if ! compose build >"$CACHE/build.log" 2>&1; then
    tail -40 "$CACHE/build.log" >&2
    die "the image build failed (whole log: $CACHE/build.log)"
  fi
  stop_torch_index
  log "images built in $((SECONDS - t0)) s"
}

# the address of a service's /healthz on this host (its published port), or nothing (postgres)
healthz_url() {
  local host=${FLEETMAP_BIND:-127.0.0.1}
  [ "$host" = 0.0.0.0 ] && host=127.0.0.1
  case "$1" in
    place-db) echo "http://$host:8100/healthz" ;;
    place-db-2) echo "http://$host:8101/healthz" ;;
    aligner) echo "http://$host:8200/healthz" ;;
  esac
}

# wait_healthy SERVICE...: each one running and healthy: Docker's health status, or,
# sooner, for an HTTP service, its /healthz answering on its published port (what the
# image's health check asks inside the container; Docker runs that check every 10 s from the
# start, and the engine's legacy builder knows no --start-interval: up and restart waited
# 8-10 s for nothing)
wait_healthy() {
  local CURL svc cid status url deadline=$((SECONDS + ${FLEETMAP_UP_TIMEOUT:-180}))
  for svc in "$@"; do
    cid=$(compose ps -q "$svc")
    [ -n "$cid" ] || die "$svc has no container"
    url=$(healthz_url "$svc")
    CURL=$(command -v curl || true)
    while :; do
      status=$(docker inspect -f '{{.State.Status}} {{if .State.Health}}{{.State.Health.Status}}{{end}}' "$cid")
      [ "$status" = "running healthy" ] && break
      if [ "${status%% *}" != running ] || [ "$SECONDS" -ge "$deadline" ]; then
        compose logs --tail 40 "$svc" >&2 || true
        die "$svc is not healthy ($status)"
      fi
      [ -n "$url" ] && [ -n "$CURL" ] && curl -fsS -m 2 -o /dev/null "$url" 2>/dev/null && break
      sleep 0.5
    done
    log "$svc healthy"
  done
}

# another compose project's place database (the other stack, or compose-test.sh's) holds
# the ports: say which, rather than compose's "port is already allocated"
other_stack() {
  local other
  other=$(docker ps --filter label=com.docker.compose.service=place-db \
    --format '{{.Label "com.docker.compose.project"}}' | grep -vx "$COMPOSE_PROJECT_NAME" | head -1) || true
  [ -z "$other" ] && return 0
  local how="COMPOSE_PROJECT_NAME=$other scripts/compose.sh down"
  [ "$other" = fleetmap ] && how="scripts/compose.sh down"
  [ "$other" = fleetmap-pg ] && how="FLEETMAP_STACK=postgres scripts/compose.sh down"
  [[ "$other" == *-pg ]] && [ "$other" != fleetmap-pg ] && how="FLEETMAP_STACK=postgres $how"
  die "compose project $other runs a place database on these ports: take it down first ($how)"
}

cmd_up() {
  prepare
  other_stack
  build
  compose up -d --no-build
  wait_healthy "${SERVICES[@]}"
  local second=""
  [ "${FLEETMAP_STACK:-sqlite}" = postgres ] && second=" and :8101 (PostgreSQL replicas)"
  log "place database on http://${FLEETMAP_BIND:-127.0.0.1}:8100$second, aligner on http://${FLEETMAP_BIND:-127.0.0.1}:8200"
}

cmd_down() {
  if engine_running; then
    compose_find
    compose down --timeout 45
  fi
  [ "${FLEETMAP_KEEP_ENGINE:-0}" = 1 ] || engine_stop
}

cmd_restart() {
  local svc="${1:-}"
  [[ " ${SERVICES[*]} " == *" $svc "* ]] || die "restart which service? ${SERVICES[*]}"
  engine_running || die "no Docker engine runs: scripts/compose.sh up first"
  compose_find
  compose restart --timeout 45 "$svc"
  wait_healthy "$svc"
}

case "${1:-}" in
  up) cmd_up ;;
  down) cmd_down ;;
  restart) cmd_restart "${2:-}" ;;
  prepare) prepare ;;
  build) prepare && build ;;
  engine-stop) engine_stop ;;
  *) die "usage: scripts/compose.sh up|down|restart SERVICE|prepare|build|engine-stop" ;;
esac
