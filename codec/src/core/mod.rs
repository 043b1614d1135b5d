//! What every codec shares: the operator form and its decoders, the transforms of a block, the
//! entropy coder, the quality metrics and what a reader finds wrong with coded bytes
//! ([`format::FormatError`]). Nothing here knows a codec or the asset file.

pub mod decode;
pub(crate) mod entropy;
pub mod fidelity;
pub mod format;
pub(crate) mod lattice;
pub mod metrics;
pub mod operator;
pub mod pieces;
pub(crate) mod transform;
