"""GDAL's resampling as the reference for a mosaic of inputs on different grids (issue 78).

`python tools/resample_reference.py make SOURCE.tif DIR`: writes DIR/a.tif (the west half of
SOURCE, on its grid) and DIR/b.tif (the east part, resampled by GDAL to cells 1.5 times as
wide, its origin 0.37 of a cell off: another grid of the same CRS), and DIR/ref.tif: b.tif
brought back onto a.tif's grid by rasterio's reproject (bilinear), float32, NaN outside.

`python tools/resample_reference.py utm SOURCE.tif UTM.tif DIR`: writes DIR/a.tif (SOURCE's
west half on a longitude/latitude grid of half its cells: the finest input, whose grid the
mosaic takes) and DIR/ref.tif: UTM.tif (another CRS) brought onto that grid by rasterio's
reproject, bilinear, with the exact transform (tolerance 0), and DIR/bilinear.tif: the
textbook bilinear between the four UTM cells around each target centre, the centre taken to
UTM by PROJ (rasterio's `transform`). GDAL's warper departs from the textbook bilinear here by
up to metres (a rotated grid: it seems to widen its kernel), so bilinear.tif is the reference
that holds to float precision and ref.tif the peer's figure.

`python tools/resample_reference.py compare DIR/ref.tif DECODED.tif BORDER`: the largest
|decoded - ref| over ref's cells at least BORDER cells inside b's footprint and east of
a.tif (where the mosaic's first input does not win), as one JSON line.
"""

import json
import sys

import numpy as np
import rasterio
from rasterio.transform import Affine
from rasterio.warp import Resampling, reproject, transform
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


def utm(source, projected, out):
    with rasterio.open(source) as src:
        data = src.read(1).astype("float32")
        st, crs = src.transform, src.crs
    sh, sw = data.shape
    t = Affine(st.a / 2, 0, st.c, 0, st.e / 2, st.f)
    h, w = 2 * sh, 2 * sw
    half = w // 2
    fine = np.full((h, half), np.nan, dtype="float32")
    reproject(data, fine, src_transform=st, src_crs=crs, dst_transform=t, dst_crs=crs,
              resampling=Resampling.bilinear)
    prof = {"driver": "GTiff", "count": 1, "dtype": "float32", "crs": crs}
    with rasterio.open(f"{out}/a.tif", "w", width=half, height=h, transform=t, **prof) as d:
        d.write(fine, 1)
    with rasterio.open(projected) as p:
        pdata = p.read(1).astype("float32")
        nodata = p.nodata
        if nodata is not None:
            pdata[pdata == nodata] = np.nan
        ref = np.full((h, w), np.nan, dtype="float32")
        reproject(pdata, ref, src_transform=p.transform, src_crs=p.crs, dst_transform=t,
                  dst_crs=crs, resampling=Resampling.bilinear, src_nodata=np.nan,
                  dst_nodata=np.nan, tolerance=0)
        # The textbook bilinear at the same points, through PROJ's transform (rasterio's):
        # GDAL's warper departs from it on this rotated grid (it widens its kernel).
        xs, ys = np.meshgrid(t.c + (np.arange(w) + 0.5) * t.a, t.f + (np.arange(h) + 0.5) * t.e)
        px, py = transform(crs, p.crs, xs.ravel().tolist(), ys.ravel().tolist())
        pt = p.transform
        sx = (np.array(px) - pt.c) / pt.a - 0.5
        sy = (np.array(py) - pt.f) / pt.e - 0.5
        i, j = np.floor(sx).astype(int), np.floor(sy).astype(int)
        fx, fy = sx - i, sy - j
        ph, pw = pdata.shape
        inside = (i >= 0) & (j >= 0) & (i + 1 < pw) & (j + 1 < ph)
        i, j = np.where(inside, i, 0), np.where(inside, j, 0)
        bil = ((1 - fx) * (1 - fy) * pdata[j, i] + fx * (1 - fy) * pdata[j, i + 1]
               + (1 - fx) * fy * pdata[j + 1, i] + fx * fy * pdata[j + 1, i + 1])
        bil = np.where(inside, bil, np.nan).reshape(h, w).astype("float32")
    for name, grid in [("ref", ref), ("bilinear", bil)]:
        with rasterio.open(f"{out}/{name}.tif", "w", width=w, height=h, transform=t,
                           nodata=np.nan, **prof) as d:
            d.write(grid, 1)
    print(json.dumps({"a": [half, h], "ref": [w, h]}))


def coarse(source, out, factor, shift):
    """DIR/grid.tif: a grid FACTOR times coarser than SOURCE's, SHIFT of a coarse cell off
    (a few cells: it only names the grid), and DIR/ref.tif: SOURCE averaged onto that grid
    over SOURCE's extent by rasterio's reproject (Resampling.average)."""
    with rasterio.open(source) as src:
        data = src.read(1).astype("float32")
        t, crs = src.transform, src.crs
    h, w = data.shape
    ct = Affine(t.a * factor, 0, t.c + shift * t.a * factor, 0, t.e * factor, t.f)
    prof = {"driver": "GTiff", "count": 1, "dtype": "float32", "crs": crs}
    with rasterio.open(f"{out}/grid.tif", "w", width=4, height=4, transform=ct, **prof) as d:
        d.write(np.zeros((4, 4), dtype="float32"), 1)
    cw, ch = int(w / factor) - 1, int(h / factor) - 1
    ref = np.full((ch, cw), np.nan, dtype="float32")
    reproject(data, ref, src_transform=t, src_crs=crs, dst_transform=ct, dst_crs=crs,
              resampling=Resampling.average, dst_nodata=np.nan)
    with rasterio.open(f"{out}/ref.tif", "w", width=cw, height=ch, transform=ct, nodata=np.nan,
                       **prof) as d:
        d.write(ref, 1)
    print(json.dumps({"ref": [cw, ch]}))


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
    elif sys.argv[1] == "coarse":
        coarse(sys.argv[2], sys.argv[3], float(sys.argv[4]), float(sys.argv[5]))
    elif sys.argv[1] == "utm":
        utm(sys.argv[2], sys.argv[3], sys.argv[4])
    else:
        compare(sys.argv[2], sys.argv[3], int(sys.argv[4]))
