//! An asset read by range: the bytes its caller has fetched so far, the range the last answer
//! lacked, and answers (tiles, points) as the server gives them, through the same codec calls.
//! No I/O here: the caller (the browser's worker, `wasm/js/worker.js`) fetches what
//! a failed call names ([`ReadError::Missing`]), hands it to [`Reader::add`] and asks again. A tile names all the
//! chunks it reads beforehand ([`Reader::tile_ranges`]), so that they are fetched at once.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};

use fractile_codec::chunked::{ChunkCache, ChunkSource, is_chunked};
use fractile_codec::extract::{PointSample, Points, Request, Resources, SampleError};
use fractile_codec::geo::{Pixels, Placement, map_bounds, native_zoom, tile_pixels};
use fractile_codec::{Asset, AssetLimits};
use fractile_proto::AssetMeta;

/// What the server answers with when a request names neither steps nor a tolerance: its
/// default `max_iterations`, each answer stopping at the tolerance its pixels settle
/// (`Asset::answer`). The browser answers the same way so that both give the same
/// heights.
pub const ITERATIONS: u32 = 64;

/// The bytes of a file fetched so far, by offset, and the first range a read lacked.
#[derive(Default)]
struct Ranges {
    held: Mutex<BTreeMap<u64, Arc<[u8]>>>,
    missing: Mutex<Option<(u64, u64)>>,
    length: u64,
}

impl Ranges {
    /// `len` bytes from `offset`, if one fetched range holds them all.
    fn get(&self, offset: u64, len: u64) -> Option<Vec<u8>> {
        let held = self.held.lock().unwrap_or_else(PoisonError::into_inner);
        let (&start, bytes) = held.range(..=offset).next_back()?;
        let from = usize::try_from(offset - start).ok()?;
        let to = from.checked_add(usize::try_from(len).ok()?)?;
        bytes.get(from..to).map(<[u8]>::to_vec)
    }

    /// Records that `len` bytes from `offset` were wanted and not held (the first such range
    /// since the caller last asked).
    fn want(&self, offset: u64, len: u64) {
        let mut m = self.missing.lock().unwrap_or_else(PoisonError::into_inner);
        m.get_or_insert((offset, len));
    }

    fn take_missing(&self) -> Option<(u64, u64)> {
        self.missing
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()
    }
}

/// The codec's view of the fetched ranges: a read of bytes not fetched fails, and says which.
struct Fetched(Arc<Ranges>);

impl ChunkSource for Fetched {
    fn len(&self) -> u64 {
        self.0.length
    }

    fn read(&self, offset: u64, len: usize) -> std::io::Result<Vec<u8>> {
        self.0.get(offset, len as u64).ok_or_else(|| {
            self.0.want(offset, len as u64);
            std::io::Error::new(std::io::ErrorKind::WouldBlock, "bytes not fetched yet")
        })
    }

    fn describe(&self) -> String {
        "an asset read by range".into()
    }
}

/// Why an answer did not come.
#[derive(Debug, PartialEq)]
pub enum ReadError {
    /// These bytes `(offset, length)` are needed first: fetch them, [`Reader::add`] them, and
    /// ask again.
    Missing(u64, u64),
    /// The asset or the request is wrong (a corrupt file, a point off the asset, ...).
    Failed(String),
}

/// A tile's heights and what bounds them.
#[derive(Debug)]
pub struct Tile {
    /// `size x size` heights, row-major from the north-west; NaN where there is no data.
    pub heights: Vec<f32>,
    /// The a-priori bound on the heights' distance to the asset's attractor (source units).
    pub bound: f32,
}

/// The largest tile, in pixels a side: map tiles are 256 or 512; a tile of 30,000 ran the
/// module out of memory (a trap, after which the reader was unusable). Checked before anything
/// is made.
pub const MOST_TILE_SIZE: usize = 2048;

/// What a file may claim and cost in the browser: the codec's limits, with a decode budget of
/// 1 GiB (wasm32's memory is 4 GiB at most, and a tab is granted less).
fn limits() -> AssetLimits {
    AssetLimits {
        max_decode_bytes: 1 << 30,
        ..AssetLimits::default()
    }
}

/// Refuses a tile size the reader does not make (see [`MOST_TILE_SIZE`]).
fn check_size(size: usize) -> Result<(), ReadError> {
    if (1..=MOST_TILE_SIZE).contains(&size) {
        Ok(())
    } else {
        Err(ReadError::Failed(format!(
            "a tile of {size} pixels a side: 1 to {MOST_TILE_SIZE} (map tiles are 256 or 512)"
        )))
    }
}

/// The first bytes fetched when a reader opens: a chunked file's header and table (a few
/// kilobytes on a DEM of 16k x 16k cells in chunks of 1,024), or all of a small file.
pub const OPENING_BYTES: u64 = 16 << 10;

/// An asset fetched by range (see the module).
pub struct Reader {
    ranges: Arc<Ranges>,
    asset: Option<Asset>,
    placement: Option<Placement>,
    cache: ChunkCache,
}

impl Reader {
    /// A reader of a file of `length` bytes whose decoded chunks take at most `cache_bytes`.
    pub fn new(length: u64, cache_bytes: u64) -> Reader {
        Reader {
            ranges: Arc::new(Ranges {
                length,
                ..Ranges::default()
            }),
            asset: None,
            placement: None,
            cache: ChunkCache::new(cache_bytes),
        }
    }

    /// Bytes of the file fetched from `offset`.
    pub fn add(&self, offset: u64, bytes: Vec<u8>) {
        self.ranges
            .held
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(offset, bytes.into());
    }

    /// Bytes held, all ranges together.
    pub fn held_bytes(&self) -> u64 {
        let held = self
            .ranges
            .held
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        held.values().map(|b| b.len() as u64).sum()
    }

    /// The error of a failed codec call: the range it lacked, else its message.
    fn failed(&self, e: impl std::fmt::Display) -> ReadError {
        match self.ranges.take_missing() {
            Some((offset, len)) => ReadError::Missing(offset, len),
            None => ReadError::Failed(e.to_string()),
        }
    }

    /// Opens the asset: a chunked file from its header and table, any other whole.
    pub fn open(&mut self) -> Result<&AssetMeta, ReadError> {
        if self.asset.is_none() {
            let length = self.ranges.length;
            let head = self
                .ranges
                .get(0, length.min(12))
                .ok_or(ReadError::Missing(0, length.min(OPENING_BYTES)))?;
            let limits = limits();
            let asset = if is_chunked(&head) {
                let source = Box::new(Fetched(self.ranges.clone()));
                Asset::open_chunked(source, &limits, self.cache.clone())
                    .map_err(|e| self.failed(e))?
            } else {
                // Before asking for it whole: a length no asset in one piece has (a lying
                // server, a wrong URL) is refused, not fetched.
                fractile_codec::asset::check_whole_file(&head, length, &limits)
                    .map_err(|e| ReadError::Failed(e.to_string()))?;
                let bytes = self
                    .ranges
                    .get(0, length)
                    .ok_or(ReadError::Missing(0, length))?;
                Asset::from_bytes_limited(&bytes, &limits).map_err(|e| self.failed(e))?
            };
            self.placement = match &asset.meta.georef {
                Some(g) => Some(
                    Placement::of(g, asset.meta.width, asset.meta.height)
                        .map_err(|e| ReadError::Failed(e.to_string()))?,
                ),
                None => None,
            };
            self.asset = Some(asset);
        }
        Ok(&self.opened()?.meta)
    }

    /// The asset's lon/lat bounds as a map source states them, and the zoom at which a tile
    /// pixel of `tile_size` is about a source cell (the server's TileJSON's).
    pub fn map_frame(&self, tile_size: usize) -> Result<([f64; 4], u8), ReadError> {
        let p = self.placement.as_ref();
        let width = self.opened()?.meta.width;
        Ok((map_bounds(p), native_zoom(p, width, tile_size)))
    }

    fn opened(&self) -> Result<&Asset, ReadError> {
        self.asset
            .as_ref()
            .ok_or_else(|| ReadError::Failed("the asset is not open yet".into()))
    }

    /// The pixel centres of tile `z/x/y` of `size` pixels a side on the asset (the server's).
    fn tile_pixels(&self, (z, x, y): (u8, u32, u32), size: usize) -> Pixels {
        tile_pixels(self.placement.as_ref(), z, x, y, size, 0)
    }

    /// The ranges of the file a tile reads that are not fetched yet.
    pub fn tile_ranges(
        &self,
        tile: (u8, u32, u32),
        size: usize,
    ) -> Result<Vec<(u64, u64)>, ReadError> {
        check_size(size)?;
        let pixels = self.tile_pixels(tile, size);
        if pixels.is_outside() {
            return Ok(Vec::new());
        }
        let wanted = self.opened()?.chunk_ranges(&pixels);
        Ok(wanted
            .into_iter()
            .filter(|&(o, l)| self.ranges.get(o, l).is_none())
            .collect())
    }

    /// Tile `z/x/y` of `size x size` heights, as the server answers it with neither steps nor
    /// a tolerance asked: `ITERATIONS` at most, each pixel stopping at the tolerance the
    /// tile's pixels settle.
    pub fn tile(&self, tile: (u8, u32, u32), size: usize) -> Result<Tile, ReadError> {
        check_size(size)?;
        let asset = self.opened()?;
        let pixels = self.tile_pixels(tile, size);
        if pixels.is_outside() {
            return Ok(Tile {
                heights: vec![f32::NAN; pixels.len()],
                bound: 0.0,
            });
        }
        // The server's one call: the tolerance settled over the tile's pixels.
        let request = Request {
            pixels: &pixels,
            iterations: ITERATIONS,
            tolerance: None,
        };
        match asset.answer(&request, &Resources::CPU) {
            Ok(mut answer) => Ok(Tile {
                heights: answer.channels.swap_remove(0),
                bound: answer.convergence,
            }),
            Err(SampleError::Chunk(e) | SampleError::Refused(e)) => Err(self.failed(e)),
            Err(SampleError::Cancelled) => Err(ReadError::Failed("cancelled".into())),
        }
    }

    /// The asset's values at `(lon, lat)` (or unit coordinates where the asset has no
    /// georeference), as the server's point answer: `ITERATIONS` at most, stopping at the
    /// asset's default tolerance, with each point's bound.
    pub fn point(&self, lon: f64, lat: f64) -> Result<PointSample, ReadError> {
        let asset = self.opened()?;
        let unit = match &self.placement {
            Some(p) => p.unit(lon, lat),
            None => Some([lon as f32, lat as f32]),
        }
        .filter(|[u, v]| (0.0..=1.0).contains(u) && (0.0..=1.0).contains(v))
        .ok_or_else(|| ReadError::Failed(format!("({lon}, {lat}) is outside the asset")))?;
        let pts = [unit];
        let wanted = asset.point_chunk_ranges(&pts);
        if let Some(&(o, l)) = wanted
            .iter()
            .find(|&&(o, l)| self.ranges.get(o, l).is_none())
        {
            return Err(ReadError::Missing(o, l));
        }
        // The server's one call; its tolerance the asset's default.
        let question = Points {
            points: &pts,
            iterations: ITERATIONS,
            tolerance: None,
        };
        let mut answers = asset
            .answer(&question, &Resources::CPU)
            .map_err(|e| self.failed(e.into_error()))?;
        Ok(answers.swap_remove(0))
    }
}
