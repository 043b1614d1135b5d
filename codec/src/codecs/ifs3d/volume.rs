//! Where a volume's grid lies in the world, and what an IFS3D volume asset holds; distances
//! between surfaces, to measure a decoded mesh against its source.
//!
//! Coordinates: the asset keeps the world placement of its grid ([`Placement`]); requests speak
//! world units (those of the source mesh). Unit coordinates `[0, 1]^3` span the grid's cube, as
//! they span the frame in 2D.

use serde::{Deserialize, Serialize};

use crate::codecs::ifs3d::octree::{OctreeHeader, OctreeOperator};
use crate::core::format::FormatError;

/// Where a volume's grid lies in world units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Placement {
    /// Outer corner of the grid (the minimum of every axis).
    pub origin: [f64; 3],
    /// Side of a voxel.
    pub voxel: f64,
}

impl Placement {
    /// Rejects placements no encoder writes.
    pub fn validate(&self) -> Result<(), FormatError> {
        if self.origin.iter().all(|v| v.is_finite()) && self.voxel.is_finite() && self.voxel > 0.0 {
            Ok(())
        } else {
            Err(FormatError::header(format!("bad placement {self:?}")))
        }
    }
}

/// A coded volume: header and stream as stored, the decoding operator, the placement.
#[derive(Clone, Debug)]
pub struct Volume {
    /// Frame, sizes, quantiser.
    pub header: OctreeHeader,
    /// The transform stream.
    pub stream: Vec<u8>,
    /// The decoding operator.
    pub operator: OctreeOperator,
    /// The grid in world units.
    pub placement: Placement,
}

impl Volume {
    /// Samples per side of the source grid.
    pub fn size(&self) -> usize {
        self.header.valid as usize
    }

    /// World bounds of the grid's cube: (min, max).
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let o = self.placement.origin;
        let side = self.size() as f64 * self.placement.voxel;
        (o, o.map(|v| v + side))
    }

    /// Unit coordinates of a world point; `None` outside the grid's cube (or not finite).
    pub fn unit(&self, p: [f64; 3]) -> Option<[f32; 3]> {
        let (lo, hi) = self.bounds();
        let u: [f64; 3] = std::array::from_fn(|a| (p[a] - lo[a]) / (hi[a] - lo[a]));
        u.iter()
            .all(|v| (0.0..=1.0).contains(v))
            .then(|| u.map(|v| v as f32))
    }
}

pub use crate::mesh::distance::{SurfaceDistance, surface_distance};
