"""The Python package against real data: round trips within the bounds it reports, rasterio's
georeference, the command line's decode, the server's points, and assets read by range from
SeaweedFS (s3://) and from the server (http://)."""

import subprocess
import threading
import time

import numpy as np
import pytest
import rasterio
import rasterio.warp
from rasterio.windows import Window

import fractile
from conftest import TESTDATA, binary, cell_centres, read_source

SLACK = 1e-3  # float32 rounding of heights of a few hundred metres


def lonlat_centres(transform, crs, width, height):
    xs, ys = cell_centres(transform, width, height)
    if crs.is_geographic:
        return xs, ys
    lon, lat = rasterio.warp.transform(crs, "EPSG:4326", xs, ys)
    return np.asarray(lon), np.asarray(lat)


@pytest.mark.parametrize("name", ["jacksboro.tif", "etopo20.tif", "topobathy.tif", "jacksboro-utm.tif"])
def test_dem_round_trip_within_bound_at_every_cell(work, name):
    values, transform, crs, nodata, _ = read_source(name)
    path = work / f"rt-{name}.fra"
    report = fractile.encode(values, path, transform=transform, crs=crs, nodata=nodata)
    assert report["codec"] == "projected" and report["ratio"] > 5
    a = fractile.open(path)
    h, w = values.shape
    valid = values != nodata if nodata is not None else np.isfinite(values)
    source = values.astype(np.float64)

    lon, lat = lonlat_centres(transform, crs, w, h)
    got, bounds = a.points(lon, lat)
    got, bounds = got.reshape(h, w), bounds.reshape(h, w)
    # Every valid cell's value within the bound answered with it.
    err = np.abs(got[valid] - source[valid])
    assert np.all(np.isfinite(bounds[valid]))
    assert np.all(err <= bounds[valid] + SLACK), f"worst excess {np.max(err - bounds[valid])}"
    # Nodata stays nodata.
    assert np.all(np.isnan(got[~valid]))

    grid = a.read()
    assert grid.shape == (h, w) and grid.dtype == np.float32
    assert np.all(np.isnan(grid[~valid]))
    # The reported bound holds in the array read, with no float32 slack (issue 73).
    assert np.max(np.abs(grid[valid].astype(np.float64) - source[valid])) <= report["max_error"]


def test_chunked_round_trip_within_bound(chunked_asset):
    values, transform, crs, nodata, _ = read_source("jacksboro-utm.tif")
    a = fractile.open(chunked_asset)
    assert a.meta["chunked"]
    h, w = values.shape
    valid = values != nodata
    lon, lat = lonlat_centres(transform, crs, w, h)
    got, bounds = a.points(lon, lat)
    got, bounds = got.reshape(h, w), bounds.reshape(h, w)
    err = np.abs(got[valid] - values[valid])
    assert np.all(err <= bounds[valid] + SLACK), f"worst excess {np.max(err - bounds[valid])}"
    assert np.all(np.isnan(got[~valid]))


@pytest.mark.parametrize("name", ["camera.png", "astronaut.png"])
def test_image_round_trip(work, name):
    with rasterio.open(TESTDATA / name) as src:
        bands = src.read()
    array = bands[0] if bands.shape[0] == 1 else np.moveaxis(bands[:3], 0, -1).copy()
    path = work / f"rt-{name}.fra"
    seen = []
    report = fractile.encode(array, path, target_bpp=1.0, progress=lambda d, t: seen.append((d, t)))
    # The default for images (issue 77), as `fractile encode`'s.
    assert report["codec"] == "projected"
    assert report["bpp"] <= 1.0 + 1e-6
    assert seen and seen[-1][0] == seen[-1][1], "the progress callback saw the end"
    a = fractile.open(path)
    got = a.read()
    assert got.shape == array.shape
    # The decode the encoder measured: the same PSNR and largest error.
    err = got.astype(np.float64) - array
    psnr = 10 * np.log10(255.0**2 / np.mean(err**2))
    assert abs(psnr - report["psnr"]) < 0.2, (psnr, report["psnr"])
    assert np.max(np.abs(err)) <= report["max_error"] + 0.5
    # Unit coordinates: the values at cell centres, with a bound on the attractor.
    values, bounds = a.points([0.25, 0.75], [0.5, 0.5])
    assert values.shape == ((2,) if array.ndim == 2 else (2, 3))
    assert np.all(np.isfinite(values)) and np.all(bounds >= 0)


@pytest.mark.parametrize("name", ["jacksboro.tif", "jacksboro-utm.tif"])
def test_georeference_is_rasterios(work, name):
    path = work / f"geo-{name}.fra"
    fractile.encode_file(TESTDATA / name, path)
    a = fractile.open(path)
    with rasterio.open(TESTDATA / name) as src:
        p = a.profile
        assert p["transform"].almost_equals(src.transform, precision=1e-12)
        assert rasterio.crs.CRS.from_user_input(p["crs"]) == src.crs
        assert (p["width"], p["height"], p["count"]) == (src.width, src.height, src.count)
        assert np.allclose(a.meta["bounds"], tuple(src.bounds), rtol=0, atol=1e-9)
        assert a.meta["crs"] == f"EPSG:{src.crs.to_epsg()}"
        # What rasterio writes from the profile is georeferenced as the source.
        out = work / f"geo-{name}.tif"
        with rasterio.open(out, "w", **p) as dst:
            dst.write(a.read(), 1)
        with rasterio.open(out) as back:
            assert back.transform.almost_equals(src.transform, precision=1e-12)
            assert back.crs == src.crs


def cli_decode(asset, out, *args):
    subprocess.run(
        [str(binary()), "decode", str(asset), "-o", str(out), "--backend", "cpu", *args],
        check=True,
        capture_output=True,
    )
    with rasterio.open(out) as r:
        # The CLI writes nodata cells as the source's nodata value; Python's are NaN.
        values = r.read(1)
        if r.nodata is not None:
            values[values == r.nodata] = np.nan
        return values


@pytest.mark.parametrize("which", ["dem_asset", "chunked_asset"])
def test_read_at_4x_is_the_cli_decode(work, request, which):
    asset = request.getfixturevalue(which)
    a = fractile.open(asset)
    w, h = a.meta["width"], a.meta["height"]
    expected = cli_decode(asset, work / f"{which}-x4.tif", "--scale", "4")
    got = a.read(out_shape=(4 * h, 4 * w))
    assert got.shape == expected.shape == (4 * h, 4 * w)
    np.testing.assert_array_equal(got, expected)
    # A window, finer than the source: the same as `--window` at the same size.
    window = Window(col_off=100, row_off=50, width=64, height=48)
    u = (100 / w, 50 / h, 164 / w, 98 / h)
    expected = cli_decode(
        asset, work / f"{which}-win.tif", "--window", ",".join(f"{v:.9}" for v in u),
        "--width", "512", "--height", "384",
    )
    got = a.read(window=window, out_shape=(384, 512))
    assert np.nanmax(np.abs(got - expected)) < 1e-3
    assert np.mean(np.isnan(got) == np.isnan(expected)) == 1.0


def test_points_are_the_servers(server, dem_asset, chunked_asset):
    client = fractile.Client(server.url)
    rng = np.random.default_rng(7)
    for id, path in [("jacksboro", dem_asset), ("utm", chunked_asset)]:
        a = fractile.open(path)
        west, south, east, north = a.meta["lonlat_bounds"]
        lon = rng.uniform(west, east, 300)
        lat = rng.uniform(south, north, 300)
        ours = a.points(lon, lat)
        theirs = client.points(id, lon.tolist(), lat.tolist())
        np.testing.assert_array_equal(ours[0], theirs[0])
        np.testing.assert_array_equal(ours[1], theirs[1])
        assert np.isfinite(ours[0]).sum() > 100
    summary = client.asset("jacksboro")
    assert summary["width"] == 403 and summary["codec"] == "projected"
    tile = client.tile("jacksboro", 10, 271, 399)
    assert tile.values.shape == (256, 256) and np.isfinite(tile.values).any()
    assert tile.error_bound is not None and tile.error_bound > 0
    region = client.region("jacksboro", [-84.3, 36.5, -84.2, 36.6], 64, 48)
    assert region.values.shape == (48, 64) and np.all(np.isfinite(region.values))
    with pytest.raises(fractile.ClientError) as e:
        client.asset("no-such-asset")
    assert e.value.status == 404


@pytest.mark.parametrize("id", ["jacksboro", "utm"])
def test_open_over_http_reads_by_range(server, id, dem_asset, chunked_asset):
    local = fractile.open(dem_asset if id == "jacksboro" else chunked_asset)
    remote = fractile.open(fractile.Client(server.url).file_url(id))
    assert remote.meta["width"] == local.meta["width"]
    assert remote.meta["chunked"] == local.meta["chunked"]
    np.testing.assert_array_equal(remote.read(out_shape=(200, 220)), local.read(out_shape=(200, 220)))
    lon, lat = [-84.2, -84.3], [36.6, 36.5]
    np.testing.assert_array_equal(remote.points(lon, lat)[0], local.points(lon, lat)[0])


def test_open_from_s3(weed, chunked_asset, dem_asset, monkeypatch):
    weed.put("assets/utm.fra", chunked_asset.read_bytes())
    weed.put("assets/jacksboro.fra", dem_asset.read_bytes())
    for k, v in {
        "AWS_ENDPOINT_URL": weed.endpoint,
        "AWS_ACCESS_KEY_ID": "fractile",
        "AWS_SECRET_ACCESS_KEY": "fractile-test",
        "AWS_REGION": "us-east-1",
        "AWS_ALLOW_HTTP": "true",
    }.items():
        monkeypatch.setenv(k, v)
    for key, path in [("utm", chunked_asset), ("jacksboro", dem_asset)]:
        remote = fractile.open(f"s3://fractile/assets/{key}.fra")
        local = fractile.open(path)
        np.testing.assert_array_equal(remote.read(), local.read())
    with pytest.raises(fractile.InputError):
        fractile.open("s3://fractile/assets/missing.fra")
    # The store goes away after the header was read: the chunks' reads fail as unavailable
    # (worth trying again), not as NaN arrays or a corrupt asset. Last: it ends the store.
    opened = fractile.open("s3://fractile/assets/utm.fra")
    weed.stop()
    with pytest.raises(fractile.UnavailableError):
        opened.read()


def test_errors_are_typed(work, dem_asset):
    bad = work / "corrupt.fra"
    data = bytearray(dem_asset.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad.write_bytes(bytes(data))
    with pytest.raises(fractile.AssetError):
        fractile.open(bad)
    truncated = work / "truncated.fra"
    truncated.write_bytes(dem_asset.read_bytes()[:100])
    with pytest.raises(fractile.AssetError):
        fractile.open(truncated)
    with pytest.raises(fractile.InputError):
        fractile.open(work / "absent.fra")
    with pytest.raises(fractile.InputError):
        fractile.encode(np.full((32, 32), np.nan, np.float32), work / "nan.fra")
    with pytest.raises(fractile.SettingsError):
        fractile.encode(np.zeros((32, 32), np.int16), work / "x.fra", codec="jpeg")
    with pytest.raises(fractile.SettingsError):
        fractile.encode(np.zeros((32, 32), np.int16), work / "x.fra", codec="quadtree-pifs", max_error=3)
    with pytest.raises(TypeError):
        fractile.encode(np.zeros((4, 32, 32), np.complex64), work / "x.fra")
    a = fractile.open(dem_asset)
    with pytest.raises(ValueError):
        a.read(window=(400, 0, 10, 10))
    with pytest.raises(ValueError):
        a.read(out_shape=(1 << 15, 1 << 15))
    with pytest.raises(fractile.UnavailableError):
        fractile.open("http://127.0.0.1:9/nothing.fra")
    assert issubclass(fractile.UnavailableError, fractile.FractileError)


def test_decoding_releases_the_gil(dem_asset):
    a = fractile.open(dem_asset)
    done = threading.Event()

    def decode():
        a.read(out_shape=(3000, 3000), method="continuous")
        done.set()

    t = threading.Thread(target=decode)
    start = time.perf_counter()
    t.start()
    ticks = 0
    while not done.is_set():
        ticks += 1
        time.sleep(0.001)
    t.join()
    elapsed = time.perf_counter() - start
    # Held, the GIL would let this loop run about once in the whole decode.
    assert elapsed > 0.05 and ticks > 10, (elapsed, ticks)
