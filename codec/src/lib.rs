//! fractile's codecs: images, height fields (and later volumes and curves) as partitioned
//! iterated function systems, with every decoder written once against one operator form,
//! `(W f)(p) = g_c(p) + s_c(p) f(phi_c(p))` (see [`operator`]).
//!
//! Data flows one way: [`raster`] (input) -> [`encode()`] (using [`search`], [`partition`],
//! [`stream`], [`entropy`]) -> [`asset`] (the file) -> [`operator`] -> [`decode`] and [`extract`]
//! (output). No HTTP and no async here: the server calls these functions.

pub mod asset;
pub mod colour;
pub mod curve;
pub mod decode;
pub mod encode;
pub mod entropy;
pub mod extract;
pub mod fis;
pub mod geo;
pub mod isosurface;
pub mod mesh;
pub mod metrics;
pub mod octree;
pub mod operator;
pub mod partition;
pub mod pieces;
pub mod psa;
pub mod raster;
pub mod render;
pub mod sdf;
pub mod search;
pub mod stream;
pub mod transform;
pub mod volume;

pub use asset::{Asset, AssetLimits};
pub use decode::{DiscreteOptions, Method};
pub use encode::{EncodeSettings, Encoded, RateMode, Roi, encode};
pub use raster::Raster;
pub use search::SearchMode;
pub use transform::Quantiser;

/// Everything that can go wrong, by whose fault: the input, the settings, an asset file, or
/// writing the output. Messages name the file and the problem.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The input file or grid cannot be encoded.
    #[error("input: {0}")]
    Input(String),
    /// The encoder settings are inconsistent.
    #[error("settings: {0}")]
    Settings(String),
    /// An asset file is corrupt, truncated, or of an unknown version or codec.
    #[error("asset: {0}")]
    Asset(String),
    /// An output could not be written.
    #[error("output: {0}")]
    Output(String),
}
