//! IFS3D: a mesh as a signed distance field (`sdf`), coded as an octree partitioned IFS
//! ([`octree`]); surfaces come back by marching cubes (`isosurface`); [`volume`] holds the
//! decoded volume's placement in the world.

pub mod fit;
pub(crate) mod isosurface;
pub mod octree;
pub(crate) mod sdf;
pub mod volume;
