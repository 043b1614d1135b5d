//! The quadtree partitioned IFS (Jacquin; Fisher): square ranges from a quadtree, each mapped
//! from a domain of twice its side by one of 8 isometries, with a contrast and an offset (or a
//! planar offset). The flow: [`partition`] splits the frame and [`search`] finds each range's
//! map; [`stream`] codes the tree and the maps; [`operator`] states them in the operator form.

pub(crate) mod encode;
pub mod operator;
pub mod partition;
pub(crate) mod plane;
pub(crate) mod pool;
pub mod search;
pub mod settings;
pub mod stream;
