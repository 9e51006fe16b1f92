#!/usr/bin/env bash
# docker-compose.yml for real: the Docker engine (installed and started if absent), the local
# base image (made once, cached), both images, both services in containers; then against them
# the HTTP integration tests, a whole two-robot merge of real data (../shared/data), and a
# restart of the place database that must keep its data. Then the PostgreSQL stack
# (docker-compose.postgres.yml: postgres, place-db replicas on 8100 and 8101, aligner): the
# integration tests against replica 1, the merge through both replicas (client failover URLs),
# both replicas listing it, SIGKILL of replica 1 (replica 2 and the clients carry on), a
# restart of postgres (replica 2 serves again without a restart of its own), replica 1 started
# again. Everything it started is torn down at the end, whatever happened: the containers,
# its own volumes, and dockerd if this script started it. Runs as its own compose projects
# (fleetmap-test, fleetmap-test-pg), so the volumes of a stack started by hand (project
# fleetmap) are never touched; the ports are the same (8100, 8101, 8200).
# Exit 0: all passed (the data parts are skipped, with a message, only where ../shared/data is
# absent); anything else failed.
set -euo pipefail
cd "$(dirname "$0")/.."

PROJECT=fleetmap-test
export COMPOSE_PROJECT_NAME=$PROJECT FLEETMAP_STACK=sqlite
export PLACE_DB_URL=http://127.0.0.1:8100 ALIGNER_URL=http://127.0.0.1:8200
DATA=${FLEETMAP_DATA:-../shared/data}
PAIR=sun3d_studyroom # the smallest real two-robot recording: 2 x 50 RGB-D frames
VOLUME=${COMPOSE_PROJECT_NAME}_place-db-data
PG_PROJECT=fleetmap-test-pg # the PostgreSQL stack: two place-db replicas over one database
T0=$SECONDS
SKIPPED=""

log() { echo "compose-test.sh: [$((SECONDS - T0)) s] $*"; }
fail() {
  log "FAILED: $*"
  exit 1
}

# the project venv: the test runner and the CLI that drives the containers
[ -x .venv/bin/python ] || bash scripts/install.sh

engine_was_running=0
docker info >/dev/null 2>&1 && engine_was_running=1
WORK=$(mktemp -d /tmp/fleetmap-compose-test.XXXXXX)

teardown() {
  local rc=$?
  trap - EXIT INT TERM
  log "tearing down (exit status so far: $rc)"
  if docker info >/dev/null 2>&1; then
    COMPOSE_PROJECT_NAME=$PROJECT FLEETMAP_STACK=sqlite FLEETMAP_KEEP_ENGINE=1 \
      bash scripts/compose.sh down || rc=1
    docker volume rm -f "$VOLUME" >/dev/null || rc=1
    COMPOSE_PROJECT_NAME=$PG_PROJECT FLEETMAP_STACK=postgres FLEETMAP_KEEP_ENGINE=1 \
      bash scripts/compose.sh down || rc=1
    docker volume rm -f "${PG_PROJECT}_postgres-data" "${PG_PROJECT}_place-db-data" >/dev/null || rc=1
  fi
  if [ "$engine_was_running" = 0 ]; then
    bash scripts/compose.sh engine-stop || rc=1
  fi
  rm -rf "$WORK"
  if [ "$rc" = 0 ]; then
    log "compose test passed in $((SECONDS - T0)) s$SKIPPED"
  else
    log "compose test FAILED (exit $rc) after $((SECONDS - T0)) s"
  fi
  exit "$rc"
}
trap teardown EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

HAVE_DATA=1
if [ ! -d "$DATA/$PAIR/robot_a" ] || [ ! -d "$DATA/$PAIR/robot_b" ]; then
  HAVE_DATA=0
  SKIPPED=" (without the real-data part: no $DATA/$PAIR)"
fi

# merge OUT PLACE_DB: a whole merge of $PAIR's two robots through the containers; both merged,
# B's transform within the data set's tolerance of the ground truth (5 cm, 2 deg)
merge() {
  timeout 300 .venv/bin/fleetmap --quiet merge "A=$DATA/$PAIR/robot_a" "B=$DATA/$PAIR/robot_b" \
    --place-db "$2" --aligner "$ALIGNER_URL" --out "$1" || fail "fleetmap merge through $2"
  .venv/bin/python - "$1/report.json" "$DATA/$PAIR/T_a_b.txt" <<'EOF' || fail "$1/report.json"
import json, sys
import numpy as np
report = json.load(open(sys.argv[1]))
assert set(report["robots"]) == {"A", "B"} and report["unmerged"] == [], report["unmerged"]
T, T_true = np.array(report["transforms"]["B"]), np.loadtxt(sys.argv[2])
dt = float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]))
R = T[:3, :3].T @ T_true[:3, :3]
dr = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
print(f"report.json: A and B merged, B off the ground truth by {dt:.3f} m, {dr:.2f} deg")
assert dt < 0.05 and dr < 2.0, (dt, dr)
EOF
}

# robots PORT: GET /robots of the place database on 127.0.0.1:PORT
robots() { curl -fsS --max-time 10 "http://127.0.0.1:$1/robots"; }
# "A=10 B=13": the keyframe counts of A and B in GET /robots' answer (or, with --report FILE,
# in report.json)
keyframes() {
  .venv/bin/python - "$@" <<'EOF'
import json, sys
if sys.argv[1] == "--report":
    robots = json.load(open(sys.argv[2]))["robots"]
    counts = {name: r["keyframes"] for name, r in robots.items()}
else:
    counts = {r["robot_id"]: r["keyframes"] for r in json.loads(sys.argv[1])["robots"]}
print(" ".join(f"{name}={counts.get(name)}" for name in ("A", "B")))
EOF
}

# --- the SQLite stack (docker-compose.yml) ------------------------------------------------
log "engine, compose and base image"
timeout 600 bash scripts/compose.sh prepare || fail "no Docker engine or base image"
# a fresh database: no volume left over from an interrupted run
docker volume rm -f "$VOLUME" >/dev/null
log "building the images and starting the stack"
timeout 900 bash scripts/compose.sh up || fail "the stack did not come up healthy"

log "HTTP integration tests against the containers"
timeout 300 .venv/bin/python -m pytest -p no:dash -q tests/e2e/test_services_e2e.py ||
  fail "integration tests against the containers"

if [ "$HAVE_DATA" = 1 ]; then
  log "a whole merge of $PAIR's two robots through the containers"
  merge "$WORK/merge" "$PLACE_DB_URL"
  expected=$(keyframes --report "$WORK/merge/report.json") || fail "report.json"
  before=$(keyframes "$(robots 8100)") || fail "GET /robots"
  [ "$before" = "$expected" ] || fail "the place database holds $before, report.json says $expected"
  log "place database holds $before; restarting the place-db container"
  bash scripts/compose.sh restart place-db || fail "restart place-db"
  after=$(keyframes "$(robots 8100)") || fail "GET /robots after the restart"
  [ "$after" = "$before" ] || fail "after the restart the place database holds '$after', before '$before'"
  log "after the restart the place database still holds $after (the volume kept them)"
else
  log "SKIPPED the real-data merge and the restart check: no $DATA/$PAIR (the project's shared data beside the clone)"
fi

# --- the PostgreSQL stack: two place-db replicas over one database (issue 12) ---------------
log "the PostgreSQL stack: postgres, two place-db replicas (8100, 8101), the aligner"
FLEETMAP_KEEP_ENGINE=1 bash scripts/compose.sh down || fail "stopping the SQLite stack"
export COMPOSE_PROJECT_NAME=$PG_PROJECT FLEETMAP_STACK=postgres
docker volume rm -f "${PG_PROJECT}_postgres-data" "${PG_PROJECT}_place-db-data" >/dev/null
timeout 900 bash scripts/compose.sh up || fail "the PostgreSQL stack did not come up healthy"
log "HTTP integration tests against replica 1"
timeout 300 .venv/bin/python -m pytest -p no:dash -q tests/e2e/test_services_e2e.py ||
  fail "integration tests against replica 1"
if [ "$HAVE_DATA" = 0 ]; then
  log "SKIPPED the merge through the replicas and the failover checks: no $DATA/$PAIR"
  exit 0
fi

REPLICAS=http://127.0.0.1:8100,http://127.0.0.1:8101
log "a whole merge through both replicas ($REPLICAS)"
merge "$WORK/merge-pg" "$REPLICAS"
expected=$(keyframes --report "$WORK/merge-pg/report.json") || fail "report.json (PostgreSQL)"
# a container of the PostgreSQL stack by its compose labels (compose v1 and v2 name them apart)
container() {
  docker ps -aq --filter "label=com.docker.compose.project=$PG_PROJECT" \
    --filter "label=com.docker.compose.service=$1"
}
# poll PORT: until the replica on PORT lists the expected keyframes again (60 s at most)
poll() {
  local got="" deadline=$((SECONDS + 60))
  while [ "$SECONDS" -lt "$deadline" ]; do
    got=$(keyframes "$(robots "$1" 2>/dev/null || echo '{"robots": []}')")
    [ "$got" = "$expected" ] && return 0
    sleep 0.5
  done
  echo "$got"
  return 1
}
on_one=$(keyframes "$(robots 8100)") || fail "GET /robots on replica 1"
on_two=$(keyframes "$(robots 8101)") || fail "GET /robots on replica 2"
[ "$on_one" = "$expected" ] || fail "replica 1 holds $on_one, report.json says $expected"
[ "$on_two" = "$expected" ] || fail "replica 2 holds $on_two, report.json says $expected"
log "both replicas hold $on_two; SIGKILL of replica 1"
docker kill "$(container place-db)" >/dev/null || fail "docker kill"
[ "$(keyframes "$(robots 8101)")" = "$expected" ] || fail "replica 2 after replica 1 was killed"
.venv/bin/fleetmap --quiet overlaps A B --place-db "$REPLICAS" --json >/dev/null ||
  fail "the clients' failover to replica 2"
log "replica 2 serves alone, the clients fail over; restarting PostgreSQL"
docker restart "$(container postgres)" >/dev/null || fail "restart postgres"
back=$(poll 8101) || fail "replica 2 after the PostgreSQL restart: $back"
.venv/bin/fleetmap --quiet overlaps A B --place-db "$REPLICAS" --json >/dev/null ||
  fail "the clients after the PostgreSQL restart"
log "after the PostgreSQL restart replica 2 serves $expected again, without a restart of its own"
docker start "$(container place-db)" >/dev/null || fail "start replica 1"
back=$(poll 8100) || fail "replica 1 after its restart: $back"
log "replica 1, started again after its SIGKILL, serves $expected too"
