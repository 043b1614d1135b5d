#!/usr/bin/env python3
"""Bytes of terrain-RGB tiles as TiTiler makes them against fractile's, on the same tiles.

The walk is the one of `server/tests/precision.rs` and the `tile_png` bench: zooms 10 to 16, N
tiles a zoom along the asset's diagonal (N = 8, then 4). TiTiler's side is rio-tiler (the
library TiTiler serves tiles with): the DEM read at each tile (nearest resampling, its default),
heights coded as terrain-RGB (-10000 m base, 0.1 m steps, the Mapbox encoding TiTiler's
`algorithm=terrainrgb` writes) and rendered as PNG by GDAL with its defaults, the mask as alpha.

    python3 -m venv /tmp/tt && /tmp/tt/bin/pip install rio-tiler
    fractile serve &   # the demo, or --assets DIR holding the asset
    /tmp/tt/bin/python tools/titiler_bytes.py testdata/jacksboro.tif \
        http://127.0.0.1:8080/v1/assets/jacksboro
"""

import json
import math
import sys
import urllib.request

import numpy as np
from rio_tiler.io import Reader
from rio_tiler.utils import render


def terrain_rgb(data):
    """Heights as Mapbox terrain-RGB: (h + 10000) / 0.1 spread over three bytes."""
    v = np.round((data.astype(np.float64) + 10000.0) / 0.1)
    return np.stack([(v // 65536) % 256, (v // 256) % 256, v % 256]).astype("uint8")


def tile_of(z, lon, lat):
    lat_r = math.radians(lat)
    x = int((lon + 180.0) / 360.0 * 2**z)
    y = int((1.0 - math.log(math.tan(lat_r) + 1.0 / math.cos(lat_r)) / math.pi) / 2.0 * 2**z)
    return x, y


def main(dem, asset_url):
    w, s, e, n = json.load(urllib.request.urlopen(asset_url))["bounds"]
    with Reader(dem) as reader:
        for per in (8, 4):
            theirs, ours, rows = 0, 0, []
            for z in range(10, 17):
                zt, zo = 0, 0
                for k in range(per):
                    t = (k + 0.5) / per
                    x, y = tile_of(z, w + t * (e - w), n - t * (n - s))
                    img = reader.tile(x, y, z, tilesize=256)
                    zt += len(render(terrain_rgb(img.data[0]), mask=img.mask, img_format="PNG"))
                    url = f"{asset_url}/tiles/{z}/{x}/{y}.png?encoding=terrainrgb"
                    zo += len(urllib.request.urlopen(url).read())
                rows.append((z, zt / per, zo / per))
                theirs += zt
                ours += zo
            tiles = 7 * per
            print(f"{per} tiles a zoom: rio-tiler {theirs / tiles:.0f} B, "
                  f"fractile {ours / tiles:.0f} B, {ours / theirs:.2f}x")
            for z, a, b in rows:
                print(f"  zoom {z}: {a:.0f} B against {b:.0f} B")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
