#!/usr/bin/env bash
# Install fleetmap and its dependencies into ./.venv (Debian, Python 3.11).
set -euo pipefail
cd "$(dirname "$0")/.."
# postgresql-15: the PostgreSQL backend and its tests (a throwaway cluster per test run);
# chromium: the operator page's test in a real headless browser
APT_PACKAGES="libusb-1.0-0 libgl1 libgomp1 postgresql-15 chromium"
missing=$(for p in $APT_PACKAGES; do dpkg -s "$p" >/dev/null 2>&1 || echo "$p"; done)
if [ -n "$missing" ]; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq && $SUDO apt-get install -y -qq $missing
fi
# Fast path: a venv this script completed for the same pyproject.toml and install.sh (the
# stamp), whose `fleetmap` is this checkout and whose requirements hold (pip check). A fresh
# machine, a changed dependency list or a venv copied from elsewhere installs everything.
STAMP=.venv/.fleetmap-install-stamp
want=$(cat pyproject.toml scripts/install.sh | sha256sum | cut -d' ' -f1)
if [ -z "${FLEETMAP_FULL_INSTALL:-}" ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ] \
  && .venv/bin/python -c "import fleetmap, pathlib, sys; \
sys.exit(pathlib.Path(fleetmap.__file__).parent.resolve() != pathlib.Path('shared').resolve())" \
  2>/dev/null && .venv/bin/python -m pip check -q >/dev/null 2>&1; then
  echo "fleetmap already installed in .venv (FLEETMAP_FULL_INSTALL=1 reinstalls)"
  exit 0
fi
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip 2>/dev/null || true
quiet() { grep -v "^WARNING: Location" || true; }
# uv (PyPI) installs what pip would, from the same places, in a quarter of the time (a clean
# clone here: torch and the rest 61 -> 16 s, the whole script 70 -> 17 s): pip's own
# settings (find-links, constraint, extra indexes, cert) are handed to it. Where uv cannot be
# had or fails, pip does it all (as FLEETMAP_NO_UV=1 asks). Both leave the packages'
# bytecode compiled (uv only when asked: UV_COMPILE_BYTECODE): where PYTHONDONTWRITEBYTECODE
# is set, as on this machine, nothing else ever writes it, and every process (each merge,
# service, extraction worker and test subprocess) compiled SciPy, Open3D and the rest from
# source again: 3.0 -> 1.6 s to import them, a two-robot merge 13.1-14.0 -> 10.3-10.4 s.
with_uv() {
  .venv/bin/python -m pip install -q --disable-pip-version-check uv 2>&1 | quiet
  [ -x .venv/bin/uv ] || return 1
  local conf; conf=$(.venv/bin/python -m pip config list 2>/dev/null || true)
  setting() { sed -n "s/^[a-z:]*\.$1='\(.*\)'$/\1/p" <<<"$conf" | head -1; }
  local links constraint extra cert
  links=$(setting find-links) constraint=$(setting constraint) extra=$(setting extra-index-url)
  cert=$(setting cert)
  UV_FIND_LINKS=${links// /,} UV_CONSTRAINT=$constraint UV_EXTRA_INDEX_URL=$extra \
    SSL_CERT_FILE=${cert:-${SSL_CERT_FILE:-}} UV_INDEX_STRATEGY=unsafe-best-match \
    UV_PYTHON=.venv/bin/python UV_COMPILE_BYTECODE=1 \
    bash -c '.venv/bin/uv pip install -q "torch==2.13.0" && .venv/bin/uv pip install -q -e ".[server,dev]"'
}
# CPU torch first: an unpinned torch would pull a multi-GB CUDA build.
if [ -n "${FLEETMAP_NO_UV:-}" ] || ! with_uv; then
  [ -n "${FLEETMAP_NO_UV:-}" ] || echo "install.sh: uv could not install; pip instead" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check "torch==2.13.0" 2>&1 | quiet
  # (the build backend warns on every editable install of a package-dir mapping: not for users)
  PYTHONWARNINGS=ignore .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[server,dev]" 2>&1 | quiet
fi
.venv/bin/python -c "import fastapi, cv2, open3d, torch, faiss, psycopg; import fleetmap.services.cli" \
  || { echo "install.sh: dependencies failed to import" >&2; exit 1; }
echo "$want" > "$STAMP"
echo "fleetmap installed in .venv"
