#!/usr/bin/env bash
# docker/requirements.lock: what the Docker images install, every package pinned with its
# sha256 hashes (pip install --require-hashes). Made with pip-tools' pip-compile, for Linux
# x86_64 and CPython 3.11 (the images' platform): pyproject.toml's dependencies and its
# `server` extra, with the CPU build of torch and open3d-cpu as the images use, plus the
# build backend (setuptools, wheel) so the project itself installs without unhashed
# downloads. Run it after changing a dependency in pyproject.toml; tests/unit/
# test_deploy_files.py fails while the lock no longer satisfies pyproject.toml.
#   FLEETMAP_TORCH_INDEX   PEP 503 index with torch 2.13.0+cpu (default: PyTorch's CPU index)
#   FLEETMAP_TORCH_WHEELS  a folder holding the torch 2.13.0+cpu wheel, instead of the index
#                          (a machine that cannot reach PyTorch's index: the lock then holds
#                          that file's hash, which must be the index's for an image build)
#   FLEETMAP_OPEN3D        open3d-cpu (default) or open3d (the CUDA build, 0.6 GB larger)
# Only PyPI and these are consulted: this machine's pip configuration is ignored.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=docker/requirements.lock
PY=${PYTHON:-python3.11}
[ "$(uname -s)-$(uname -m)" = Linux-x86_64 ] ||
  { echo "lock.sh: run on Linux x86_64 (the images' platform)" >&2; exit 1; }
"$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' ||
  { echo "lock.sh: needs CPython 3.11 (set PYTHON)" >&2; exit 1; }

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$PY" -m venv "$work/venv"
quiet() { grep -v "^WARNING: Location" || true; }
pipenv=(env -u PIP_FIND_LINKS -u PIP_INDEX_URL -u PIP_EXTRA_INDEX_URL PIP_CONFIG_FILE=/dev/null)
"${pipenv[@]}" "$work/venv/bin/pip" install -q --disable-pip-version-check "pip-tools==7.6.2" 2>&1 | quiet

# the images' requirements, from pyproject.toml
"$PY" - "${FLEETMAP_OPEN3D:-open3d-cpu}" >"$work/requirements.in" <<'EOF'
import re, sys, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
for req in project["dependencies"] + project["optional-dependencies"]["server"]:
    req = re.sub(r"^open3d\b", sys.argv[1], req)
    print(re.sub(r"^torch==([\d.]+)$", r"torch==\1+cpu", req))
print("setuptools>=77\nwheel")  # the build backend: pip install --no-build-isolation /src
EOF

if [ -n "${FLEETMAP_TORCH_WHEELS:-}" ]; then
  torch_source=(--find-links "$FLEETMAP_TORCH_WHEELS")
else
  torch_source=(--extra-index-url "${FLEETMAP_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}")
fi
"${pipenv[@]}" "$work/venv/bin/pip-compile" --quiet --generate-hashes --allow-unsafe \
  --strip-extras --no-emit-index-url --no-emit-find-links --no-header "${torch_source[@]}" \
  --output-file "$work/requirements.lock" "$work/requirements.in"
{
  echo "# The Docker images' dependencies with their hashes (Linux x86_64, CPython 3.11)."
  echo "# Made by scripts/lock.sh from pyproject.toml (dependencies + the server extra, CPU torch,"
  echo "# ${FLEETMAP_OPEN3D:-open3d-cpu}); do not edit by hand. torch comes from the Dockerfiles' TORCH_INDEX."
  sed "s|$work/requirements.in|pyproject.toml|" "$work/requirements.lock"
} >"$OUT"
echo "lock.sh: $(grep -c '^[a-z0-9]' "$OUT") packages pinned in $OUT"
