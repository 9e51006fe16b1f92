# fleetmap place database: `fleetmap serve place-db`, storage in the /data volume.
# The base image and the torch wheel source are build arguments: ordinary users take these
# defaults; an offline machine points them at a local base image and wheel index
# (scripts/compose.sh does, see docs/OPERATIONS.md "Docker compose").
#   BASE_IMAGE   Debian bookworm with Python 3.11 (`python3 -m venv` must work); a tag, not
#                a digest: pin one with BASE_IMAGE=python:3.11-slim-bookworm@sha256:...
#   TORCH_INDEX  a PEP 503 index with the CPU build of torch 2.13.0
# Every Python package comes from docker/requirements.lock (scripts/lock.sh), pinned with its
# hashes: the CPU torch and open3d-cpu (the same `open3d` module, 0.6 GB smaller than the
# CUDA build the services never use), the rest from PyPI.
# Three stages: the dependencies into /opt/venv (`deps`), the project built into a wheel
# (`build`); the runtime stage copies the dependencies' venv, then installs the wheel on top.
# A code change rebuilds only the wheel and its small layer while the 2.5 GB venv layer stays
# cached: both images rebuilt in 3 s after a code change, 43 s when the venv was copied
# again. No pip cache, build tools or sources are left in the image.
ARG BASE_IMAGE=python:3.11-slim-bookworm

FROM ${BASE_IMAGE} AS deps
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PATH=/opt/venv/bin:$PATH
RUN python3 -m venv /opt/venv
# The dependencies alone, so a code change does not reinstall them: --require-hashes refuses
# a file whose sha256 is not the lock's and a package the lock does not pin.
COPY docker/requirements.lock /tmp/requirements.lock
RUN pip install --no-cache-dir --require-hashes -r /tmp/requirements.lock \
        --extra-index-url ${TORCH_INDEX}
# The project itself (.dockerignore keeps tests, docs and the venv out of the context), built
# with the locked setuptools: nothing unpinned is downloaded.

FROM deps AS build
COPY . /src
RUN pip wheel --no-cache-dir --no-deps --no-build-isolation --wheel-dir /wheels /src

FROM ${BASE_IMAGE}
# Open3D's shared libraries; a base image that has them already skips apt.
RUN dpkg -s libusb-1.0-0 libgl1 libegl1 libgomp1 >/dev/null 2>&1 \
    || (apt-get update && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libegl1 libgomp1 \
        && rm -rf /var/lib/apt/lists/*)
RUN useradd --system --uid 10001 --home-dir /app --no-create-home fleetmap \
    && mkdir -p /app /data && chown fleetmap /data
COPY --from=deps /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH PYTHONUNBUFFERED=1
COPY --from=build /wheels /tmp/wheels
RUN pip install --no-cache-dir --no-deps --no-index /tmp/wheels/*.whl && rm -rf /tmp/wheels
WORKDIR /app
# not root: a compromised service cannot touch the image
USER fleetmap
ENV FLEETMAP_PLACE_DB_DATA_DIR=/data
VOLUME /data
EXPOSE 8100
HEALTHCHECK --interval=10s --timeout=3s --retries=5 --start-period=30s \
    CMD python -c "import httpx; httpx.get('http://127.0.0.1:8100/healthz').raise_for_status()"
CMD ["fleetmap", "serve", "place-db", "--host", "0.0.0.0", "--port", "8100", "--data-dir", "/data"]
