# PostgreSQL 15 for the place database's replicas (docker-compose.postgres.yml). Debian's own
# package on the same base as the services (a build argument, as theirs), so a machine
# without an image registry builds it from its local base image too.
ARG BASE_IMAGE=python:3.11-slim-bookworm
FROM ${BASE_IMAGE}
RUN apt-get update && apt-get install -y --no-install-recommends postgresql-15 \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /var/lib/postgresql/data && chown -R postgres:postgres /var/lib/postgresql \
    && chmod 700 /var/lib/postgresql/data
COPY docker/postgres-entrypoint.sh /usr/local/bin/postgres-entrypoint.sh
USER postgres
ENV PGDATA=/var/lib/postgresql/data PATH=/usr/lib/postgresql/15/bin:$PATH
VOLUME /var/lib/postgresql/data
EXPOSE 5432
# fast shutdown: SIGTERM is PostgreSQL's "smart" one, which waits for the replicas' pooled
# connections to close, i.e. the whole stop_grace_period, then SIGKILL and crash recovery
STOPSIGNAL SIGINT
HEALTHCHECK --interval=5s --timeout=3s --retries=10 --start-period=30s \
    CMD pg_isready -h 127.0.0.1 -U fleetmap -d fleetmap
ENTRYPOINT ["sh", "/usr/local/bin/postgres-entrypoint.sh"]
