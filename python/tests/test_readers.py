"""What issue 74 found in the Python package, as a careless user or an attacker meets it: exact
constants and integer types, extreme values, reads coarser than a chunked asset's overviews,
sizes refused before anything is allocated, a 100 GB sparse file, and servers that lie about
ranges or stall. Real data, a real `fractile` binary, servers on loopback; no mocks."""

import http.server
import resource
import socketserver
import subprocess
import threading
import time

import numpy as np
import pytest
import rasterio

import fractile
from conftest import TESTDATA, binary, read_source


@pytest.mark.parametrize("dtype", [np.int16, np.uint16, np.float32, np.float64])
@pytest.mark.parametrize("shape,chunk", [((2, 2), None), ((16, 16), None), ((300, 260), 128)])
def test_constants_read_back_exactly(work, dtype, shape, chunk):
    # 7.25 is no integer: a continuous constant (a chunked one failed "internal").
    value = 7.25 if np.issubdtype(dtype, np.floating) else 7
    path = work / f"constant-{np.dtype(dtype).name}-{shape[0]}.fra"
    report = fractile.encode(np.full(shape, value, dtype), path, chunk=chunk)
    assert report["max_error"] == 0.0
    a = fractile.open(path)
    out = a.read()
    assert out.shape == shape
    # A constant 7 read back as 6 (100 as 99) at every size under the rate's header.
    assert np.all(out == np.float32(value)), np.unique(out)
    finer = a.read(out_shape=(shape[0] * 3, shape[1] * 3))
    assert np.all(finer == np.float32(value)), np.unique(finer)
    values, _ = a.points([0.25, 0.75], [0.5, 0.1])
    assert np.all(values == np.float32(value))


@pytest.mark.parametrize("chunk", [0, 128])
@pytest.mark.parametrize("e", [1.0, 10.0, 2.5])
def test_a_max_error_holds_in_the_arrays_read(work, chunk, e):
    """Issue 73: what read() returns, whole and a window, is within max_error of the source in
    float64, with no float32 slack (a window of max_error=10 came back 10.0005 away), on an
    integer DEM and on one with fractions, in one piece and in chunks."""
    values, transform, crs, nodata, _ = read_source("etopo20.tif")
    fractional = values.astype(np.float32) + np.float32(0.37) * np.sin(np.arange(values.size)).reshape(values.shape).astype(np.float32)
    for name, source in [("integer", values), ("fractional", fractional)]:
        path = work / f"promise-{name}-{chunk}-{e}.fra"
        report = fractile.encode(source, path, transform=transform, crs=crs, max_error=e, chunk=chunk)
        assert report["max_error"] <= e, report
        a = fractile.open(path)
        assert a.meta["chunked"] == (chunk > 0)
        src = source.astype(np.float64)
        whole = a.read().astype(np.float64)
        assert np.abs(whole - src).max() <= e, (name, np.abs(whole - src).max())
        window = a.read(window=(130, 70, 500, 300)).astype(np.float64)
        worst = np.abs(window - src[70:370, 130:630]).max()
        assert worst <= e, (name, worst)


@pytest.mark.parametrize("dtype", [np.int16, np.uint16])
def test_integer_dems_are_exact_at_max_error_zero(work, dtype):
    values, *_ = read_source("jacksboro.tif")
    source = values.astype(dtype)
    path = work / f"exact-{np.dtype(dtype).name}.fra"
    fractile.encode(source, path, max_error=0)
    np.testing.assert_array_equal(fractile.open(path).read(), source.astype(np.float32))


def test_extreme_values_are_refused_or_declared(work):
    values, *_ = read_source("topobathy.tif")
    heights = values.astype(np.float32)
    marked = heights.copy()
    marked[:10, :10] = -3.4028235e38  # GDAL's float nodata, left undeclared
    marked[-1, -1] = 3.4e38
    with pytest.raises(fractile.InputError, match="nodata"):
        fractile.encode(marked, work / "extreme.fra")
    # float64 beyond float32 was infinity, and so nodata, silently.
    huge = heights.astype(np.float64)
    huge[5, 5] = 1e300
    with pytest.raises(fractile.InputError, match="beyond"):
        fractile.encode(huge, work / "huge.fra")
    # Declared, the marker is nodata and the rest within the bound.
    marked[-1, -1] = -3.4028235e38
    path = work / "declared.fra"
    report = fractile.encode(marked, path, nodata=-3.4028235e38, max_error=1)
    out = fractile.open(path).read()
    assert np.isnan(out[:10, :10]).all() and np.isnan(out[-1, -1])
    valid = ~np.isnan(out)
    assert valid.sum() == heights.size - 101
    worst = np.abs(out[valid].astype(np.float64) - heights[valid].astype(np.float64)).max()
    assert worst <= 1.0, worst
    assert report["max_error"] <= 1.0


def test_sizes_are_refused_before_anything_is_made(dem_asset, work):
    a = fractile.open(dem_asset)
    for shape in [(16384, 16384), (1, 2**28)]:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t = time.perf_counter()
        with pytest.raises(ValueError, match="windows"):
            a.read(out_shape=shape)
        assert time.perf_counter() - t < 1.0
        # Nothing of the 9 GB it took was allocated (ru_maxrss is in KiB on Linux).
        assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 100 << 10
    with pytest.raises(ValueError, match="at least 1"):
        a.read(iterations=0)


def test_a_100_gb_sparse_file_is_refused_from_its_length(work):
    path = work / "sparse.fra"
    with open(path, "wb") as f:
        f.write(b"FRACTILE\x05\x00\x01\x06")
        f.truncate(100 << 30)
    t = time.perf_counter()
    with pytest.raises(fractile.AssetError, match="not chunked"):
        fractile.open(path)
    assert time.perf_counter() - t < 5.0
    path.unlink()


def test_reads_coarser_than_the_overviews_are_the_cli_decode(work):
    path = work / "etopo-256.fra"
    fractile.encode_file(TESTDATA / "etopo20.tif", path, chunk=256)
    a = fractile.open(path)
    for rows, cols in [(68, 135), (32, 64), (4, 8)]:
        out = a.read(out_shape=(rows, cols))
        # All NaN before, on etopo20 in chunks of 256 read 8x and more coarser.
        assert np.isfinite(out).all(), (rows, cols)
        tif = work / f"etopo-{cols}.tif"
        subprocess.run(
            [str(binary()), "decode", str(path), "-o", str(tif), "--width", str(cols), "--height", str(rows)],
            check=True,
            capture_output=True,
        )
        with rasterio.open(tif) as src:
            np.testing.assert_array_equal(out, src.read(1))


class _Lying(http.server.BaseHTTPRequestHandler):
    """Answers the length probe right, then lies as the server's `lie` says."""

    lie = "whole"

    def log_message(self, *args):
        pass

    def do_GET(self):
        probe = self.headers.get("Range") == "bytes=0-0"
        try:
            if self.lie == "whole":
                # Ignores ranges: 100 GB said and sent for as long as the reader reads.
                self.send_response(200)
                self.send_header("Content-Length", str(100 << 30))
                self.end_headers()
                while True:
                    self.wfile.write(bytes(1 << 16))
            if probe:
                self.send_response(206)
                self.send_header("Content-Range", "bytes 0-0/5000")
                self.send_header("Content-Length", "1")
                self.end_headers()
                self.wfile.write(b"F")
                return
            self.send_response(206)
            self.send_header("Content-Range", "bytes 0-99/5000")
            self.end_headers()
            while True:
                self.wfile.write(bytes(1 << 16))
        except (BrokenPipeError, ConnectionResetError):
            pass


@pytest.mark.parametrize("lie", ["whole", "long-range"])
def test_remote_readers_take_no_more_than_asked(lie):
    handler = type("Handler", (_Lying,), {"lie": lie})
    with socketserver.ThreadingTCPServer(("127.0.0.1", 0), handler) as httpd:
        httpd.daemon_threads = True
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        url = f"http://127.0.0.1:{httpd.server_address[1]}/asset.fra"
        t = time.perf_counter()
        with pytest.raises(fractile.FractileError):
            fractile.open(url)
        assert time.perf_counter() - t < 20.0
        httpd.shutdown()


def _mutant(data: bytes, k: int, rng) -> bytes:
    """Mutant `k`: bytes flipped anywhere, in the header and table, cut short, or a run of the
    table set to 0xFF (offsets and lengths far past the file)."""
    b = bytearray(data)
    head = min(len(b), 4096)
    kind = k % 4
    if kind == 0:
        for i in rng.integers(0, len(b), rng.integers(1, 9)):
            b[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:
        for i in rng.integers(0, head, rng.integers(1, 5)):
            b[i] ^= 0xFF
    elif kind == 2:
        b = b[: int(rng.integers(0, len(b)))]
    else:
        at = int(rng.integers(12, head - 8))
        b[at : at + 8] = b"\xff" * 8
    return bytes(b)


def test_broken_files_are_errors_not_crashes(work, dem_asset, chunked_asset):
    """Flipped, truncated and crafted files, 100 of each asset: each opens and reads, or raises
    the package's error; none crashes the interpreter, none takes gigabytes."""
    rng = np.random.default_rng(74)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    refused = answered = 0
    for source in (dem_asset, chunked_asset):
        data = source.read_bytes()
        for k in range(100):
            path = work / f"mutant-{source.stem}-{k}.fra"
            path.write_bytes(_mutant(data, k, rng))
            try:
                a = fractile.open(path)
                a.read(out_shape=(64, 64))
                a.read(window=(10, 10, 50, 40))
                a.points([-84.2, 0.5], [36.6, 0.5])
                answered += 1
            except fractile.FractileError:
                refused += 1
            path.unlink()
    assert refused + answered == 200
    assert refused > 40, (refused, answered)
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert grown < 2 << 20, f"{grown >> 10} MiB"


def test_a_grid_readers_would_refuse_is_not_coded_in_one_piece(work):
    """What one reader writes, every reader opens: a DEM in one piece over the readers' decode
    limit (8640 x 8640 was coded for minutes, then refused by `open`) is refused before it is
    coded, and nothing is written; in chunks it is coded."""
    path = work / "one-piece.fra"
    big = np.zeros((7800, 7800), np.int16)
    t = time.perf_counter()
    with pytest.raises(fractile.SettingsError, match="in chunks"):
        fractile.encode(big, path, chunk=0)
    assert time.perf_counter() - t < 10.0
    assert not path.exists()
