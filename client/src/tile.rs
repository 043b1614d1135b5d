//! Tiles: their address, how they are asked for, and how the height encodings are read back to
//! floats. Unpacking a PNG is a file format, not decoding of the fractal: that stays on the
//! server.

use std::time::Duration;

use crate::ClientError;

/// A slippy-map tile address (Web Mercator, y from the north).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TileAddress {
    /// Zoom.
    pub z: u8,
    /// Column.
    pub x: u32,
    /// Row.
    pub y: u32,
}

impl TileAddress {
    /// The four children of a tile, one zoom deeper.
    pub fn children(self) -> [TileAddress; 4] {
        let (z, x, y) = (self.z + 1, 2 * self.x, 2 * self.y);
        [
            TileAddress { z, x, y },
            TileAddress { z, x: x + 1, y },
            TileAddress { z, x, y: y + 1 },
            TileAddress {
                z,
                x: x + 1,
                y: y + 1,
            },
        ]
    }

    /// `[west, south, east, north]` in degrees.
    pub fn bounds(self) -> [f64; 4] {
        fractile_proto::tiles::tile_bounds(self.z, self.x, self.y)
    }

    /// The tile of zoom `z` that holds a point.
    pub fn containing(z: u8, lon: f64, lat: f64) -> TileAddress {
        let (x, y) = fractile_proto::tiles::lonlat_tile(z, lon, lat);
        TileAddress { z, x, y }
    }
}

impl std::fmt::Display for TileAddress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}/{}", self.z, self.x, self.y)
    }
}

/// What a tile carries.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TileEncoding {
    /// A picture (images as they are; heights as grey). Values are 8-bit channel intensities.
    #[default]
    Visual,
    /// Heights in Terrarium RGB (1/256 m steps).
    Terrarium,
    /// Heights in Mapbox terrain-RGB (0.1 m steps).
    TerrainRgb,
    /// Heights as 16-bit grey over the asset's value range.
    Gray16,
    /// Heights as little-endian float32 (NaN for nodata).
    F32,
}

impl TileEncoding {
    /// The `encoding=` value, if any.
    pub(crate) fn query_name(self) -> Option<fractile_proto::query::HeightEncoding> {
        use fractile_proto::query::HeightEncoding;
        match self {
            TileEncoding::Terrarium => Some(HeightEncoding::Terrarium),
            TileEncoding::TerrainRgb => Some(HeightEncoding::TerrainRgb),
            TileEncoding::Gray16 => Some(HeightEncoding::Gray16),
            TileEncoding::Visual | TileEncoding::F32 => None,
        }
    }

    /// Parses a CLI name (`png`, `terrarium`, `terrainrgb`, `gray16`, `f32`).
    pub fn parse(name: &str) -> Option<TileEncoding> {
        Some(match name {
            "png" | "visual" => TileEncoding::Visual,
            "terrarium" => TileEncoding::Terrarium,
            "terrainrgb" => TileEncoding::TerrainRgb,
            "gray16" => TileEncoding::Gray16,
            "f32" => TileEncoding::F32,
            _ => return None,
        })
    }

    /// Whether the values are heights (as opposed to 8-bit intensities).
    pub fn is_heights(self) -> bool {
        self != TileEncoding::Visual
    }
}

/// A tile request.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TileRequest {
    /// Which tile.
    pub address: TileAddress,
    /// What it carries.
    pub encoding: TileEncoding,
    /// Exactly this many steps (`None`: the server's default).
    pub iterations: Option<u32>,
    /// Per-point stopping tolerance in value units.
    pub tolerance: Option<f32>,
    /// 256 or 512.
    pub tile_size: u32,
    /// `precision` of terrain-RGB and Terrarium tiles (`None`: the server's default,
    /// `bound`: heights rounded to what the tile's error bound justifies).
    pub precision: Option<fractile_proto::query::Precision>,
}

impl TileRequest {
    /// A 256-pixel tile at the server's default steps.
    pub fn new(address: TileAddress, encoding: TileEncoding) -> TileRequest {
        TileRequest {
            address,
            encoding,
            iterations: None,
            tolerance: None,
            tile_size: 256,
            precision: None,
        }
    }
}

/// A tile as answered.
#[derive(Clone, Debug)]
pub struct Tile {
    /// Which tile.
    pub address: TileAddress,
    /// Pixels a side.
    pub size: u32,
    /// The body as sent (PNG or float32 bytes), ready to write to a file.
    pub body: Vec<u8>,
    /// Row-major values: heights (NaN where the server marked nodata in float32 tiles) for the
    /// height encodings; interleaved 8-bit channel intensities for visual tiles.
    pub values: Vec<f32>,
    /// Values per pixel (1 for heights, 1 to 4 for visual tiles).
    pub channels: u32,
    /// The server's convergence bound (`X-Convergence-Bound`), value units: how far the
    /// tile is from the fractal's attractor; what refinement stops on.
    pub convergence_bound: f32,
    /// The server's bound against the source data (`X-Error-Bound`), value units; `None`
    /// for assets encoded before format version 5.
    pub error_bound: Option<f32>,
    /// The ETag, for conditional requests.
    pub etag: Option<String>,
    /// Time from request to the last byte.
    pub elapsed: Duration,
}

impl Tile {
    /// Reads a tile body. `range` is the asset's value range, which only Gray16 needs.
    pub(crate) fn decode(
        req: &TileRequest,
        body: Vec<u8>,
        (convergence_bound, error_bound): (f32, Option<f32>),
        etag: Option<String>,
        elapsed: Duration,
        range: Option<[f64; 2]>,
    ) -> Result<Tile, ClientError> {
        let (size, values, channels) = decode_values(req.encoding, &body, range)?;
        if size != req.tile_size {
            return Err(ClientError::malformed(
                "tile",
                format!("{size} pixels a side, asked for {}", req.tile_size),
            ));
        }
        Ok(Tile {
            address: req.address,
            size,
            body,
            values,
            channels,
            convergence_bound,
            error_bound,
            etag,
            elapsed,
        })
    }
}

/// Side, values and channels of a tile body.
pub fn decode_values(
    encoding: TileEncoding,
    body: &[u8],
    range: Option<[f64; 2]>,
) -> Result<(u32, Vec<f32>, u32), ClientError> {
    if encoding == TileEncoding::F32 {
        let n = body.len() / 4;
        let side = (n as f64).sqrt().round() as u32;
        if !body.len().is_multiple_of(4) || (side * side) as usize != n || n == 0 {
            return Err(ClientError::malformed(
                "tile",
                format!("{} bytes is no square of float32", body.len()),
            ));
        }
        let v = body
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        return Ok((side, v, 1));
    }
    let img = image::load_from_memory_with_format(body, image::ImageFormat::Png)
        .map_err(|e| ClientError::malformed("tile PNG", e.to_string()))?;
    let (w, h) = (img.width(), img.height());
    if w != h {
        return Err(ClientError::malformed(
            "tile",
            format!("{w}x{h} is not square"),
        ));
    }
    let rgb = || img.to_rgb8().into_raw();
    let values: Vec<f32> = match encoding {
        // MapLibre's formulas, as the server packs them.
        TileEncoding::Terrarium => rgb()
            .chunks_exact(3)
            .map(|p| p[0] as f32 * 256.0 + p[1] as f32 + p[2] as f32 / 256.0 - 32768.0)
            .collect(),
        TileEncoding::TerrainRgb => rgb()
            .chunks_exact(3)
            .map(|p| {
                // f64: in f32 the 0.1 m steps near 10 km lose a millimetre.
                let code = p[0] as u32 * 65536 + p[1] as u32 * 256 + p[2] as u32;
                (-10000.0 + code as f64 * 0.1) as f32
            })
            .collect(),
        TileEncoding::Gray16 => {
            let [lo, hi] = range.ok_or_else(|| {
                ClientError::malformed("gray16 tile", "the asset's value range is needed")
            })?;
            img.to_luma16()
                .into_raw()
                .into_iter()
                .map(|g| (lo + g as f64 / 65535.0 * (hi - lo)) as f32)
                .collect()
        }
        TileEncoding::Visual => {
            let c = img.color().channel_count() as u32;
            let raw = match c {
                1 => img.to_luma8().into_raw(),
                2 => img.to_luma_alpha8().into_raw(),
                3 => img.to_rgb8().into_raw(),
                _ => img.to_rgba8().into_raw(),
            };
            return Ok((w, raw.into_iter().map(f32::from).collect(), c.min(4)));
        }
        TileEncoding::F32 => unreachable!("handled above"),
    };
    Ok((w, values, 1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_of_a_point_contains_it_and_children_tile_the_parent() {
        // Mount Everest at zoom 10, and its parent's four children.
        let t = TileAddress::containing(10, 86.925, 27.9881);
        let [w, s, e, n] = t.bounds();
        assert!(
            w <= 86.925 && 86.925 < e && s <= 27.9881 && 27.9881 < n,
            "{t} {w} {s} {e} {n}"
        );
        let parent = TileAddress {
            z: 9,
            x: t.x / 2,
            y: t.y / 2,
        };
        assert!(parent.children().contains(&t));
        let pb = parent.bounds();
        let kids: Vec<[f64; 4]> = parent.children().iter().map(|c| c.bounds()).collect();
        let west = kids.iter().map(|b| b[0]).fold(f64::MAX, f64::min);
        let north = kids.iter().map(|b| b[3]).fold(f64::MIN, f64::max);
        assert!((west - pb[0]).abs() < 1e-9 && (north - pb[3]).abs() < 1e-9);
    }

    #[test]
    fn height_encodings_read_back_maplibre_formulas() {
        // One pixel of each encoding, packed by hand from MapLibre's definitions:
        // Terrarium 1234.5 m + 32768 = 34002.5 -> R 132, G 210, B 128; terrain-RGB 1234.5 m =
        // (11234.5 * 10 = 112345) -> R 1, G 182, B 217.
        let png = |px: [u8; 3]| {
            let mut out = Vec::new();
            image::RgbImage::from_raw(1, 1, px.to_vec())
                .unwrap()
                .write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
                .unwrap();
            out
        };
        let (_, v, _) =
            decode_values(TileEncoding::Terrarium, &png([132, 210, 128]), None).unwrap();
        assert_eq!(v, vec![1234.5]);
        let (_, v, _) = decode_values(TileEncoding::TerrainRgb, &png([1, 182, 217]), None).unwrap();
        assert!((v[0] - 1234.5).abs() < 1e-3, "{v:?}");
        assert!(decode_values(TileEncoding::Gray16, &png([0, 0, 0]), None).is_err());
        assert!(decode_values(TileEncoding::F32, &[0, 0, 0], None).is_err());
        assert!(decode_values(TileEncoding::Terrarium, b"not a png", None).is_err());
    }
}
