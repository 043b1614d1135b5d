//! What every codec shares: the operator form and its decoders, the transforms of a block, the
//! entropy coder, the quality metrics and what a reader finds wrong with coded bytes
//! ([`format::FormatError`]). Nothing here knows a codec or the asset file.

pub(crate) mod decode;
pub(crate) mod entropy;
pub(crate) mod fidelity;
pub(crate) mod format;
pub(crate) mod lattice;
pub(crate) mod metrics;
pub(crate) mod operator;
pub(crate) mod pieces;
pub(crate) mod transform;
