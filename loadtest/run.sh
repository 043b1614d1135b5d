#!/usr/bin/env bash
# Load test of a release server on loopback: bounded (DURATION per scenario) and self-stopping.
# Needs wrk (Debian: apt-get install wrk). Usage: loadtest/run.sh [duration, default 10s]
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION=${1:-10s}
PORT=${PORT:-18090}
CONNS=16
command -v wrk >/dev/null || { echo "wrk is needed: apt-get install wrk" >&2; exit 1; }
cargo build --release -p fractile-cli -q
CACHE=$(mktemp -d)
FRACTILE_CACHE=$CACHE RUST_LOG=warn target/release/fractile serve --bind 127.0.0.1:$PORT &
PID=$!
trap 'kill $PID 2>/dev/null; wait $PID 2>/dev/null; rm -rf "$CACHE"' EXIT
for _ in $(seq 1 120); do curl -fs "http://127.0.0.1:$PORT/readyz" >/dev/null && break; sleep 0.5; done
BASE=http://127.0.0.1:$PORT
# Warm one tile for the cached scenario.
TILE="$BASE/v1/assets/jacksboro/tiles/12/1089/1599.png?encoding=terrainrgb"
curl -fs -o /dev/null "$TILE"

run() { # name, per-request items, wrk args...
  local name=$1 items=$2; shift 2
  local out; out=$(wrk -t2 -c$CONNS -d"$DURATION" --latency "$@")
  local rps p50 p99 errs
  rps=$(awk '/Requests\/sec/ {print $2}' <<<"$out")
  p50=$(awk '$1=="50%" {print $2}' <<<"$out")
  p99=$(awk '$1=="99%" {print $2}' <<<"$out")
  errs=$(awk '/Non-2xx/ {print $5}' <<<"$out"); errs=${errs:-0}
  printf "| %s | %s | %.0f | %s | %s | %s |\n" "$name" "$CONNS" "$(awk -v r="$rps" -v n="$items" 'BEGIN{print r*n}')" "$p50" "$p99" "$errs"
}
echo "| scenario | connections | items/s | p50 | p99 | non-2xx |"
echo "|---|---|---|---|---|---|"
run "cached 256x256 terrain-RGB tile" 1 "$TILE"
# Zoom 17 has 15,240 distinct tiles over the asset: enough for 10 s without a repeat.
run "uncached 256x256 terrain-RGB tiles (zoom 17)" 1 -s loadtest/uncached.lua "$BASE"
ASSET=jacksboro-utm run "uncached tiles, UTM asset (reprojected)" 1 -s loadtest/uncached.lua "$BASE"
run "points in batches of 1,000 (12 steps)" 1000 -s loadtest/points.lua "$BASE/v1/assets/jacksboro/points"
