//! fractile's codecs: images, height fields, volumes and curves as partitioned iterated function
//! systems, with every decoder written once against one operator form,
//! `(W f)(p) = g_c(p) + s_c(p) f(phi_c(p))` (see [`operator`]).
//!
//! Data flows one way, and so do the imports, folder by folder:
//!
//! | stage | module | depends on |
//! |---|---|---|
//! | input | `io::raster` (images, DEMs), [`mesh`] (triangle meshes), [`geo`] | `core` |
//! | encode | [`mod@encode`] (rasters, meshes, curves: rate control, codec choice) | `codecs`, `io` |
//! | codecs | [`codecs`] (one folder each; encoders return coded planes) | `core`, `mesh`, the input |
//! | asset | `io::asset` (the container) | `codecs` |
//! | operator, decode | `core` (the operator form, its decoders, entropy coder) | nothing |
//! | output | [`extract`] (tiles, points, regions, distances), [`render`] | `io`, `codecs`, `core` |
//!
//! No module imports one that imports it back, in this crate or any other of the workspace
//! (`codec/tests/layout.rs` checks, resolving paths as the compiler does).
//!
//! No HTTP and no async here: the server calls these functions.
//!
//! What is public is a curated surface, as image-rs and rav1e publish theirs: the root
//! re-exports the common entry points (`Asset`, `Raster`, `encode`, `CodecSettings`, each
//! codec's settings, decode options), and the modules `core` (the operator form, its
//! decoders, the entropy coder) and `io` (files, the container) are private, what other crates
//! name of them published by concept below ([`asset`], [`chunked`], [`raster`], [`rows`],
//! [`mosaic`]; [`operator`], [`decode`], [`pieces`], [`metrics`]): a name moved inside them
//! changes no user's code, and a `pub` item no list names is an `unreachable_pub` warning.
//! The range coder and lattice coding, block transforms (`Quantiser` is re-exported), each
//! codec's `plane`, `fit`, `encode` and stream internals where no other crate names them, the
//! projected codec's grid machinery, the SDF and marching of IFS3D, the source-error measure
//! and colour conversion are crate-private. Each codec's module publishes what a user of that
//! codec needs, as image's `codecs::png` does: its settings (`codecs::fis::FisSettings`,
//! encoded through [`encode()`]), its operator; its search, stream and pyramid internals are
//! `#[doc(hidden)]`, public only for this crate's own integration tests and benches, and no
//! other crate of the workspace names them (`codec/tests/layout.rs` checks, grouped imports
//! included).

#[macro_use]
pub mod codecs;
mod core;
pub mod encode;
pub mod extract;
pub mod geo;
mod io;
pub mod mesh;
pub mod render;

/// The asset file: an [`Asset`] read and checked, its planes' operators, and files written
/// whole or not at all.
pub mod asset {
    pub use crate::io::asset::{
        Asset, AssetLimits, Body, ChunkCache, Chunked, Codec, Coding, FORMAT_VERSION, Mask,
        OLDEST_CURVE_VERSION, OLDEST_READ_VERSION, Plane, PlaneOperator, check_magic, check_opens,
        check_whole_file, temporary_owner, write_atomic, write_atomic_with,
    };
}

/// Chunked assets: the layout of their files, the sources they are read from by range, and
/// their assembly from chunks.
pub mod chunked {
    pub use crate::io::chunked::{
        CHUNK_SIDES, CHUNKED_CODEC, CHUNKED_PIXELS_FACTOR, CHUNKED_VERSION, CODED_TOP_VERSION,
        ChunkCache, ChunkEntry, ChunkSource, ChunkTable, Chunked, FileSource, InMemory, Level,
        MAGIC, MAX_CHUNKS, OLDEST_CHUNKED_VERSION, OVERLAP, VIEW_DEPTH, VIEW_OVERLAP, ViewLevel,
        assemble, chunk_files, file_crc, header, is_chunked, overlap_for,
    };
}

/// Input rasters (images, GeoTIFF and PNG DEMs) whole, and rasters written.
pub mod raster {
    pub use crate::io::raster::{
        MAX_MAGNITUDE, Raster, geotiff_f32, write_geotiff_f32, write_png8, write_png16,
    };
}

/// Input rasters read a band of rows at a time (inputs larger than memory).
pub mod rows {
    pub use crate::io::ranged::{KeptBudget, RangeReader, RangedFile};
    pub use crate::io::rows::{GeoTiff, Header, InMemory, Rows, TiffSource, is_tiff};
}

/// Several input rasters read as one, on one grid (inputs of another pixel size or alignment
/// in the same CRS resampled onto it).
pub mod mosaic {
    pub use crate::io::mosaic::{
        MAX_HEIGHT, MAX_WIDTH, Mosaic, input_files, mirrored, open, open_rows,
    };
    pub use crate::io::resample::{Reprojected, Resampled};
}

/// The operator form every codec is written against, `(W f)(p) = g_c(p) + s_c(p) f(phi_c(p))`.
pub mod operator {
    pub use crate::core::operator::{
        AffineCell, AxisAligned, AxisCell, Chain, ISOMETRY_MATRICES, Operator, Step, active,
        invariant_interval, run_chains_stepwise,
    };
}

/// The decoders written once against [`operator::Operator`]: discrete grids at any size,
/// continuous points, windows and volumes.
pub mod decode {
    pub use crate::core::decode::*;
}

/// Piecewise tables of a plane's cells, flattened for a device (the GPU's kernels).
pub mod pieces {
    pub use crate::core::pieces::{
        Ends, Flat, Flatten, Lattice, Offsets, Piece, PieceTable, SPLIT, bilinear,
    };
}

/// Quality metrics of a decode against its source.
pub mod metrics {
    pub use crate::core::metrics::{Errors, compare};
}

pub use crate::core::decode::{DiscreteOptions, Method};
pub use crate::core::format::FormatError;
pub use crate::core::transform::Quantiser;
pub use codecs::quadtree::search::SearchMode;
pub use codecs::quadtree::settings::{QuadtreeSettings, RateMode, Roi};
pub use codecs::registry::Codec;
pub use encode::{CodecSettings, Encoded, PlaneEncoder, encode, encode_default};
pub use io::asset::{Asset, AssetLimits, Body};
pub use io::raster::Raster;

/// The error beneath an [`Error`] (an I/O, TIFF or image error), shared so that an error stays
/// `Clone` (a corrupt chunk's error is kept and answered again).
pub type Cause = std::sync::Arc<dyn std::error::Error + Send + Sync + 'static>;

/// Everything that can go wrong, by whose fault: the input, the settings, an asset file,
/// writing the output, or a store that cannot be read now. Each kind carries its message for
/// people, the file it concerns where one does ([`Error::path`]), and the error beneath
/// ([`std::error::Error::source`]). Built with [`Error::input`] and its siblings, then
/// [`Error::at`] and [`Error::caused_by`].
#[derive(Clone, Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The input file or grid cannot be encoded.
    #[error("input: {message}")]
    #[non_exhaustive]
    Input {
        /// What is wrong, for people.
        message: String,
        /// The file it concerns.
        path: Option<std::path::PathBuf>,
        /// The error beneath.
        #[source]
        source: Option<Cause>,
    },
    /// The encoder settings are inconsistent.
    #[error("settings: {message}")]
    #[non_exhaustive]
    Settings {
        /// What is wrong, for people.
        message: String,
        /// The file it concerns.
        path: Option<std::path::PathBuf>,
        /// The error beneath.
        #[source]
        source: Option<Cause>,
    },
    /// An asset file is corrupt, truncated, or of an unknown version or codec.
    #[error("asset: {message}")]
    #[non_exhaustive]
    Asset {
        /// What is wrong, for people.
        message: String,
        /// The file it concerns.
        path: Option<std::path::PathBuf>,
        /// The error beneath.
        #[source]
        source: Option<Cause>,
    },
    /// An output could not be written.
    #[error("output: {message}")]
    #[non_exhaustive]
    Output {
        /// What is wrong, for people.
        message: String,
        /// The file it concerns.
        path: Option<std::path::PathBuf>,
        /// The error beneath.
        #[source]
        source: Option<Cause>,
    },
    /// A chunk's bytes could not be read from where the asset lies (a store that is down, a
    /// file gone): trying again later may succeed, unlike [`Error::asset`].
    #[error("unavailable: {message}")]
    #[non_exhaustive]
    Unavailable {
        /// What is wrong, for people.
        message: String,
        /// The file it concerns.
        path: Option<std::path::PathBuf>,
        /// The error beneath.
        #[source]
        source: Option<Cause>,
    },
}

/// The fields every kind of [`Error`] carries, by kind.
macro_rules! error_kinds {
    ($($kind:ident => $make:ident,)*) => {
        impl Error {
            $(
                #[doc = concat!("An [`Error::", stringify!($kind), "`] saying `message`.")]
                pub fn $make(message: impl Into<String>) -> Error {
                    Error::$kind { message: message.into(), path: None, source: None }
                }
            )*

            fn parts(&self) -> (&String, &Option<std::path::PathBuf>, &Option<Cause>) {
                match self {
                    $(Error::$kind { message, path, source } => (message, path, source),)*
                }
            }

            fn parts_mut(
                &mut self,
            ) -> (&mut String, &mut Option<std::path::PathBuf>, &mut Option<Cause>) {
                match self {
                    $(Error::$kind { message, path, source } => (message, path, source),)*
                }
            }
        }
    };
}

error_kinds! {
    Input => input,
    Settings => settings,
    Asset => asset,
    Output => output,
    Unavailable => unavailable,
}

impl Error {
    /// This error, concerning the file at `path` (its message unchanged).
    pub fn at(mut self, path: impl Into<std::path::PathBuf>) -> Error {
        *self.parts_mut().1 = Some(path.into());
        self
    }

    /// This error, caused by `cause` (kept as its [`std::error::Error::source`]).
    pub fn caused_by(mut self, cause: impl std::error::Error + Send + Sync + 'static) -> Error {
        *self.parts_mut().2 = Some(std::sync::Arc::new(cause));
        self
    }

    /// The same kind, path and cause, its message put after `context` (`chunk 3: ...`).
    pub fn within(mut self, context: impl std::fmt::Display) -> Error {
        let message = self.parts_mut().0;
        *message = format!("{context}: {message}");
        self
    }

    /// The message, for people, without the kind.
    pub fn message(&self) -> &str {
        self.parts().0
    }

    /// The file the error concerns, where it names one.
    pub fn path(&self) -> Option<&std::path::Path> {
        self.parts().1.as_deref()
    }
}
