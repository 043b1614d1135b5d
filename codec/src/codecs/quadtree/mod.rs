//! The quadtree partitioned IFS (Jacquin; Fisher): square ranges from a quadtree, each mapped
//! from a domain of twice its side by one of 8 isometries, with a contrast and an offset (or a
//! planar offset). The flow: [`partition`] splits the frame and [`search`] finds each range's
//! map; [`stream`] codes the tree and the maps; [`operator`] states them in the operator form.

pub(crate) mod encode;
#[doc(hidden)] // public for the crate's own integration tests and benches, not API
pub mod operator;
#[doc(hidden)] // public for the crate's own integration tests and benches, not API
pub mod partition;
pub(crate) mod plane;
pub(crate) mod pool;
#[doc(hidden)] // public for the crate's own integration tests and benches, not API
pub mod search;
pub(crate) mod settings;
pub use settings::*;
#[doc(hidden)] // public for the crate's own integration tests and benches, not API
pub mod stream;
