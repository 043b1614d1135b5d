//! Curve deformation: the body of `POST /v1/assets/{id}/curve/deform` (JSON). The answer is
//! GeoJSON, like `GET /v1/assets/{id}/curve`.

use serde::{Deserialize, Serialize};

/// One deformation of a curve asset's model (applied in order, statelessly: the stored asset
/// is unchanged).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Deformation {
    /// Global: new positions for every base control point of a ring (its level-0 polygon, as
    /// `GET .../curve?level=0&control=true` lists it). The details are rotated and scaled by the
    /// rotation-and-scale part of the affine map that best takes the old control points to the
    /// new ones.
    Control {
        /// Ring index (input order).
        ring: usize,
        /// New base control points, as many as the ring has.
        points: Vec<[f64; 2]>,
    },
    /// Appearance: the details of the levels from `from_level` on are scaled and rotated.
    Details {
        /// First asset level whose details change (0: all of them).
        from_level: usize,
        /// Factor on the details (0 removes them, 2 doubles the roughness).
        scale: f64,
        /// Rotation of the details, degrees counter-clockwise.
        #[serde(default)]
        rotate_degrees: f64,
        /// One ring, or every ring when absent.
        #[serde(default)]
        ring: Option<usize>,
    },
    /// Local: the curve at asset level `level` is analysed, its point `index` moved to `to`,
    /// its neighbours within `radius` points moved with a smooth falloff, and the curve
    /// resynthesised with the finer details kept.
    Local {
        /// Ring index.
        ring: usize,
        /// Asset level of the edit (at most the finest).
        level: usize,
        /// Index of the point in that level's output.
        index: usize,
        /// Where the point goes.
        to: [f64; 2],
        /// Neighbours on each side that follow (0: the point alone).
        #[serde(default)]
        radius: usize,
    },
}

/// Deformations and the level to answer at.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeformRequest {
    /// Applied in order.
    pub deformations: Vec<Deformation>,
    /// Asset level of the answer; the finest when absent.
    #[serde(default)]
    pub level: Option<usize>,
}
