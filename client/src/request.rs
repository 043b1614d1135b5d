//! The requests and answers of the endpoints that have more than a query string: regions,
//! meshes, points batches and uploads.

use crate::{AssetSummary, MeshFormat, RegionFormat};

/// How a points batch travels: JSON (readable) or proto's binary encoding (about 3x smaller and
/// faster to parse for large batches).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PointsEncoding {
    /// `application/json`.
    #[default]
    Json,
    /// `application/x-bincode`.
    Binary,
}

/// A window of an asset sampled on a `width x height` grid of pixel centres.
#[derive(Clone, Debug, PartialEq)]
pub struct RegionRequest {
    /// `[minx, miny, maxx, maxy]`: lon/lat for georeferenced assets, unit coordinates otherwise.
    pub bbox: [f64; 4],
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Exactly this many steps (`None`: the server's default).
    pub iterations: Option<u32>,
    /// Per-point stopping tolerance in value units.
    pub tolerance: Option<f32>,
    /// Answer format.
    pub format: RegionFormat,
}

/// A region as answered.
#[derive(Clone, Debug)]
pub struct Region {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// The body as the server sent it (PNG, float32 or GeoTIFF bytes).
    pub body: Vec<u8>,
    /// Per channel, `width * height` values, for [`RegionFormat::F32`] answers.
    pub values: Option<Vec<Vec<f32>>>,
    /// The server's convergence bound (`X-Convergence-Bound`, value units).
    pub convergence_bound: f32,
    /// The server's bound against the source (`X-Error-Bound`, value units; `None` for assets
    /// without a source-error map).
    pub error_bound: Option<f32>,
}

/// A terrain mesh request: a regular grid of `resolution x resolution` vertices.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshRequest {
    /// The box (`None`: the whole asset).
    pub bbox: Option<[f64; 4]>,
    /// Vertices a side (server default 256).
    pub resolution: Option<u32>,
    /// Exactly this many steps.
    pub iterations: Option<u32>,
    /// Per-point stopping tolerance in value units.
    pub tolerance: Option<f32>,
    /// An adaptive triangulation within this many height units of the decoded grid (`None`:
    /// the regular grid).
    pub max_error: Option<f32>,
    /// File format.
    pub format: MeshFormat,
}

/// A mesh of a volume asset (IFS3D): `GET /v1/assets/{id}/mesh` with a 3D box.
#[derive(Clone, Debug, Default)]
pub struct VolumeMeshRequest {
    /// `[x0, y0, z0, x1, y1, z1]` in the mesh's units (`None`: the whole grid).
    pub bbox: Option<[f64; 6]>,
    /// Samples along the box's longest side (server default: the encoded grid).
    pub resolution: Option<u32>,
    /// Exactly this many steps.
    pub iterations: Option<u32>,
    /// Per-sample stopping tolerance, world units.
    pub tolerance: Option<f32>,
    /// File format.
    pub format: MeshFormat,
}

/// A mesh as answered.
#[derive(Clone, Debug)]
pub struct MeshFile {
    /// The file's bytes.
    pub body: Vec<u8>,
    /// Its media type.
    pub content_type: String,
    /// The server's bound on the heights against the attractor (decoding, plus `max_error`
    /// for adaptive meshes).
    pub convergence_bound: f32,
    /// The same against the source (`None` for assets without a source-error map).
    pub error_bound: Option<f32>,
}

/// Result of an upload.
#[derive(Clone, Debug)]
pub struct Uploaded {
    /// The asset as the catalog now lists it.
    pub summary: AssetSummary,
    /// Whether the id was new (201) rather than replaced (200).
    pub created: bool,
}
