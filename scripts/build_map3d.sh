#!/usr/bin/env bash
# Build the operator page's 3D view: services/place_db/static/map3d.js (the source) with
# three.js and its OrbitControls from npm, bundled and minified by esbuild into
# services/place_db/static/map3d.bundle.js (what the page loads: one file, no CDN).
# Needs node and npm (the npm registry); the bundle is committed, so installs never run this.
set -euo pipefail
cd "$(dirname "$0")/.."
THREE_VERSION=${THREE_VERSION:-0.187.0}
ESBUILD_VERSION=${ESBUILD_VERSION:-0.28.2}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
static=services/place_db/static
(cd "$tmp" && npm install --silent --no-audit --no-fund "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION")
# the source imports "three/addons/OrbitControls.js" (the import map's name): npm's path here
sed 's#"three/addons/OrbitControls.js"#"three/examples/jsm/controls/OrbitControls.js"#' \
  "$static/map3d.js" > "$tmp/map3d.js"
"$tmp/node_modules/.bin/esbuild" "$tmp/map3d.js" --bundle --minify --format=esm \
  --legal-comments=eof --outfile="$static/map3d.bundle.js"
cp "$tmp/node_modules/three/LICENSE" "$static/three/LICENSE"
echo "built $static/map3d.bundle.js with three $THREE_VERSION"
