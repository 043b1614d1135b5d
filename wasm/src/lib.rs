//! fractile's decoder in WebAssembly: an asset file on static storage (S3, a CDN, nginx) read by
//! HTTP range requests and decoded in the browser, with the server's own extraction (the codec
//! crate, built without its server-side parts: no moka, no files, no threads).
//!
//! The JavaScript side (`wasm/js/`) fetches; this side only decodes what it is handed. A call
//! that lacks bytes throws, and [`FractileReader::missing`] then names the range to fetch:
//!
//! ```js
//! const r = new FractileReader(fileLength, 256 << 20);
//! // fetch what r.missing() names, r.add(offset, bytes), call again
//! ```
//!
//! [`reader`] holds the logic, in plain Rust (tested natively); this file only binds it.

pub mod reader;

use reader::{ReadError, Reader};
use wasm_bindgen::prelude::*;

/// An asset fetched by range, for JavaScript.
#[wasm_bindgen]
pub struct FractileReader {
    inner: Reader,
    bound: f32,
    missing: Option<(u64, u64)>,
}

/// JavaScript numbers are f64: offsets and lengths up to 2^53 bytes pass exactly.
fn whole(x: f64) -> Result<u64, JsError> {
    if x.is_finite() && x >= 0.0 && x.fract() == 0.0 && x < 9.007_199_254_740_992e15 {
        Ok(x as u64)
    } else {
        Err(JsError::new(&format!("{x} is no byte offset or length")))
    }
}

#[wasm_bindgen]
impl FractileReader {
    /// A reader of a file of `length` bytes, keeping at most `cache_bytes` of decoded chunks.
    #[wasm_bindgen(constructor)]
    pub fn new(length: f64, cache_bytes: f64) -> Result<FractileReader, JsError> {
        Ok(FractileReader {
            inner: Reader::new(whole(length)?, whole(cache_bytes)?),
            bound: 0.0,
            missing: None,
        })
    }

    /// Hands the reader `bytes` fetched from `offset`.
    pub fn add(&mut self, offset: f64, bytes: Vec<u8>) -> Result<(), JsError> {
        self.inner.add(whole(offset)?, bytes);
        Ok(())
    }

    /// After a call threw for want of bytes: `[offset, length]` to fetch; else `undefined`.
    pub fn missing(&self) -> Option<Vec<f64>> {
        self.missing.map(|(o, l)| vec![o as f64, l as f64])
    }

    /// Bytes fetched and held so far.
    #[wasm_bindgen(js_name = heldBytes)]
    pub fn held_bytes(&self) -> f64 {
        self.inner.held_bytes() as f64
    }

    /// The bound of the last tile: the heights' distance to the asset's attractor at most.
    pub fn bound(&self) -> f32 {
        self.bound
    }

    fn answer<T>(&mut self, r: Result<T, ReadError>) -> Result<T, JsError> {
        self.missing = None;
        r.map_err(|e| match e {
            ReadError::Missing(o, l) => {
                self.missing = Some((o, l));
                JsError::new(&format!("bytes {o}..{} are not fetched yet", o + l))
            }
            ReadError::Failed(m) => JsError::new(&m),
        })
    }

    /// Opens the asset and returns its metadata as JSON (the server's `AssetMeta`).
    pub fn open(&mut self) -> Result<String, JsError> {
        let r = self.inner.open().map(serde_json::to_string);
        match self.answer(r)? {
            Ok(json) => Ok(json),
            Err(e) => Err(JsError::new(&e.to_string())),
        }
    }

    /// `[west, south, east, north, nativeZoom]`: the asset's bounds as a map source states
    /// them and the zoom at which a pixel of a `tile_size` tile is about a source cell.
    #[wasm_bindgen(js_name = mapFrame)]
    pub fn map_frame(&mut self, tile_size: usize) -> Result<Vec<f64>, JsError> {
        let r = self.inner.map_frame(tile_size);
        let (b, z) = self.answer(r)?;
        Ok(vec![b[0], b[1], b[2], b[3], f64::from(z)])
    }

    /// `[offset, length, offset, length, ...]` of the chunks tile `z/x/y` reads and the reader
    /// has not fetched: fetch them all (in parallel), then ask for the tile.
    #[wasm_bindgen(js_name = tileRanges)]
    pub fn tile_ranges(&mut self, z: u8, x: u32, y: u32, size: usize) -> Result<Vec<f64>, JsError> {
        let r = self.inner.tile_ranges((z, x, y), size);
        let ranges = self.answer(r)?;
        Ok(ranges
            .into_iter()
            .flat_map(|(o, l)| [o as f64, l as f64])
            .collect())
    }

    /// Tile `z/x/y` as `size * size` heights (NaN where there is no data), as the server
    /// answers it; its bound is [`Self::bound`] after.
    pub fn tile(&mut self, z: u8, x: u32, y: u32, size: usize) -> Result<Vec<f32>, JsError> {
        let r = self.inner.tile((z, x, y), size);
        let t = self.answer(r)?;
        self.bound = t.bound;
        Ok(t.heights)
    }

    /// Tile `z/x/y` as RGBA pixels for a MapLibre `raster-dem` source, in `encoding`
    /// (`terrainrgb` or `terrarium`), nodata drawn at the asset's fill height (as the server
    /// packs its PNG tiles, at full precision).
    #[wasm_bindgen(js_name = tileRgba)]
    pub fn tile_rgba(
        &mut self,
        z: u8,
        x: u32,
        y: u32,
        size: usize,
        encoding: &str,
    ) -> Result<Vec<u8>, JsError> {
        let e: fractile_proto::query::HeightEncoding =
            encoding.parse().map_err(|e: String| JsError::new(&e))?;
        let heights = self.tile(z, x, y, size)?;
        let meta = self.inner.open().map_err(|_| JsError::new("not open"))?;
        let fill = fractile_proto::heights::fill_height(meta.value_min, meta.value_max);
        let rgb = fractile_proto::heights::pack_rgb(&heights, e, fill, 0)
            .ok_or_else(|| JsError::new(&format!("{encoding} is not packed into RGB")))?;
        Ok(rgb
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect())
    }

    /// The asset's values at `(lon, lat)` with the point's bound last:
    /// `[value, ..., error_bound]` (the source error added where the asset measured one).
    pub fn point(&mut self, lon: f64, lat: f64) -> Result<Vec<f32>, JsError> {
        let r = self.inner.point(lon, lat);
        let p = self.answer(r)?;
        let mut out = p.values;
        out.push(p.error_bound + p.source_error.unwrap_or(0.0));
        Ok(out)
    }
}
