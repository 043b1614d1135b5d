"""Cloud-optimized GeoTIFFs cut from a DEM, for the tests and benches of encodes from a bucket
(issue 78): `python tools/make_cogs.py SOURCE.tif OUT_DIR SIDE [NODATA_EVERY [SCALE [TILE]]]`.

Cuts SOURCE into pieces of SIDE x SIDE cells (the last row and column of pieces narrower),
each written by GDAL's COG driver (rasterio): DEFLATE with the horizontal predictor, internal
tiles of TILE cells (default: SIDE rounded up to 16, one tile a piece), the georeference of
its window. SCALE > 1 first resamples SOURCE SCALE times finer (GDAL's bilinear), for pieces
of the size real DEM tiles have (a test DEM is small). Every NODATA_EVERY-th piece
(0: none) declares nodata -32768 and holds it in its top-left quarter, as real DEM tiles hold
voids. Beside OUT_DIR, OUT_DIR.items.json: a STAC ItemCollection of the pieces (hrefs their
file names) with what the projection, raster and file extensions say of each (`proj:epsg`,
`proj:shape`, `proj:transform`, `raster:bands` data type and nodata, `file:size`), as public
DEM catalogs publish them. Prints one JSON line: the pieces written and their total bytes.
"""

import json
import os
import sys

import numpy as np
import rasterio
from rasterio.enums import Resampling
from rasterio.windows import Window


def main():
    source, out, side = sys.argv[1], sys.argv[2], int(sys.argv[3])
    every = int(sys.argv[4]) if len(sys.argv) > 4 else 0
    scale = int(sys.argv[5]) if len(sys.argv) > 5 else 1
    os.makedirs(out, exist_ok=True)
    block = int(sys.argv[6]) if len(sys.argv) > 6 else max(16, -(-side // 16) * 16)
    written, total, items = 0, 0, []
    with rasterio.open(source) as src:
        height, width = src.height * scale, src.width * scale
        whole = src.read(1, out_shape=(height, width), resampling=Resampling.bilinear)
        transform = src.transform * src.transform.scale(1 / scale, 1 / scale)
        rows = -(-height // side)
        cols = -(-width // side)
        for r in range(rows):
            for c in range(cols):
                w = Window(c * side, r * side, min(side, width - c * side),
                           min(side, height - r * side))
                data = whole[r * side:r * side + int(w.height), c * side:c * side + int(w.width)]
                profile = {
                    "driver": "COG", "width": int(w.width), "height": int(w.height),
                    "count": 1, "dtype": data.dtype.name, "crs": src.crs,
                    "transform": rasterio.windows.transform(w, transform), "compress": "DEFLATE",
                    "predictor": 2, "blocksize": block, "overviews": "NONE",
                }
                k = r * cols + c
                if every and k % every == 0 and np.issubdtype(data.dtype, np.signedinteger):
                    data = data.copy()
                    data[: data.shape[0] // 2, : data.shape[1] // 2] = -32768
                    profile["nodata"] = -32768
                path = os.path.join(out, f"piece-{r:03d}-{c:03d}.tif")
                with rasterio.open(path, "w", **profile) as dst:
                    dst.write(data, 1)
                written += 1
                size = os.path.getsize(path)
                total += size
                band = {"data_type": data.dtype.name}
                if "nodata" in profile:
                    band["nodata"] = profile["nodata"]
                items.append({
                    "type": "Feature", "stac_version": "1.0.0", "id": os.path.basename(path),
                    "properties": {
                        "proj:epsg": src.crs.to_epsg(),
                        "proj:shape": [int(w.height), int(w.width)],
                        "proj:transform": list(profile["transform"])[:6],
                    },
                    "assets": {"data": {
                        "href": os.path.basename(path), "roles": ["data"],
                        "type": "image/tiff; application=geotiff; profile=cloud-optimized",
                        "file:size": size, "raster:bands": [band],
                    }},
                })
    with open(out.rstrip("/") + ".items.json", "w") as f:
        json.dump({"type": "FeatureCollection", "features": items}, f)
    print(json.dumps({"pieces": written, "bytes": total}))


if __name__ == "__main__":
    main()
