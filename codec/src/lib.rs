//! fractile's codecs: images, height fields, volumes and curves as partitioned iterated function
//! systems, with every decoder written once against one operator form,
//! `(W f)(p) = g_c(p) + s_c(p) f(phi_c(p))` (see [`core::operator`]).
//!
//! Data flows one way, and so do the imports, folder by folder:
//!
//! | stage | module | depends on |
//! |---|---|---|
//! | input | [`io::raster`] (images, DEMs), [`mesh`] (triangle meshes), [`geo`] | `core` |
//! | encode | [`mod@encode`] (rasters, meshes, curves: rate control, codec choice) | `codecs`, `io` |
//! | codecs | [`codecs`] (one folder each) | `core`, `mesh` |
//! | asset | [`io::asset`] (the container) | `codecs` |
//! | operator, decode | [`core`] (the operator form, its decoders, entropy coder) | nothing |
//! | output | [`extract`] (tiles, points, regions, distances), [`render`] | `io`, `codecs`, `core` |
//!
//! No module imports one that imports it back, in this crate or any other of the workspace
//! (`codec/tests/layout.rs` checks, resolving paths as the compiler does).
//!
//! No HTTP and no async here: the server calls these functions.

pub mod codecs;
pub mod core;
pub mod encode;
pub mod extract;
pub mod geo;
pub mod io;
pub mod mesh;
pub mod render;

pub use crate::core::decode::{DiscreteOptions, Method};
pub use crate::core::transform::Quantiser;
pub use codecs::quadtree::search::SearchMode;
pub use encode::{EncodeSettings, Encoded, RateMode, Roi, encode, encode_default};
pub use io::asset::{Asset, AssetLimits};
pub use io::raster::Raster;

/// Everything that can go wrong, by whose fault: the input, the settings, an asset file, or
/// writing the output. Messages name the file and the problem.
#[derive(Clone, Debug, thiserror::Error)]
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
    /// A chunk's bytes could not be read from where the asset lies (a store that is down, a
    /// file gone): trying again later may succeed, unlike [`Error::Asset`].
    #[error("unavailable: {0}")]
    Unavailable(String),
}
