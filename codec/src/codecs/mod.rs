//! The codecs, one folder each: how a codec partitions its support, searches its maps, codes
//! them and states them as an [`crate::core::operator::Operator`]. A codec depends on
//! [`crate::core`] only; the asset container ([`crate::io::asset`]) depends on the codecs.
//!
//! | codec | asset kinds | folder |
//! |---|---|---|
//! | quadtree PIFS (codec 1) | images, height fields | [`quadtree`] |
//! | fractal interpolation surfaces (codec 2) | height fields | [`fis`] |
//! | projected IFS with details on surfaces (codecs 3, 4) | height fields | [`psa`] |
//! | IFS3D on signed distance fields (octree) | volumes (meshes) | [`ifs3d`] |
//! | projected IFS with details on curves (codec 5) | curves | [`curve`] |
//! | projected IFS with details on grids (codec 6) | height fields, grey images | [`projected`] |

pub mod curve;
pub mod fis;
pub mod ifs3d;
pub mod projected;
pub mod psa;
pub mod quadtree;
