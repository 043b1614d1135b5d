"""GDAL's resampling as the reference for a mosaic of inputs on different grids (issue 78).

`python tools/resample_reference.py make SOURCE.tif DIR`: writes DIR/a.tif (the west half of
SOURCE, on its grid) and DIR/b.tif (the east part, resampled by GDAL to cells 1.5 times as
wide, its origin 0.37 of a cell off: another grid of the same CRS), and DIR/ref.tif: b.tif
brought back onto a.tif's grid by rasterio's reproject (bilinear), float32, NaN outside.

`python tools/resample_reference.py compare DIR/ref.tif DECODED.tif BORDER`: the largest
|decoded - ref| over ref's cells at least BORDER cells inside b's footprint and east of
a.tif (where the mosaic's first input does not win), as one JSON line.
"""

import json
import sys

import numpy as np
import rasterio
from rasterio.transform import Affine
from rasterio.warp import Resampling, reproject
from rasterio.windows import Window


def make(source, out):
    with rasterio.open(source) as src:
        data = src.read(1).astype("float32")
        t = src.transform
        crs = src.crs
    h, w = data.shape
    half = w // 2
    prof = {"driver": "GTiff", "count": 1, "dtype": "float32", "crs": crs}
    with rasterio.open(f"{out}/a.tif", "w", width=half, height=h, transform=t, **prof) as d:
        d.write(data[:, :half], 1)
    # b: columns from half - 10 on, on a grid 1.5 times coarser, 0.37 of a cell off.
    x0 = t.c + (half - 10 + 0.37) * t.a
    bt = Affine(t.a * 1.5, 0, x0, 0, t.e * 1.5, t.f)
    bw, bh = int((w - half + 10) / 1.5) - 1, int(h / 1.5) - 1
    b = np.full((bh, bw), np.nan, dtype="float32")
    reproject(data, b, src_transform=t, src_crs=crs, dst_transform=bt, dst_crs=crs,
              resampling=Resampling.average)
    with rasterio.open(f"{out}/b.tif", "w", width=bw, height=bh, transform=bt, **prof) as d:
        d.write(b, 1)
    # b back on a's grid, over b's footprint.
    cols = int(np.ceil((x0 + bw * bt.a - t.c) / t.a))
    ref = np.full((h, cols), np.nan, dtype="float32")
    reproject(b, ref, src_transform=bt, src_crs=crs, dst_transform=t, dst_crs=crs,
              resampling=Resampling.bilinear, src_nodata=np.nan, dst_nodata=np.nan)
    with rasterio.open(f"{out}/ref.tif", "w", width=cols, height=h, transform=t,
                       nodata=np.nan, **prof) as d:
        d.write(ref, 1)
    print(json.dumps({"a": [half, h], "b": [bw, bh], "ref": [cols, h]}))


def compare(ref_path, decoded_path, border):
    with rasterio.open(ref_path) as r, rasterio.open(decoded_path) as d:
        ref, t = r.read(1), r.transform
        dec, dt = d.read(1), d.transform
        a_cols = int(sys.argv[5]) if len(sys.argv) > 5 else 0
    # The decoded mosaic's column and row of ref's cell (0, 0): both on a's grid.
    dx = round((t.c - dt.c) / t.a)
    dy = round((t.f - dt.f) / t.e)
    # b's footprint on a's grid: where ref holds values, less BORDER cells each way.
    valid = np.isfinite(ref)
    rows = np.where(valid.any(axis=1))[0]
    cols = np.where(valid.any(axis=0))[0]
    r0, r1 = rows[0] + border, rows[-1] - border
    c0, c1 = max(cols[0] + border, a_cols + border), cols[-1] - border
    worst, n = 0.0, 0
    for y in range(r0, r1 + 1):
        for x in range(c0, c1 + 1):
            want = float(ref[y, x])
            got = float(dec[y + dy, x + dx])
            if np.isfinite(want):
                worst = max(worst, abs(got - want))
                n += 1
    print(json.dumps({"cells": n, "max_abs_diff": worst}))


if __name__ == "__main__":
    if sys.argv[1] == "make":
        make(sys.argv[2], sys.argv[3])
    else:
        compare(sys.argv[2], sys.argv[3], int(sys.argv[4]))
