#!/usr/bin/env bash
# Load test through our own client (no wrk needed): starts a release server on loopback with the
# demo assets and a fresh cache, runs `fractile-client bench` (pyramid walk of terrain tiles cold
# then warm, random point batches, regions; each kind bounded by DURATION), stops the server.
# Usage: loadtest/bench.sh [seconds per kind, default 10] [concurrency, default 16]
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION=${1:-10}
CONCURRENCY=${2:-16}
PORT=${PORT:-18091}
cargo build --release -p fractile-cli -p fractile-client -q
CACHE=$(mktemp -d)
FRACTILE_CACHE=$CACHE RUST_LOG=warn target/release/fractile serve --bind 127.0.0.1:$PORT &
PID=$!
trap 'kill $PID 2>/dev/null; wait $PID 2>/dev/null; rm -rf "$CACHE"' EXIT
BASE=http://127.0.0.1:$PORT
for _ in $(seq 1 240); do curl -fs "$BASE/readyz" >/dev/null && break; sleep 0.5; done
curl -fs "$BASE/readyz" >/dev/null || { echo "the server did not become ready" >&2; exit 1; }
target/release/fractile-client --server "$BASE" bench --asset jacksboro \
  --duration "$DURATION" --concurrency "$CONCURRENCY"
