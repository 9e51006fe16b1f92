# fleetmap place database: `fleetmap serve place-db`, storage in the /data volume.
# The base image and the torch wheel source are build arguments: ordinary users take these
# defaults; an offline machine points them at a local base image and wheel folder.
ARG BASE_IMAGE=python:3.11-slim-bookworm
FROM ${BASE_IMAGE}
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
RUN apt-get update && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libgomp1 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
# CPU-only torch first, so no CUDA build is pulled in.
RUN pip install --no-cache-dir torch==2.13.0 --index-url ${TORCH_INDEX}
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY services ./services
RUN pip install --no-cache-dir . \
    && useradd --system --uid 10001 --home-dir /app fleetmap \
    && mkdir -p /data && chown fleetmap /data
# not root: a compromised service cannot touch the image
USER fleetmap
ENV FLEETMAP_PLACE_DB_DATA_DIR=/data
VOLUME /data
EXPOSE 8100
HEALTHCHECK --interval=10s --timeout=3s --retries=5 --start-period=30s \
    CMD python -c "import httpx; httpx.get('http://127.0.0.1:8100/healthz').raise_for_status()"
CMD ["fleetmap", "serve", "place-db", "--host", "0.0.0.0", "--port", "8100", "--data-dir", "/data"]
