#!/usr/bin/env bash
# End-to-end test of the web viewer: starts a release server on loopback with the demo assets,
# loads the page in headless Chromium (Debian's `chromium`, software WebGL through SwiftShader)
# through tests/browser.py, which waits until the page says its maps are idle, the globe ready and the coast
# is in, and checks the screenshot (each map draws more than its background: `browser-pixels`,
# tests/pixels.rs), that the maps loaded tiles from the server, and that the page logged no
# error. Bounded: the page gets 90 s to get there; the server is stopped on exit. Prints a
# closing "N passed, N failed" line.
set -euo pipefail
cd "$(dirname "$0")/.."
command -v chromium >/dev/null || { echo "chromium is needed (apt-get install chromium)" >&2; exit 1; }
PORT=${PORT:-18197}
WORK=$(mktemp -d)
# The whole workspace, as CI builds it before: one package alone unifies dependency features
# differently and would rebuild wgpu and the server.
cargo build --release --workspace -q
# CesiumJS for the globe panel (npm, pinned; kept in target/ between runs).
CESIUM=$(tools/fetch-cesium.sh) || { echo "tools/fetch-cesium.sh failed (needs npm and its registry)" >&2; exit 1; }
# The viewer is under test here, not the GPU (gpu/ and server/tests cover that): the CPU backend
# keeps a software Vulkan adapter out of the server process while Chromium runs SwiftShader.
FRACTILE_BACKEND=cpu FRACTILE_CACHE=$WORK/cache RUST_LOG=warn \
  target/release/fractile serve --bind 127.0.0.1:$PORT --cesium "$CESIUM" &
PID=$!
trap 'kill $PID 2>/dev/null; wait $PID 2>/dev/null; rm -rf "$WORK"' EXIT
for _ in $(seq 1 240); do curl -fs "http://127.0.0.1:$PORT/readyz" >/dev/null && break; sleep 0.5; done

pass=0; fail=0
check() { if eval "$2"; then pass=$((pass + 1)); echo "ok: $1"; else fail=$((fail + 1)); echo "FAILED: $1"; fi; }

URL="http://127.0.0.1:$PORT/${PAGE_QUERY:-}"
# The page (server/web/index.html): a 48 px bar, then five 240 px wide maps, each with a label
# at its top (64 px with up to three lines) and the attribution at its bottom (40 px). A map that
# drew nothing is one flat colour: 20% of the terrain, image and globe panels, 0.1% of the
# coast panel (a 1.2 px line around Great Britain is ~1.3%) and 3% of the volume panel (a
# part seen whole, most of the panel its background) must differ from it.
idle=0
python3 tests/browser.py "$URL" "$WORK" 90 && idle=1
DOM=$(cat "$WORK/dom.html" 2>/dev/null || true)
pixels() {
  [ -s "$WORK/shot.png" ] &&
    target/release/browser-pixels "$WORK/shot.png" 48 64 40 terrain:0.2 image:0.2 coast:0.001 globe:0.2 volume:0.03
}
STATUS=$(grep -o '<span id="status"[^>]*>[^<]*' <<<"$DOM" || true)
echo "page status: $STATUS"
tiles=$(sed -n 's/.*data-tiles="\([0-9]*\)".*/\1/p' <<<"$STATUS")
terrain=$(sed -n 's/.*data-terrain-tiles="\([0-9]*\)".*/\1/p' <<<"$STATUS")
image=$(sed -n 's/.*data-image-tiles="\([0-9]*\)".*/\1/p' <<<"$STATUS")
coast=$(sed -n 's/.*data-coast-points="\([0-9]*\)".*/\1/p' <<<"$STATUS")
errors=$(sed -n 's/.*data-errors="\([0-9]*\)".*/\1/p' <<<"$STATUS")
served=$(curl -fs "http://127.0.0.1:$PORT/metrics" | awk '/^fractile_requests_total\{route="\/v1\/assets\/\{id\}\/tiles\/\{z\}\/\{x\}\/\{tile\}",status="200"\}/ {s += $2} END {print s + 0}')
echo "tiles loaded by the page: ${tiles:-none}; tile requests the server answered: $served"
check "the page rendered its status" '[ -n "$STATUS" ]'
check "the page reported its maps idle within 90 s" '[ "$idle" -eq 1 ]'
check "each map draws more than its background (screenshot)" 'pixels'
check "the terrain map loaded tiles" '[ "${terrain:-0}" -gt 0 ]'
check "the image map loaded tiles" '[ "${image:-0}" -gt 0 ]'
check "the coast map received the curve asset" '[ "${coast:-0}" -gt 0 ]'
globe=$(sed -n 's/.*data-globe="\([a-z]*\)".*/\1/p' <<<"$STATUS")
terrain_tiles=$(curl -fs "http://127.0.0.1:$PORT/metrics" | awk '/^fractile_requests_total\{route="\/v1\/assets\/\{id\}\/terrain\/\{z\}\/\{x\}\/\{tile\}",status="200"\}/ {s += $2} END {print s + 0}')
echo "globe: ${globe:-none}; Cesium terrain tiles the server answered: $terrain_tiles"
check "the globe loaded Cesium terrain from the server" '[ "$globe" = ready ] && [ "$terrain_tiles" -gt 0 ]'
check "the server answered the tile requests" '[ "$served" -gt 0 ]'
# The volume: 3D Tiles streamed by CesiumJS; then a second look from close by (`?near`), which
# must fetch more tiles (deeper levels where the camera looks) and change the volume's pixels.
volume=$(sed -n 's/.*data-volume="\([a-z]*\)".*/\1/p' <<<"$STATUS")
volume_tiles=$(sed -n 's/.*data-volume-tiles="\([0-9]*\)".*/\1/p' <<<"$STATUS")
glbs() {
  curl -fs "http://127.0.0.1:$PORT/metrics" | awk '/^fractile_requests_total\{route="\/v1\/assets\/\{id\}\/3dtiles\/\{level\}\/\{x\}\/\{y\}\/\{file\}",status="200"\}/ {s += $2} END {print s + 0}'
}
far_glbs=$(glbs)
echo "volume: ${volume:-none}, ${volume_tiles:-0} tiles drawn; 3D tiles the server answered: $far_glbs"
check "the volume panel streamed 3D Tiles from the server" '[ "$volume" = ready ] && [ "${volume_tiles:-0}" -gt 0 ] && [ "$far_glbs" -gt 0 ]'
mkdir -p "$WORK/near"
sep='?'; [ -n "${PAGE_QUERY:-}" ] && sep='&'
python3 tests/browser.py "${URL}${sep}near" "$WORK/near" 90 || true
NEAR=$(grep -o '<span id="status"[^>]*>[^<]*' "$WORK/near/dom.html" 2>/dev/null || true)
near_tiles=$(sed -n 's/.*data-volume-tiles="\([0-9]*\)".*/\1/p' <<<"$NEAR")
near_volume=$(sed -n 's/.*data-volume="\([a-z]*\)".*/\1/p' <<<"$NEAR")
echo "volume from close by: ${near_volume:-none}, ${near_tiles:-0} tiles drawn (from afar: ${volume_tiles:-0})"
check "closer, the volume refines: more tiles than from afar" '[ "$near_volume" = ready ] && [ "${near_tiles:-0}" -gt "${volume_tiles:-0}" ]'
check "closer, the volume's pixels change" '[ -s "$WORK/near/shot.png" ] && target/release/browser-pixels --changed "$WORK/shot.png" "$WORK/near/shot.png" 48 64 40 terrain:0 image:0 coast:0 globe:0 volume:0.05'
if [ -s "$WORK/near/console.txt" ]; then sed 's/^/  logged (near): /' "$WORK/near/console.txt"; fi
check "no map error (the page's counter)" '[ "${errors:-1}" -eq 0 ]'
if [ -s "$WORK/console.txt" ]; then sed 's/^/  logged: /' "$WORK/console.txt"; fi
check "no error logged (exceptions, console.error, as Chromium saw them)" '[ -f "$WORK/console.txt" ] && [ ! -s "$WORK/console.txt" ]'
echo "browser: $pass passed, $fail failed"
[ "$fail" -eq 0 ]
