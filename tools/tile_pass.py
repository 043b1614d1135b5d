"""Every tile over an asset at zooms ZMIN..ZMAX, each requested once (shuffled), CONCURRENCY in
flight, against a running server; prints throughput and latency percentiles, overall and per
zoom. With a fresh server (and cache) per pass, nothing is cached: not the tiles, not the
coarse decodes a zoom's tiles share. Standard library only.

    python3 tools/tile_pass.py http://127.0.0.1:8080/v1/assets/ID ZMIN ZMAX CONCURRENCY [SEED]
"""
import json, math, random, sys, time, urllib.request, concurrent.futures as cf
base, zmin, zmax, conc = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
random.seed(int(sys.argv[5]) if len(sys.argv) > 5 else 1)
with urllib.request.urlopen(base) as r:
    west, south, east, north = json.load(r)["bounds"]
def tile_of(lon, lat, z):
    n = 1 << z
    lat = max(min(lat, 85.0511), -85.0511)
    x = int((lon + 180.0) / 360.0 * n)
    y = int((1.0 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2.0 * n)
    return min(max(x, 0), n - 1), min(max(y, 0), n - 1)
tiles = []
for z in range(zmin, zmax + 1):
    (x0, y0), (x1, y1) = tile_of(west, north, z), tile_of(east, south, z)
    tiles += [(z, x, y) for x in range(x0, x1 + 1) for y in range(y0, y1 + 1)]
random.shuffle(tiles)
def get(t):
    z, x, y = t
    t0 = time.perf_counter()
    with urllib.request.urlopen(f"{base}/tiles/{z}/{x}/{y}.png?encoding=terrainrgb") as r:
        r.read(); status = r.status
    return z, time.perf_counter() - t0, status
t0 = time.perf_counter()
with cf.ThreadPoolExecutor(conc) as ex:
    res = list(ex.map(get, tiles))
wall = time.perf_counter() - t0
lat = sorted(r[1] for r in res)
pct = lambda l, p: l[min(len(l) - 1, int(p * len(l)))] * 1000
print(f"{len(res)} tiles, {sum(1 for r in res if r[2] != 200)} not 200, wall {wall:.2f} s, {len(res)/wall:.1f}/s, p50 {pct(lat, 0.5):.1f} ms, p99 {pct(lat, 0.99):.1f} ms")
for z in range(zmin, zmax + 1):
    l = sorted(r[1] for r in res if r[0] == z)
    if l: print(f"  zoom {z}: {len(l)} tiles, p50 {pct(l, 0.5):.1f} ms, p99 {pct(l, 0.99):.1f} ms")
