# fleetmap place database: `fleetmap serve place-db`, storage in the /data volume.
FROM python:3.11-slim
RUN apt-get update && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libgomp1 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
# CPU-only torch first, so no CUDA build is pulled in.
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY services ./services
RUN pip install --no-cache-dir .
ENV FLEETMAP_PLACE_DB_DATA_DIR=/data
VOLUME /data
EXPOSE 8100
HEALTHCHECK --interval=10s --timeout=3s --retries=5 \
    CMD python -c "import httpx; httpx.get('http://127.0.0.1:8100/healthz').raise_for_status()"
CMD ["fleetmap", "serve", "place-db", "--host", "0.0.0.0", "--port", "8100", "--data-dir", "/data"]
