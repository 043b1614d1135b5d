#!/usr/bin/env bash
# The browser's decoder end to end (issue 58), with no tile server in the path: an asset in
# chunks is served as a static file by nginx (Debian's, with Range support), and
#  1. Node decodes 20 tiles at zooms inside and past the source through wasm/js/reader.js and
#     compares them with the server's float32 tiles (wasm/tests/parity.mjs; prints decode times),
#     then again reading the asset from the server's own /v1/assets/{id}/file by range;
#  2. headless Chromium loads wasm/web/terrain.html from nginx: MapLibre draws the asset from
#     the fractile:// protocol (hillshade, 3D terrain), decoded in a Web Worker; the page
#     compares 20 tiles' heights with the server's (nginx proxies /v1/ to it) and the
#     screenshot must show each map drawing more than its background;
#     the same page on another origin than the server's /file, which it reads by range (CORS);
#  3. the server's viewer with its switch "decode in the browser" on: both paths side by side.
# Also: format versions 1-4 read through /file (parity.mjs) and hostile servers and files
# (wasm/tests/hostile.mjs).
# Prints a closing "N passed, N failed" line.
set -euo pipefail
cd "$(dirname "$0")/.."
for c in nginx node chromium; do
  command -v $c >/dev/null || [ -x /usr/sbin/$c ] || { echo "$c is needed (.ci/run installs it)" >&2; exit 1; }
done
NGINX=$(command -v nginx || echo /usr/sbin/nginx)
PORT=${PORT:-18297}
SERVER_PORT=$((PORT + 1))
WORK=$(mktemp -d)
# nginx's workers run as nobody when it starts as root: they must reach the files.
chmod 755 "$WORK"
cargo build --release --workspace -q
WEB=$(wasm/build.sh "$WORK/site")
mkdir -p "$WORK/assets" "$WORK/nginx"
# etopo20 in chunks of 128: 45 chunks at the source level, so a tile reads a few of them.
target/release/fractile encode testdata/etopo20.tif -o "$WORK/assets/etopo20.fra" --chunk 128 >/dev/null
cp "$WORK/assets/etopo20.fra" "$WEB/"
# Files of format versions 1 to 4 (height fields), served as they are stored through /file.
for v in 1 2 3 4; do
  cp testdata/golden/v$v-fis-jacksboro.fra "$WORK/assets/v$v-fis.fra"
  cp testdata/golden/v$v-quadtree-jacksboro-utm.fra "$WORK/assets/v$v-utm.fra"
done
FRACTILE_BACKEND=cpu RUST_LOG=warn target/release/fractile serve --bind 127.0.0.1:$SERVER_PORT \
  --assets "$WORK/assets" &
PID=$!
cat > "$WORK/nginx/nginx.conf" <<CONF
worker_processes 1;
daemon off;
error_log $WORK/nginx/error.log;
pid $WORK/nginx/nginx.pid;
events { worker_connections 256; }
http {
  access_log $WORK/nginx/access.log;
  client_body_temp_path $WORK/nginx/body;
  proxy_temp_path $WORK/nginx/proxy;
  fastcgi_temp_path $WORK/nginx/fastcgi;
  uwsgi_temp_path $WORK/nginx/uwsgi;
  scgi_temp_path $WORK/nginx/scgi;
  types { text/html html; text/javascript js; text/css css; application/wasm wasm; }
  default_type application/octet-stream;
  server {
    listen 127.0.0.1:$PORT;
    root $WEB;
    location /v1/ { proxy_pass http://127.0.0.1:$SERVER_PORT; }
  }
}
CONF
"$NGINX" -c "$WORK/nginx/nginx.conf" &
NGINX_PID=$!
trap 'kill $PID $NGINX_PID 2>/dev/null; wait $PID $NGINX_PID 2>/dev/null; rm -rf "$WORK"' EXIT
for _ in $(seq 1 240); do curl -fs "http://127.0.0.1:$SERVER_PORT/readyz" >/dev/null && break; sleep 0.5; done
for _ in $(seq 1 40); do curl -fs -o /dev/null "http://127.0.0.1:$PORT/terrain.html" && break; sleep 0.25; done

pass=0; fail=0
check() { if eval "$2"; then pass=$((pass + 1)); echo "ok: $1"; else fail=$((fail + 1)); echo "FAILED: $1"; fi; }

SIZE=$(stat -c %s "$WEB/etopo20.fra")
check "nginx answers a range of the asset with 206" \
  '[ "$(curl -s -o /dev/null -w "%{http_code}" -H "Range: bytes=0-99" "http://127.0.0.1:$PORT/etopo20.fra")" = 206 ]'
check "the module is at most 1 MB before compression" \
  '[ "$(stat -c %s "$WEB/pkg/fractile_wasm_bg.wasm")" -le 1000000 ]'
check "Node: 20 tiles decoded from ranges equal the server's" \
  'node wasm/tests/parity.mjs --web "$WEB" --static "http://127.0.0.1:$PORT/" --server "http://127.0.0.1:$SERVER_PORT" --assets etopo20 --tiles 20'
check "Node: the same, the asset read by range from the server's /v1/assets/{id}/file" \
  'node wasm/tests/parity.mjs --web "$WEB" --static "http://127.0.0.1:$SERVER_PORT/v1/assets/{id}/file" --server "http://127.0.0.1:$SERVER_PORT" --assets etopo20 --tiles 20 >/dev/null'

check "Node: files of format versions 1 to 4 read through /file equal the server's tiles" \
  'node wasm/tests/parity.mjs --web "$WEB" --static "http://127.0.0.1:$SERVER_PORT/v1/assets/{id}/file" --server "http://127.0.0.1:$SERVER_PORT" --assets v1-fis,v1-utm,v2-fis,v2-utm,v3-fis,v3-utm,v4-fis,v4-utm --tiles 16 >/dev/null'
check "Node: lying and stalling servers and 200 broken files end in errors, no trap, no hang" \
  'node wasm/tests/hostile.mjs --web "$WEB" --asset "$WEB/etopo20.fra" --mutants 200'

READY_JS="(() => { const s = document.getElementById('status'); return !!s && s.dataset.loaded === 'true'; })()" \
  python3 tests/browser.py "http://127.0.0.1:$PORT/terrain.html?url=etopo20.fra&compare=/v1/assets/etopo20/tiles" "$WORK" 120 || true
DOM=$(cat "$WORK/dom.html" 2>/dev/null || true)
STATUS=$(grep -o '<span id="status"[^>]*>[^<]*' <<<"$DOM" || true)
echo "page status: $STATUS"
attr() { sed -n "s/.*data-$1=\"\([^\"]*\)\".*/\1/p" <<<"$STATUS"; }
check "the page finished" '[ "$(attr loaded)" = true ]'
check "the maps decoded tiles in the browser" '[ "${tiles:=$(attr tiles)}" -gt 0 ]'
check "the page compared 20 tiles, some past the source's zoom" '[ "$(attr compared)" = 20 ] && [ "$(attr past)" -gt 0 ]'
check "all 20 equal the server's heights (within terrain-RGB's rounding)" '[ "$(attr equal)" = 20 ]'
# The page shows the whole world at zooms 1-2, whose levels are views of the source chunks
# (format 8): it needs every chunk, once each, beside the opening's read (16 KiB, which may
# overlap the first chunk).
check "the browser fetched the file's chunks once each ($SIZE bytes, 16 KiB opening)" '[ "$(attr bytes)" -gt 0 ] && [ "$(attr bytes)" -le $((SIZE + 16384)) ]'
check "nginx answered the page's reads by range" 'grep -q "GET /etopo20.fra HTTP/1.1\" 206" "$WORK/nginx/access.log"'
check "the page reported no error" '[ "$(attr errors)" = 0 ]'
check "Chromium saw no JavaScript error" '[ ! -s "$WORK/console.txt" ]'
[ -s "$WORK/console.txt" ] && sed 's/^/  console: /' "$WORK/console.txt"
# The page: a 48 px bar, then two maps side by side, each under a 32 px label. A map that drew
# nothing is one flat colour: a fifth of each must differ from it.
check "each map draws more than its background" \
  '[ -s "$WORK/shot.png" ] && target/release/browser-pixels "$WORK/shot.png" 48 32 0 hillshade:0.2 terrain:0.2'
[ -n "${KEEP_SHOT:-}" ] && cp "$WORK/shot.png" "$KEEP_SHOT"

# 2b. The same page reading the asset from the server's /file on another origin (the page from
# nginx's port, the file from the server's): ranges and their Content-Range cross origins.
mkdir -p "$WORK/cross"
READY_JS="(() => { const s = document.getElementById('status'); return !!s && s.dataset.loaded === 'true'; })()" \
  python3 tests/browser.py "http://127.0.0.1:$PORT/terrain.html?url=http://127.0.0.1:$SERVER_PORT/v1/assets/etopo20/file&compare=/v1/assets/etopo20/tiles" "$WORK/cross" 120 || true
STATUS=$(grep -o '<span id="status"[^>]*>[^<]*' "$WORK/cross/dom.html" 2>/dev/null || true)
echo "cross-origin page status: $STATUS"
check "a page on another origin reads /file by range: 20 tiles equal the server's" \
  '[ "$(attr loaded)" = true ] && [ "$(attr equal)" = 20 ] && [ "$(attr errors)" = 0 ]'
check "the cross-origin page drew each map" \
  '[ -s "$WORK/cross/shot.png" ] && target/release/browser-pixels "$WORK/cross/shot.png" 48 32 0 hillshade:0.2 terrain:0.2'

# 3. The server's viewer with its switch on (`?decode=browser`): the demo's DEM decoded in the
# browser from /v1/assets/{id}/file (the server started with --wasm), beside the server's tiles.
VIEWER_PORT=$((PORT + 2))
FRACTILE_BACKEND=cpu FRACTILE_CACHE=$WORK/demo RUST_LOG=warn target/release/fractile serve \
  --bind 127.0.0.1:$VIEWER_PORT --wasm "$WEB" &
VIEWER_PID=$!
trap 'kill $PID $NGINX_PID $VIEWER_PID 2>/dev/null; wait $PID $NGINX_PID $VIEWER_PID 2>/dev/null; rm -rf "$WORK"' EXIT
for _ in $(seq 1 240); do curl -fs "http://127.0.0.1:$VIEWER_PORT/readyz" >/dev/null && break; sleep 0.5; done
mkdir -p "$WORK/viewer"
READY_JS="(() => { const s = document.getElementById('status'); return !!s && s.dataset.loaded === 'true' && Number(s.dataset.coastPoints) > 0 && s.dataset.browser === 'ready'; })()" \
  python3 tests/browser.py "http://127.0.0.1:$VIEWER_PORT/?decode=browser" "$WORK/viewer" 120 || true
STATUS=$(grep -o '<span id="status"[^>]*>[^<]*' "$WORK/viewer/dom.html" 2>/dev/null || true)
echo "viewer status: $STATUS"
check "the viewer's switch decoded the DEM in the browser" '[ "$(attr browser)" = ready ] && [ "$(attr browser-tiles)" -gt 0 ]'
check "the viewer reported no error" '[ "$(attr errors)" = 0 ] && [ ! -s "$WORK/viewer/console.txt" ]'
# Its layout: the bar, then five panels (the globe's empty without CesiumJS), each under a label.
check "the browser's panel draws beside the server's" \
  '[ -s "$WORK/viewer/shot.png" ] && target/release/browser-pixels "$WORK/viewer/shot.png" 48 64 40 terrain:0.2 browser:0.2 image:0.2 coast:0.001 globe:0'
[ -n "${KEEP_SHOT:-}" ] && cp "$WORK/viewer/shot.png" "${KEEP_SHOT%.png}-viewer.png"
echo "wasm: $pass passed, $fail failed"
[ "$fail" = 0 ]
