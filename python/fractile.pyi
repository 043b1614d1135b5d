"""fractile: images and terrains compressed as fractals (iterated function systems).

Read and write fractile assets as NumPy arrays, with rasterio's georeference::

    import fractile
    a = fractile.open("jacksboro.fra")          # a path, s3://bucket/key or http(s)://
    heights = a.read(out_shape=(1024, 1024))    # any resolution, finer than the source too
    values, bounds = a.points([-98.1], [33.2])  # every value within its bound

Decoding releases the GIL and runs on the library's own threads.
"""

from os import PathLike
from typing import Any, Callable, Optional, Sequence, Tuple, Union, final

import numpy as np
import numpy.typing as npt

__version__: str

class FractileError(Exception):
    """Every error fractile raises."""

class InputError(FractileError):
    """The input array or file cannot be encoded (empty, all nodata, a dtype or shape not taken)."""

class SettingsError(FractileError):
    """The settings are inconsistent (an unknown codec, a rate the codec does not take)."""

class AssetError(FractileError):
    """An asset is corrupt, truncated, or of an unknown version or codec."""

class OutputError(FractileError):
    """An output could not be written."""

class UnavailableError(FractileError):
    """An asset's bytes could not be read now (a store or server down, a file gone): trying again may succeed."""

class ClientError(FractileError):
    """The server answered with an error or could not be reached."""

    status: Optional[int]
    """The HTTP status, where the server answered."""
    code: Optional[str]
    """The server's error code (``asset_not_found``, ...), where it gave one."""

_Progress = Callable[[int, int], Any]
"""Called as ``progress(done, total)`` while an encode runs (at most every 0.2 s)."""

_Coordinates = Union[float, Sequence[float], npt.NDArray[np.float64]]

def encode(
    array: npt.NDArray[Any],
    path: Union[str, PathLike[str]],
    *,
    transform: Optional[Any] = None,
    crs: Optional[Union[int, str, Any]] = None,
    nodata: Optional[float] = None,
    target_bpp: Optional[float] = None,
    max_error: Optional[float] = None,
    codec: Optional[str] = None,
    chunk: Optional[int] = None,
    progress: Optional[_Progress] = None,
) -> dict[str, Any]:
    """Encodes an array into the asset file ``path``.

    ``array``: a 2-D int16, uint16, float32 or float64 array is a height field (a DEM); a 2-D
    uint8 array a grey image; a ``(rows, cols, 3)`` uint8 array a colour image. NaN cells and
    cells equal to ``nodata`` have no data.

    ``transform`` (an ``affine.Affine`` or its six numbers ``a, b, c, d, e, f``, north-up) and
    ``crs`` (an EPSG code, ``"EPSG:4326"`` or a rasterio ``CRS``) georeference it, as
    rasterio's ``dataset.transform`` and ``dataset.crs``.

    ``codec``: ``"projected"`` (the default), ``"quadtree-pifs"`` (the seed's method), ``"fis-bilinear"``, ``"fis-rect"``, ``"fis-rect-global"``, ``"psa2d-rect"``,
    ``"psa2d-tri"``, or any other name ``fractile encode --codec`` takes (the codec's registry);
    a keyword the codec does not read is refused (``SettingsError``). The rate:
    ``target_bpp`` bits a cell (the height-field default is 0.8, bounded: every cell within
    the bound it reports; an image's 0.75) or, for the projected codec,
    ``max_error`` in value units (0: lossless, for integer samples). ``chunk``: cells a side
    of the chunks a large grid is coded in (default 1024 for grids over 2048 a side; 0 codes
    it whole, refused with ``SettingsError`` where readers would not open the file).

    Values beyond 1e30 in magnitude are refused (``InputError``): +-3.4e38 is usually a nodata
    marker, to be given as ``nodata``.

    Returns what the encoder measured: ``bytes``, ``ratio``, ``bpp``, ``psnr``, ``rmse``,
    ``max_error``, ``seconds``, ``codec``, ``chunked``.
    """

def encode_file(
    source: Union[str, PathLike[str]],
    path: Union[str, PathLike[str]],
    *,
    target_bpp: Optional[float] = None,
    max_error: Optional[float] = None,
    codec: Optional[str] = None,
    chunk: Optional[int] = None,
    progress: Optional[_Progress] = None,
) -> dict[str, Any]:
    """Encodes a raster file (GeoTIFF, 16-bit PNG, PNG, JPEG) of any size into ``path``,
    reading a band of rows at a time when it is coded in chunks; georeference and nodata are
    the file's. Keywords and result as :func:`encode`."""

def open(location: Union[str, PathLike[str]]) -> Asset:
    """Opens an asset: a path, ``s3://bucket/key`` (credentials and endpoint from the AWS
    variables, as the server's) or ``http(s)://`` (read by range, e.g. a server's
    ``/v1/assets/{id}/file``). A chunked asset is opened by its header; its chunks are read
    when a request touches them."""

@final
class Asset:
    """An opened asset."""

    @property
    def meta(self) -> dict[str, Any]:
        """``width``, ``height``, ``channels``, ``kind``, ``codec``, ``chunked``, ``units``,
        ``value_range``, ``nodata``, ``crs`` (``"EPSG:n"``), ``transform`` (rasterio's six
        numbers), ``bounds`` (left, bottom, right, top in CRS units), ``lonlat_bounds``
        (west, south, east, north), ``errors`` (``rmse``, ``psnr``, ``max_error`` as the
        encoder measured; ``max_contrast``, ``seed_bound`` of the operator), ``encoder``,
        ``location``."""

    @property
    def profile(self) -> dict[str, Any]:
        """Keywords for ``rasterio.open(path, "w", **asset.profile)``: a float32 GeoTIFF of the
        asset's size, channels, CRS and transform."""

    def read(
        self,
        window: Optional[Any] = None,
        out_shape: Optional[Sequence[int]] = None,
        iterations: Optional[int] = None,
        method: str = "auto",
    ) -> npt.NDArray[np.float32]:
        """The asset as float32, NaN on nodata: ``window`` (a rasterio ``Window``,
        ``(col_off, row_off, width, height)`` in source cells, or rasterio's
        ``((row_start, row_stop), (col_start, col_stop))``; default all of it) at
        ``out_shape`` (``(rows, cols)``; default the window's cells; any size). Shape
        ``(rows, cols)``, or ``(rows, cols, 3)`` for colour. ``iterations``: exactly this many
        (default: until converged; at least 1). ``method``: ``"auto"``, ``"discrete"``,
        ``"continuous"``. Equal to ``fractile decode`` of the same window and size on the CPU.
        A read whose decode would take over 3 GiB (about 40 bytes a pixel) is refused with
        ``ValueError`` before anything is made: read such an asset in windows."""

    def points(
        self, lon: _Coordinates, lat: _Coordinates, iterations: Optional[int] = None
    ) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """``(values, bounds)`` at ``(lon, lat)`` (unit ``(x, y)`` for assets without a
        georeference): values ``(n,)`` (``(n, 3)`` for colour), NaN outside the asset; each
        bound in value units on |value - source| where the asset has an error map (the
        default DEM codec), on |value - attractor| otherwise. The server's answer for the
        same points."""

@final
class Answer:
    """A tile or region as the server answered it."""

    values: npt.NDArray[np.float32]
    """``(rows, cols)`` heights (NaN on nodata), or ``(rows, cols, channels)`` intensities."""
    convergence_bound: float
    """How far the answer is from the fractal's attractor, value units."""
    error_bound: Optional[float]
    """The bound against the source data, value units (``None`` without an error map)."""
    body: bytes
    """The body as sent (PNG, float32 or GeoTIFF bytes)."""

@final
class Client:
    """A client of a fractile server (``fractile serve``)."""

    def __new__(cls, url: str, token: Optional[str] = None) -> Client:
        """A client of the server at ``url``; ``token`` is sent with uploads and deletes."""
    @property
    def url(self) -> str: ...
    def assets(self) -> list[dict[str, Any]]:
        """Every asset's summary."""
    def asset(self, id: str) -> dict[str, Any]:
        """One asset's summary."""
    def upload(self, id: str, path: Union[str, PathLike[str]]) -> dict[str, Any]:
        """Stores an asset file as ``id``; returns its summary."""
    def delete(self, id: str) -> None:
        """Deletes ``id``."""
    def tile(
        self,
        id: str,
        z: int,
        x: int,
        y: int,
        *,
        encoding: str = "f32",
        tile_size: int = 256,
        iterations: Optional[int] = None,
        tolerance: Optional[float] = None,
    ) -> Answer:
        """Tile ``z/x/y``: ``encoding`` ``"f32"``, ``"terrarium"``, ``"terrain-rgb"``,
        ``"gray16"`` or ``"png"``."""
    def region(
        self,
        id: str,
        bbox: Sequence[float],
        width: int,
        height: int,
        *,
        iterations: Optional[int] = None,
        tolerance: Optional[float] = None,
    ) -> Answer:
        """Values on a ``width x height`` grid of pixel centres over ``bbox`` (west, south,
        east, north)."""
    def points(
        self,
        id: str,
        lon: Sequence[float],
        lat: Sequence[float],
        iterations: Optional[int] = None,
    ) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """``(values, bounds)`` as :meth:`Asset.points` gives them."""
    def file_url(self, id: str) -> str:
        """The URL of ``id``'s file, which :func:`open` reads by range."""
