#!/bin/sh
# First start on an empty volume: a cluster, role and database `fleetmap` with the password
# of FLEETMAP_PG_PASSWORD, password logins over the network. Then PostgreSQL in the foreground.
set -eu
if [ ! -s "$PGDATA/PG_VERSION" ]; then
  : "${FLEETMAP_PG_PASSWORD:?set FLEETMAP_PG_PASSWORD}"
  initdb -D "$PGDATA" -U postgres --auth-local=trust --auth-host=scram-sha-256 >/dev/null
  echo "listen_addresses = '*'" >>"$PGDATA/postgresql.conf"
  echo "host all all 0.0.0.0/0 scram-sha-256" >>"$PGDATA/pg_hba.conf"
  pg_ctl -D "$PGDATA" -o "-c listen_addresses='' -k /tmp" -w start >/dev/null
  # the password as a psql variable, quoted by psql (any character is safe)
  psql -v ON_ERROR_STOP=1 -v pw="$FLEETMAP_PG_PASSWORD" -h /tmp -U postgres -q <<'SQL'
CREATE ROLE fleetmap LOGIN PASSWORD :'pw';
CREATE DATABASE fleetmap OWNER fleetmap;
SQL
  pg_ctl -D "$PGDATA" -m fast -w stop >/dev/null
  echo "postgres-entrypoint: new cluster with database fleetmap"
fi
exec postgres -D "$PGDATA" -k /tmp
