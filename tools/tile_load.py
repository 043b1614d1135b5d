"""Random uncached tiles against a running server: N distinct tiles, the zoom of each drawn
uniformly from 0 to ZMAX, CONCURRENCY in flight; prints throughput and latency percentiles,
overall and per zoom. Standard library only.

    python3 tools/tile_load.py http://127.0.0.1:8080/v1/assets/ID N CONCURRENCY ZMAX [SEED]

A first argument with `{z}`, `{x}` and `{y}` is a URL template instead (another tile server,
such as TiTiler: 'http://127.0.0.1:8000/cog/tiles/WebMercatorQuad/{z}/{x}/{y}.png?url=...').
"""
import random, sys, time, urllib.request, concurrent.futures as cf
base, n, conc, zmax = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
random.seed(int(sys.argv[5]) if len(sys.argv) > 5 else 1)
tiles = set()
while len(tiles) < n:
    z = random.randint(0, zmax)
    tiles.add((z, random.randrange(1 << z), random.randrange(1 << z)))
tiles = list(tiles); random.shuffle(tiles)
def get(t):
    z, x, y = t
    t0 = time.perf_counter()
    url = (base.format(z=z, x=x, y=y) if "{z}" in base
           else f"{base}/tiles/{z}/{x}/{y}.png?encoding=terrainrgb")
    with urllib.request.urlopen(url) as r:
        body = r.read(); status = r.status
    return z, time.perf_counter() - t0, status, len(body)
t0 = time.perf_counter()
with cf.ThreadPoolExecutor(conc) as ex:
    res = list(ex.map(get, tiles))
wall = time.perf_counter() - t0
lat = sorted(r[1] for r in res)
pct = lambda p: lat[min(len(lat) - 1, int(p * len(lat)))] * 1000
print(f"{len(res)} tiles, {sum(1 for r in res if r[2] != 200)} not 200, wall {wall:.1f} s, {len(res)/wall:.1f}/s, p50 {pct(0.5):.1f} ms, p90 {pct(0.9):.1f} ms, p99 {pct(0.99):.1f} ms, max {lat[-1]*1000:.1f} ms")
for z in range(zmax + 1):
    l = sorted(r[1] for r in res if r[0] == z)
    if l: print(f"  zoom {z}: {len(l)} tiles, p50 {l[len(l)//2]*1000:.1f} ms, p99 {l[min(len(l)-1, int(0.99*len(l)))]*1000:.1f} ms")
