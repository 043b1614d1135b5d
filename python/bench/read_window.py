"""Reading a 1024 x 1024 window of a chunked asset from Python against `fractile decode` of the
same window (issue 59's bar: within 1.2x). Prints a markdown table.

    python python/bench/read_window.py [--reps 7] [--bin target/release/fractile] DEM.tif:COPIES ...

Each DEM is mirrored COPIES x COPIES times (each copy the neighbour's mirror image, so that
edges join) to be over twice the chunk size on a side, encoded by `fractile.encode` (the DEM
default, in chunks of 1024), then read both ways, alternately, cold: the CLI is a fresh process
each time (its printed decode time, the asset's header read before it, the file write after it
included), Python opens the asset afresh each time (a new chunk cache key) and times `read`.
"""

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio

import fractile


def mirrored(values: np.ndarray, copies: int) -> np.ndarray:
    row = np.concatenate([values if i % 2 == 0 else values[:, ::-1] for i in range(copies)], axis=1)
    return np.concatenate([row if j % 2 == 0 else row[::-1, :] for j in range(copies)], axis=0)


def cli_ms(binary: str, asset: Path, rect, size: int, out: Path) -> float:
    window = ",".join(f"{v:.9f}" for v in rect)
    r = subprocess.run(
        [binary, "decode", str(asset), "-o", str(out), "--window", window,
         "--width", str(size), "--height", str(size), "--backend", "cpu"],
        check=True, capture_output=True, text=True,
    )
    m = re.search(r"decoded \d+x\d+ .* in ([0-9.]+) ms", r.stderr)
    if not m:
        sys.exit(f"no timing in: {r.stderr}")
    return float(m.group(1))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("dems", nargs="+", help="DEM.tif:COPIES")
    p.add_argument("--reps", type=int, default=7)
    p.add_argument("--bin", default="target/release/fractile")
    a = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for spec in a.dems:
            name, copies = spec.rsplit(":", 1)
            with rasterio.open(name) as src:
                values = mirrored(src.read(1), int(copies))
                nodata = src.nodata
            asset = tmp / (Path(name).stem + ".fra")
            report = fractile.encode(values, asset, nodata=nodata)
            assert report["chunked"], "the bench is for chunked assets: more copies"
            h, w = values.shape
            # A window of 1024 cells at the source's resolution, and one of 512 cells at twice
            # it, both in the middle (chunks of 1024 with their overlaps under them).
            for cells in (1024, 512):
                c0, r0 = (w - cells) // 2 + 37, (h - cells) // 2 + 11
                rect = (c0 / w, r0 / h, (c0 + cells) / w, (r0 + cells) / h)
                cli, py = [], []
                for _ in range(a.reps):
                    cli.append(cli_ms(a.bin, asset, rect, 1024, tmp / "out.tif"))
                    opened = fractile.open(asset)
                    t = time.perf_counter()
                    got = opened.read(window=(c0, r0, cells, cells), out_shape=(1024, 1024))
                    py.append((time.perf_counter() - t) * 1e3)
                    assert got.shape == (1024, 1024) and np.isfinite(got).mean() > 0.99
                c, q = statistics.median(cli), statistics.median(py)
                rows.append((f"{Path(name).name} x{copies} ({w}x{h})", f"{cells}² cells", c, q, q / c))
    print("| asset | window -> 1024² px | CLI decode, median ms | Python read, median ms | Python / CLI |")
    print("|---|---|---:|---:|---:|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.1f} | {r[3]:.1f} | {r[4]:.2f} |")


if __name__ == "__main__":
    main()
