//! The catalog: what `GET /v1/assets` and `GET /v1/assets/{id}` answer, the TileJSON document,
//! and the error body every failing request carries. The server writes these types and the
//! client reads them, so the two cannot drift apart.

use serde::{Deserialize, Serialize};

use crate::asset::{AssetKind, ColourModel};

/// Whether `id` can name an asset: 1 to 64 ASCII letters, digits, `-` or `_`, starting with a
/// letter or digit. Ids become file names and URL path segments, so nothing else (no `.`, no
/// `/`) is allowed: no path can escape the asset folder or be rewritten by URL normalisation.
pub fn valid_asset_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 64
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        && id.chars().next().is_some_and(|c| c.is_ascii_alphanumeric())
}

/// One asset as the catalog describes it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AssetSummary {
    /// The asset's id (its file name without `.fractile`).
    pub id: String,
    /// What it depicts.
    pub kind: AssetKind,
    /// Width of the source grid in samples.
    pub width: u32,
    /// Height of the source grid in samples.
    pub height: u32,
    /// Channels of the source.
    pub channels: u8,
    /// How the channels map to colour.
    pub colour: ColourModel,
    /// `[west, south, east, north]` in degrees for georeferenced assets.
    pub bounds: Option<[f64; 4]>,
    /// Whether requests take lon/lat (true) or unit coordinates (false).
    pub georeferenced: bool,
    /// The EPSG code of the CRS the asset's grid is in, as its file names it (4326 for a
    /// geographic grid; requests take lon/lat whatever it is: the server reprojects); absent
    /// for non-georeferenced assets and files that name no code.
    #[serde(default)]
    pub epsg: Option<u32>,
    /// `[min, max]` of the valid source values.
    pub value_range: [f64; 2],
    /// Units of the values (`m` for DEMs), when known.
    pub units: Option<String>,
    /// The source's nodata value, when it had one.
    pub nodata: Option<f64>,
    /// The codec that made the asset.
    pub codec: String,
    /// Size of the asset file in bytes.
    pub bytes: u64,
    /// Compression ratio against the source at its own sample type.
    pub ratio: f64,
    /// Number of affine maps.
    pub transforms: u64,
    /// PSNR the encoder measured (dB).
    pub encode_psnr: f64,
    /// RMS error the encoder measured (value units).
    pub encode_rmse: f64,
    /// Largest |contrast| of the operator: the a-priori error bound after n steps is at most
    /// `seed_bound * max_contrast^n`, which lets a client choose n for a tolerance.
    pub max_contrast: f32,
    /// A-priori error bound of the seed (n = 0), value units.
    pub seed_bound: f32,
    /// Absolute URL of the asset's TileJSON; only rasters (images and height fields) have
    /// tiles, so curves and volumes have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tilejson: Option<String>,
}

impl AssetSummary {
    /// Fewest steps after which the a-priori bound is under `tolerance` everywhere (`None` if
    /// the operator does not contract, which a valid asset never does).
    pub fn iterations_for(&self, tolerance: f32) -> Option<u32> {
        if self.seed_bound <= tolerance {
            return Some(0);
        }
        if !(self.max_contrast > 0.0 && self.max_contrast < 1.0 && tolerance > 0.0) {
            return (self.max_contrast == 0.0).then_some(1);
        }
        let n = (tolerance / self.seed_bound).ln() / self.max_contrast.ln();
        Some(n.ceil().max(1.0) as u32)
    }
}

/// `GET /v1/assets`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Catalog {
    /// Every asset, sorted by id.
    pub assets: Vec<AssetSummary>,
}

/// A TileJSON 3.0.0 document (the fields the server writes).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileJson {
    /// Always `3.0.0`.
    pub tilejson: String,
    /// The asset id.
    pub name: String,
    /// Tile URL templates with `{z}`, `{x}`, `{y}`.
    pub tiles: Vec<String>,
    /// Shallowest zoom.
    pub minzoom: u8,
    /// Deepest zoom worth asking (native zoom plus fractal detail).
    pub maxzoom: u8,
    /// `[west, south, east, north]` in degrees, clipped to Web Mercator.
    pub bounds: [f64; 4],
    /// Tile size in pixels.
    #[serde(rename = "tileSize")]
    pub tile_size: u32,
    /// `terrarium` for height fields (MapLibre's raster-dem encoding), absent for images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub encoding: Option<String>,
}

/// A Cesium terrain `layer.json` (the fields the server writes): what `CesiumTerrainProvider`
/// reads before it asks for quantized-mesh tiles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerJson {
    /// Always `2.1.0`, as Cesium's own layers.
    pub tilejson: String,
    /// The asset id.
    pub name: String,
    /// The layer's version, `1.0.0`.
    pub version: String,
    /// Always `quantized-mesh-1.0`.
    pub format: String,
    /// Always `tms` (rows from the south).
    pub scheme: String,
    /// Always `EPSG:4326`: Cesium's geographic tiling, two root tiles.
    pub projection: String,
    /// Tile URL templates with `{z}`, `{x}`, `{y}`, relative to the layer.
    pub tiles: Vec<String>,
    /// Shallowest level.
    pub minzoom: u8,
    /// Deepest level.
    pub maxzoom: u8,
    /// `[west, south, east, north]` in degrees.
    pub bounds: [f64; 4],
    /// Per level, the tiles that exist.
    pub available: Vec<Vec<TileRange>>,
    /// Extensions the tiles can carry when asked (`octvertexnormals`).
    pub extensions: Vec<String>,
}

/// Tiles `startX..=endX` by `startY..=endY` of one level of a [`LayerJson`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct TileRange {
    /// First column.
    pub start_x: u32,
    /// First row (from the south).
    pub start_y: u32,
    /// Last column.
    pub end_x: u32,
    /// Last row.
    pub end_y: u32,
}

/// The body of every error answer: `{"detail": "...", "code": "..."}`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ErrorBody {
    /// What went wrong, for people.
    pub detail: String,
    /// A stable machine code, one of [`ErrorCode`]'s (`unknown_asset`, `bad_tile`,
    /// `too_many_points`, ...); a string here so that a client reads codes newer than it.
    pub code: String,
}

/// Declares [`ErrorCode`] from one list, so that its variants, [`ErrorCode::ALL`] and the
/// wire names cannot drift apart.
macro_rules! error_codes {
    ($($variant:ident => $name:literal,)*) => {
        /// Every machine code an error answer carries ([`ErrorBody::code`]): one list, which
        /// the server answers with and its OpenAPI document names. Written as snake case on
        /// the wire.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
        #[serde(rename_all = "snake_case")]
        #[non_exhaustive]
        pub enum ErrorCode {
            $(#[doc = concat!("`", $name, "`.")] $variant,)*
        }

        impl ErrorCode {
            /// Every code, in the order of their names.
            pub const ALL: &'static [ErrorCode] = &[$(ErrorCode::$variant,)*];

            /// The code as the wire writes it.
            pub fn as_str(self) -> &'static str {
                match self {
                    $(ErrorCode::$variant => $name,)*
                }
            }
        }
    };
}

error_codes! {
    BadAsset => "bad_asset",
    BadBackend => "bad_backend",
    BadBbox => "bad_bbox",
    BadBody => "bad_body",
    BadColormap => "bad_colormap",
    BadDeformation => "bad_deformation",
    BadEncoding => "bad_encoding",
    BadFormat => "bad_format",
    BadHillshade => "bad_hillshade",
    BadId => "bad_id",
    BadIterations => "bad_iterations",
    BadMaxError => "bad_max_error",
    BadMediaType => "bad_media_type",
    BadPath => "bad_path",
    BadPoint => "bad_point",
    BadPrecision => "bad_precision",
    BadQuery => "bad_query",
    BadRange => "bad_range",
    BadRequest => "bad_request",
    BadRescale => "bad_rescale",
    BadResolution => "bad_resolution",
    BadSize => "bad_size",
    BadTile => "bad_tile",
    BadTilesize => "bad_tilesize",
    BadTolerance => "bad_tolerance",
    Busy => "busy",
    Cancelled => "cancelled",
    ChunkUnavailable => "chunk_unavailable",
    CorruptChunk => "corrupt_chunk",
    CurveAsset => "curve_asset",
    GpuUnavailable => "gpu_unavailable",
    Internal => "internal",
    MethodNotAllowed => "method_not_allowed",
    NoFile => "no_file",
    NoRoute => "no_route",
    NoTile => "no_tile",
    NotCurve => "not_curve",
    NotTerrain => "not_terrain",
    NotVolume => "not_volume",
    Outside => "outside",
    PreconditionFailed => "precondition_failed",
    StorageUnavailable => "storage_unavailable",
    TooExpensive => "too_expensive",
    TooLarge => "too_large",
    TooManyPoints => "too_many_points",
    TooManySamples => "too_many_samples",
    Unauthorised => "unauthorised",
    Unavailable => "unavailable",
    UnknownAsset => "unknown_asset",
    VolumeAsset => "volume_asset",
    WritesDisabled => "writes_disabled",
}

impl std::fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::ErrorCode;

    #[test]
    fn error_codes_are_written_as_their_names_once_each() {
        let mut seen = std::collections::BTreeSet::new();
        for &code in ErrorCode::ALL {
            let wire = serde_json::to_string(&code).unwrap();
            assert_eq!(wire, format!("\"{}\"", code.as_str()));
            assert!(seen.insert(code.as_str()), "{code} twice");
            let back: ErrorCode = serde_json::from_str(&wire).unwrap();
            assert_eq!(back, code);
        }
        // The names are sorted: a new code goes where a reader looks for it.
        let names: Vec<&str> = ErrorCode::ALL.iter().map(|c| c.as_str()).collect();
        let mut sorted = names.clone();
        sorted.sort_unstable();
        assert_eq!(names, sorted);
    }
}
