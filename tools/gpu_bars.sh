#!/usr/bin/env bash
# Issue 32's GPU measurements (docs/benchmarks.md, "On an H100"), for a machine with a GPU:
# the gpu bench (4096 x 4096 window, points, device time, 3D) at 16 CPU threads, then uncached
# terrain-RGB tiles (the bar's format; ENCODING=terrarium for the earlier runs') of etopo20 (the
# client's cold pyramid walk, 21,845 tiles) with backend=cpu and backend=gpu at 16, 32, 4 and 1
# clients, and the same DEM in chunks at 16 clients, each on a freshly started server (32: more tiles in
# flight than cores, which a GPU request that lends its core slot while it waits can use), and
# prints the bar's ratio for each (ratios.txt).
# Run from the repository root after `cargo build --release` and `cargo bench -p fractile-gpu
# --bench gpu --no-run`, or with BIN naming a folder holding `fractile`, `fractile-client` and
# `gpu-bench` built elsewhere.
set -u
D=${DUR:-10}
OUT=${OUT:-/tmp/gpu-bars}
mkdir -p "$OUT"
BIN=${BIN:-}
if [ -z "$BIN" ]; then
  BIN=$(mktemp -d)
  ln -s "$PWD/target/release/fractile" "$PWD/target/release/fractile-client" "$BIN/"
  ln -s "$(ls -t target/release/deps/gpu-* | grep -v '\.d$' | head -1)" "$BIN/gpu-bench"
fi
command -v nvidia-smi >/dev/null && nvidia-smi -L
export RAYON_NUM_THREADS=${THREADS:-16}
timeout 240 "$BIN/gpu-bench" 2>&1 | tee "$OUT/gpu-bench.txt"
assets=$(mktemp -d)
"$BIN/fractile" encode testdata/etopo20.tif -o "$assets/etopo20.fra"
# The same DEM in chunks of 256 (4 x 2, then overviews): whether chunked assets, which `auto`
# keeps on the CPU, pay on the GPU (each chunk's operator uploaded on first touch).
"$BIN/fractile" encode testdata/etopo20.tif -o "$assets/etopo20c.fra" --chunk 256
for run in cpu:16 gpu:16 cpu:16 gpu:16 cpu:32 gpu:32 cpu:4 gpu:4 cpu:1 gpu:1 cpu:16:etopo20c gpu:16:etopo20c; do
  IFS=: read -r b c asset <<< "$run"
  asset=${asset:-etopo20}
  "$BIN/fractile" serve --assets "$assets" --bind 127.0.0.1:18080 --backend auto > "$OUT/serve-$b.log" 2>&1 &
  pid=$!
  for _ in $(seq 240); do curl -sf localhost:18080/readyz >/dev/null && break; sleep 0.5; done
  echo "== $asset backend=$b clients=$c"
  timeout 60 "$BIN/fractile-client" bench --server http://127.0.0.1:18080 --asset "$asset" \
    --kinds tiles-cold --encoding "${ENCODING:-terrainrgb}" --backend "$b" --duration "$D" \
    --concurrency "$c" | tail -1
  # Where the tiles' time went (seconds summed over the run, and counts).
  curl -s localhost:18080/metrics | grep -E '^fractile_((tile_stage|request|decode)_seconds_(sum|count)|gpu_round|gpu_uploads)'
  kill $pid; wait $pid 2>/dev/null
done 2>&1 | tee "$OUT/tiles.txt"
grep -h "GPU decoding" "$OUT/serve-gpu.log" | head -1
# The bar's ratio, GPU tiles/s over CPU tiles/s, for each asset and client count (the mean of
# the runs of each).
awk '/^== /{split($3,b,"="); split($4,c,"="); key=$2" clients="c[2]; be=b[2]}
     /tiles, cold/{n=split($0,f,"|"); split(f[5],t," "); s[key,be]+=t[1]; k[key,be]++; keys[key]=1}
     END{for (x in keys) if (k[x,"cpu"] && k[x,"gpu"])
       printf "%s: GPU/CPU %.2f (%.0f / %.0f tiles/s)\n", x, (s[x,"gpu"]/k[x,"gpu"])/(s[x,"cpu"]/k[x,"cpu"]), s[x,"gpu"]/k[x,"gpu"], s[x,"cpu"]/k[x,"cpu"]}' \
  "$OUT/tiles.txt" | sort | tee "$OUT/ratios.txt"
