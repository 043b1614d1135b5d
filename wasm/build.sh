#!/usr/bin/env bash
# Builds the browser's decoder: fractile-wasm for wasm32-unknown-unknown (profile `wasm`: small,
# no debug info), its JavaScript bindings by wasm-bindgen-cli (the version the crate pins,
# installed from crates.io into target/ when missing), and the ES modules beside them:
#
#   OUT/pkg/fractile_wasm.js, fractile_wasm_bg.wasm   the module and its bindings
#   OUT/reader.js, worker.js, fractile-protocol.js    RemoteAsset, the worker, MapLibre's protocol
#   OUT/terrain.html, OUT/vendor/                      a page: hillshade and 3D terrain of ?url=
#
# OUT is target/wasm-web unless given. Serve OUT as static files beside the page that imports
# fractile-protocol.js (terrain.html does).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-target/wasm-web}
VERSION=$(sed -n 's/^wasm-bindgen = "=\(.*\)"/\1/p' wasm/Cargo.toml)
rustup target list --installed | grep -qx wasm32-unknown-unknown || rustup target add wasm32-unknown-unknown
BINDGEN=target/wasm-tools/bin/wasm-bindgen
if ! [ -x "$BINDGEN" ] || [ "$("$BINDGEN" --version | awk '{print $2}')" != "$VERSION" ]; then
  # Not --locked: the registry mirror lacks some of the versions its lock file names.
  cargo install -q wasm-bindgen-cli --version "$VERSION" --root target/wasm-tools
fi
cargo build -q --profile wasm -p fractile-wasm --target wasm32-unknown-unknown
mkdir -p "$OUT/pkg"
"$BINDGEN" --target web --no-typescript --out-dir "$OUT/pkg" \
  target/wasm32-unknown-unknown/wasm/fractile_wasm.wasm
cp wasm/js/*.js wasm/web/*.html "$OUT/"
# MapLibre for the page, the copy the server's viewer vendors (no CDN).
mkdir -p "$OUT/vendor"
cp server/web/vendor/maplibre-gl.js server/web/vendor/maplibre-gl.css server/web/vendor/MAPLIBRE-LICENSE.txt "$OUT/vendor/"
echo "$OUT"
