#!/usr/bin/env bash
# Issue 32's GPU measurements (docs/benchmarks.md, "On an H100"), for a machine with a GPU:
# uncached terrain-RGB tiles (the bar's format; ENCODING=terrarium for the earlier runs') of etopo20 (the
# client's cold pyramid walk, 21,845 tiles) with backend=cpu and backend=gpu at 16, 32, 4 and 1
# clients, and the same DEM in chunks at 16 clients, each on a freshly started server (32: more tiles in
# flight than cores, which a GPU request that lends its core slot while it waits can use), and
# prints the bar's ratio for each (ratios.txt); then the gpu bench (4096 x 4096 window, points,
# device time, 3D) at 16 CPU threads, for BENCH_S seconds at most (240; 0 skips it). The tiles
# go first: they are the open bar, and a device lease can end mid-run.
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
assets=$(mktemp -d)
"$BIN/fractile" encode testdata/etopo20.tif -o "$assets/etopo20.fra"
# The same DEM in chunks of 256 (4 x 2, then overviews): whether chunked assets, which `auto`
# keeps on the CPU, pay on the GPU (each chunk's operator uploaded on first touch).
"$BIN/fractile" encode testdata/etopo20.tif -o "$assets/etopo20c.fra" --chunk 256
"$BIN/fractile" encode testdata/jacksboro.tif -o "$assets/jacksboro.fra"
# Each run: backend:clients[:asset[:server]], server naming another build's binary in BIN (to
# compare two builds in one run; its lines are kept out of the ratios). RUNS overrides the list.
RUNS=${RUNS:-cpu:16 gpu:16 cpu:16 gpu:16 cpu:32 gpu:32 cpu:64 gpu:64 cpu:4 gpu:4 cpu:1 gpu:1 cpu:16:etopo20c gpu:16:etopo20c cpu:32:jacksboro gpu:32:jacksboro}
# Process CPU time (user + system, seconds) of pid $1, from /proc.
cpu_s() { awk -v t="$(getconf CLK_TCK)" '{print ($14 + $15) / t}' "/proc/$1/stat"; }
TIMEFORMAT='client cpu %U %S'
for run in $RUNS; do
  IFS=: read -r b c asset server <<< "$run"
  asset=${asset:-etopo20}
  "$BIN/${server:-fractile}" serve --assets "$assets" --bind 127.0.0.1:18080 --backend auto > "$OUT/serve-$b.log" 2>&1 &
  pid=$!
  for _ in $(seq 240); do curl -sf localhost:18080/readyz >/dev/null && break; sleep 0.5; done
  echo "== $asset backend=$b clients=$c${server:+ server=$server}"
  before=$(cpu_s $pid)
  time timeout 60 "$BIN/fractile-client" bench --server http://127.0.0.1:18080 --asset "$asset" \
    --kinds tiles-cold --encoding "${ENCODING:-terrainrgb}" --backend "$b" --duration "$D" \
    --concurrency "$c" | tail -1
  # The server's own core time over the run: what a tile costs it, the client (which shares
  # the cores) apart.
  echo "server cpu $(cpu_s $pid) $before"
  # Where the tiles' time went (seconds summed over the run, and counts).
  curl -s localhost:18080/metrics | grep -E '^fractile_((tile_stage|request|decode)_seconds_(sum|count)|gpu_round|gpu_uploads)'
  kill $pid; wait $pid 2>/dev/null
done 2>&1 | tee "$OUT/tiles.txt"
grep -h "GPU decoding" "$OUT/serve-gpu.log" | head -1
# The bar's ratio, GPU tiles/s over CPU tiles/s, for each asset and client count (the mean of
# the runs of each).
awk '/^== /{split($3,b,"="); split($4,c,"="); key=$2" clients="c[2]; be=b[2]; if ($5 != "") be=$5}
     /tiles, cold/{n=split($0,f,"|"); split(f[5],t," "); s[key,be]+=t[1]; k[key,be]++; keys[key]=1; req=f[4]}
     /^server cpu/{sc[key,be]+=($3-$4)*1000/req}
     /^client cpu/{cc[key,be]+=($3+$4)*1000/req}
     END{for (x in keys) if (k[x,"cpu"] && k[x,"gpu"])
       printf "%s: GPU/CPU %.2f (%.0f / %.0f tiles/s); core ms a tile, server: GPU %.2f CPU %.2f, client: %.2f / %.2f\n", x,
         (s[x,"gpu"]/k[x,"gpu"])/(s[x,"cpu"]/k[x,"cpu"]), s[x,"gpu"]/k[x,"gpu"], s[x,"cpu"]/k[x,"cpu"],
         sc[x,"gpu"]/k[x,"gpu"], sc[x,"cpu"]/k[x,"cpu"], cc[x,"gpu"]/k[x,"gpu"], cc[x,"cpu"]/k[x,"cpu"]}' \
  "$OUT/tiles.txt" | sort | tee "$OUT/ratios.txt"
if [ "${BENCH_S:-240}" -gt 0 ]; then
  timeout "${BENCH_S:-240}" "$BIN/gpu-bench" 2>&1 | tee "$OUT/gpu-bench.txt"
fi
