//! Point queries: the request and answer of `POST /v1/assets/{id}/points`, in JSON or in proto's
//! binary encoding (`Content-Type: application/x-bincode`).

use serde::{Deserialize, Serialize};

/// Media type of proto's binary encoding.
pub const BINARY_MEDIA_TYPE: &str = "application/x-bincode";

/// Many points of one asset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointsRequest {
    /// `[lon, lat]` for georeferenced assets, `[x, y]` in unit coordinates otherwise.
    pub points: Vec<[f64; 2]>,
    /// Inverse steps; when both this and `tolerance` are absent, the server's limit with the
    /// asset's default tolerance (half a quantisation step, or an eighth of its smallest
    /// source error where that is larger).
    pub iterations: Option<u32>,
    /// Value units: each point stops once its own error bound is under it (within
    /// `iterations`, or the server's limit).
    #[serde(default)]
    pub tolerance: Option<f32>,
}

/// The value of an asset at one point.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointResult {
    /// The point as asked.
    pub coordinates: [f64; 2],
    /// One value per channel; `None` where the source had no data or outside the asset.
    pub values: Option<Vec<Option<f32>>>,
    /// Bound on |value - source| in value units: the asset's measured error against its
    /// source where the point lies plus `convergence_bound`. Between source cells the source
    /// is the bilinear interpolation of its cell centres. `None` outside the asset and for
    /// assets encoded before format version 5 (they hold no source-error map).
    pub error_bound: Option<f32>,
    /// Bound on the distance to the fractal's own attractor (how far the iterations are from
    /// converged), in value units: what progressive refinement stops on. `None` outside.
    pub convergence_bound: Option<f32>,
    /// Inverse steps taken.
    pub iterations: u32,
    /// Whether the point lies outside the asset. (Always written: the binary encoding has no
    /// field names, so no field may be skipped.)
    #[serde(default)]
    pub outside: bool,
}

/// Answers to a [`PointsRequest`], in its order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointsResponse {
    /// One result per point.
    pub results: Vec<PointResult>,
}

/// The signed distance of a volume asset at one 3D point (`GET .../point?x=&y=&z=`, world units
/// of the source mesh).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DistanceResult {
    /// The point as asked.
    pub coordinates: [f64; 3],
    /// Signed distance to the surface (negative inside), clamped to the asset's band;
    /// `None` outside the grid.
    pub distance: Option<f32>,
    /// Bound on the error against the attractor, world units; `None` outside the grid.
    pub error_bound: Option<f32>,
    /// Inverse steps taken.
    pub iterations: u32,
    /// Whether the point lies outside the grid.
    #[serde(default)]
    pub outside: bool,
}
