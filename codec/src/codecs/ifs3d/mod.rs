//! IFS3D: a mesh as a signed distance field (`sdf`), coded as an octree partitioned IFS
//! ([`OctreeOperator`]); surfaces come back by marching cubes (`isosurface`); [`volume`] holds the
//! decoded volume's placement in the world.

pub(crate) mod fit;
pub use fit::*;
pub(crate) mod isosurface;
pub(crate) mod octree;
pub use octree::*;
pub(crate) mod sdf;
#[doc(hidden)] // public for the crate's own integration tests and benches, not API
pub mod volume;
