//! What every codec shares: the operator form and its decoders, the transforms of a block, the
//! entropy coder and the quality metrics. Nothing here knows a codec or the asset file.

pub mod decode;
pub mod entropy;
pub mod fidelity;
pub mod lattice;
pub mod metrics;
pub mod operator;
pub mod pieces;
pub mod transform;
