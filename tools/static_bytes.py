"""Issue 58's bytes bar: a DEM published as static files, fractile's one asset against a
terrain-RGB pyramid made by rio-rgbify (PNG tiles in MBTiles, converted to PMTiles), for one map
session of the same tiles.

Usage (the venv holds rio-rgbify and pmtiles: `python3 -m venv target/rgbify-venv &&
target/rgbify-venv/bin/pip install rio-rgbify pmtiles`):

    target/rgbify-venv/bin/python tools/static_bytes.py DEM.tif COPIES WORK_DIR [TILES] [SEED]

The DEM is mirrored COPIES x COPIES (odd copies flipped, as the codec's benches do: real
relief at its real resolution, at a real size; jacksboro x 12 is 4128 x 4356). Needs
target/release/fractile, wasm/build.sh's output in target/wasm-web, node and nginx.

- the pyramid: `rio rgbify -b -10000 -i 0.1` (terrain-RGB at 0.1 m, what MapLibre reads) from
  zoom 0 to the zoom whose 512-pixel tiles match the source's cells, then `pmtiles-convert`.
- fractile: `fractile encode` with its defaults (the projected codec under a bounded rate).
- the session: TILES (default 50) 512-pixel tiles drawn at random at the pyramid's four
  deepest zooms over the DEM; PMTiles' bytes are what a range-reading client fetches for them
  (header, root and leaf directories once, each tile), counted through the pmtiles reader;
  fractile's are what wasm/js/reader.js fetched from nginx for the same tiles (Node).
Prints a table of sizes and bytes, and the ratios the issue bars (a fifth, a tenth).
FRACTILE_FLAGS adds flags to fractile's encode (`--chunk 256`: smaller chunks, each decoded
sooner by the first tile that reads it).
"""

import json
import math
import os
import random
import sqlite3
import subprocess
import sys
import time

import numpy as np
import rasterio
from pmtiles.reader import Reader

dem, copies, work = sys.argv[1], int(sys.argv[2]), sys.argv[3]
count = int(sys.argv[4]) if len(sys.argv) > 4 else 50
seed = int(sys.argv[5]) if len(sys.argv) > 5 else 1
os.makedirs(work, exist_ok=True)
os.chmod(work, 0o755)
bin_dir = os.path.dirname(sys.executable)
name = os.path.splitext(os.path.basename(dem))[0] + f"-x{copies}"
big = os.path.join(work, name + ".tif")

# The DEM at a real size: mirrored copies keep every slope real.
with rasterio.open(dem) as src:
    a = src.read(1)
    profile = src.profile
    rows = []
    for j in range(copies):
        row = [a[:, ::-1] if i % 2 else a for i in range(copies)]
        band = np.concatenate(row, axis=1)
        rows.append(band[::-1, :] if j % 2 else band)
    big_a = np.concatenate(rows, axis=0)
    profile.update(width=big_a.shape[1], height=big_a.shape[0], tiled=True, blockxsize=256,
                   blockysize=256, compress="deflate")
    with rasterio.open(big, "w", **profile) as dst:
        dst.write(big_a, 1)
    h, w = big_a.shape
    raw = big_a.nbytes
print(f"{name}: {w} x {h} cells, {raw:,} bytes raw", flush=True)


def run(cmd):
    t = time.time()
    # rio-rgbify warns once a tile (NotGeoreferencedWarning of its in-memory PNGs).
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.time() - t


# fractile's asset, its defaults.
fra = os.path.join(work, name + ".fra")
encode_flags = os.environ.get("FRACTILE_FLAGS", "").split()  # e.g. "--chunk 256"
t_fra = run(["target/release/fractile", "encode", big, "-o", fra, *encode_flags])
# The pyramid to the zoom of the source's cells (512-pixel tiles, as rio-rgbify writes them).
with rasterio.open(big) as src:
    from rasterio.warp import transform_bounds
    west, south, east, north = transform_bounds(src.crs, "EPSG:4326", *src.bounds)
native = math.ceil(math.log2(w * 360.0 / (east - west) / 512))
mbtiles = os.path.join(work, name + ".mbtiles")
pmt = os.path.join(work, name + ".pmtiles")
for f in (mbtiles, pmt):
    if os.path.exists(f):
        os.remove(f)
t_rgb = run([os.path.join(bin_dir, "rio"), "rgbify", "-b", "-10000", "-i", "0.1", "--min-z", "0",
             "--max-z", str(native), "--format", "png", "-j", "2", big, mbtiles])
# rio-rgbify's MBTiles metadata lacks the zooms and bounds pmtiles-convert needs.
with sqlite3.connect(mbtiles) as db:
    for k, v in {"minzoom": "0", "maxzoom": str(native), "format": "png",
                 "bounds": f"{west},{south},{east},{north}"}.items():
        db.execute("DELETE FROM metadata WHERE name = ?", (k,))
        db.execute("INSERT INTO metadata (name, value) VALUES (?, ?)", (k, v))
run([os.path.join(bin_dir, "pmtiles-convert"), mbtiles, pmt])

# The session: tiles at the pyramid's four deepest zooms, over the DEM.
rng = random.Random(seed)


def tile_of(lon, lat, z):
    n = 2 ** z
    r = math.radians(lat)
    return (int((lon + 180) / 360 * n), int((1 - math.log(math.tan(r) + 1 / math.cos(r)) / math.pi) / 2 * n))


session = []
while len(session) < count:
    z = rng.randint(max(0, native - 3), native)
    x, y = tile_of(rng.uniform(west, east), rng.uniform(south, north), z)
    if (z, x, y) not in session:
        session.append((z, x, y))

# PMTiles: what a client reading by range fetches (each distinct range once: directories are
# cached, as pmtiles.js caches them).
with open(pmt, "rb") as f:
    data = f.read()
seen = set()


def get_bytes(offset, length):
    seen.add((offset, length))
    return data[offset:offset + length]


reader = Reader(get_bytes)
pm_tile_bytes = 0
missing = 0
for z, x, y in session:
    t = reader.get(z, x, y)
    if t is None:
        missing += 1
    else:
        pm_tile_bytes += len(t)
pm_fetched = sum(l for _, l in seen)

# fractile: the same tiles from nginx, decoded in WebAssembly (Node).
conf = os.path.join(work, "nginx.conf")
port = 18391
with open(conf, "w") as f:
    f.write(f"""worker_processes 1; daemon off; error_log {work}/nginx-error.log; pid {work}/nginx.pid;
events {{ worker_connections 64; }}
http {{ access_log off; client_body_temp_path {work}/b; proxy_temp_path {work}/p;
  fastcgi_temp_path {work}/f; uwsgi_temp_path {work}/u; scgi_temp_path {work}/s;
  default_type application/octet-stream;
  server {{ listen 127.0.0.1:{port}; root {work}; }} }}
""")
nginx = subprocess.Popen(["/usr/sbin/nginx", "-c", conf])
time.sleep(1)
try:
    out = subprocess.run(
        ["node", "wasm/tests/session.mjs", "target/wasm-web", f"http://127.0.0.1:{port}/{name}.fra", "512",
         ",".join(f"{z}/{x}/{y}" for z, x, y in session)],
        check=True, capture_output=True, text=True).stdout
finally:
    nginx.terminate()
    nginx.wait()
ours = json.loads(out)
ms = sorted(t["decodeMs"] for t in ours["tiles"])
fra_size, pmt_size, mb_size = os.path.getsize(fra), os.path.getsize(pmt), os.path.getsize(mbtiles)
print(f"\nfractile encode flags: {' '.join(encode_flags) or '(defaults)'}")
print(f"session tiles: {','.join(f'{z}/{x}/{y}' for z, x, y in session)}")
print(f"\nsession: {count} tiles of 512 px at zooms {native - 3}..{native} (the source's cells at {native}), seed {seed}")
print(f"pyramid tiles missing from the session: {missing}\n")
print("| | archive bytes | bytes fetched for the session | requests |")
print("|---|---|---|---|")
print(f"| rio-rgbify terrain-RGB PNG pyramid, PMTiles (z0-{native}) | {pmt_size:,} | {pm_fetched:,} | {len(seen)} |")
print(f"| fractile asset, read by range | {fra_size:,} | {ours['bytesFetched']:,} | {ours['requests']} |")
print(f"| ratio fractile / pyramid | {fra_size / pmt_size:.3f} | {ours['bytesFetched'] / pm_fetched:.3f} | |")
print(f"\nMBTiles {mb_size:,} bytes; raw int16 {raw:,}; encode: fractile {t_fra:.1f} s, rio-rgbify {t_rgb:.1f} s")
print(f"decode in WebAssembly (Node), ms a 512-px tile: p50 {ms[len(ms) // 2]:.1f}, p90 {ms[int(len(ms) * 0.9)]:.1f}, max {ms[-1]:.1f}")
