//! What a codec of 2D planes gives the rest of the crate: how its planes are stored
//! ([`PlaneCodec`], implemented by its header) and how they are decoded ([`PlaneDecoder`],
//! implemented by its operator); how they are coded is `coded::PlaneEncoder`, implemented by
//! its settings. The registry (`codecs::registry`) lists the codecs that implement them; the
//! container, the decoders, the GPU and the server see only these two.

use std::fmt::Debug;

use fractile_proto::AssetMeta;
use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::Error;
use crate::core::decode::{self, Patch, PointValue};
use crate::core::format::FormatError;
use crate::core::operator::Operator;
use crate::core::pieces::Flatten;

/// How an asset's operators are built when it is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Build {
    /// Whole: everything an answer reads, made once (every asset but chunks).
    Whole,
    /// Lazily where the codec can (the projected codec's `ProjectedOperator::lazy`): chunks of
    /// chunked assets, which a server keeps by the hundred.
    Lazy,
}

/// A codec of 2D planes, as the container stores it: the plane's header (what a reader
/// needs before the stream) is the implementing type, and a plane is that header and its
/// entropy-coded stream. A file's payload is its planes and its mask, one codec for all planes.
pub trait PlaneCodec: Clone + Debug + Serialize + DeserializeOwned + Send + Sync + 'static {
    /// The plane's decoding operator.
    type Operator: PlaneDecoder;
    /// The codec byte of the container (offset 11), which names the payload.
    const BYTE: u8;
    /// How an error that lists what a build reads names it.
    const LABEL: &'static str;
    /// The codec's name when its byte tells it (a chunked file's table names only a byte);
    /// `None` where the header does (several names share a byte).
    const NAME: Option<&'static str>;

    /// The codec's name as the CLI and the API spell it.
    fn name(&self) -> &'static str;

    /// Checks that the codec codes assets of this metadata (its kind, its channels).
    fn accepts(_meta: &AssetMeta) -> Result<(), Error> {
        Ok(())
    }

    /// Checks the header against the metadata without decoding anything, and estimates the
    /// bytes of the plane's operator (what a reader's limits are checked against before it
    /// allocates).
    fn cost(&self, meta: &AssetMeta, stream: &[u8]) -> Result<u64, FormatError>;

    /// Decodes the plane's stream into its operator.
    fn operator(
        &self,
        meta: &AssetMeta,
        stream: &[u8],
        build: Build,
    ) -> Result<Self::Operator, FormatError>;
}

/// A plane's decoding operator: [`Operator`] with the batch decoders written once in
/// `core::decode`, which a codec overrides where it has a faster path giving the same answers.
/// Each call resolves the codec once per batch, so that the chain loop is monomorphised on
/// the codec's own `step` (through an enum, `step` is a match the compiler does not inline:
/// measured, 37% of an uncached tile's time).
pub trait PlaneDecoder: Operator<2> + Flatten + Clone + Debug + Send + Sync + Sized {
    /// [`decode::points`].
    fn points(&self, pts: &[[f32; 2]], iterations: u32, tolerance: f32) -> Vec<PointValue> {
        decode::points(self, pts, iterations, tolerance)
    }

    /// Continuous decoding of the separable grid `(xs[i], ys[j])`, row-major; by default the
    /// listed points (codecs whose cells are axis-aligned boxes step blocks together).
    fn grid(&self, xs: &[f32], ys: &[f32], iterations: u32, tolerance: f32) -> Vec<PointValue> {
        let pts: Vec<[f32; 2]> = ys
            .iter()
            .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
            .collect();
        self.points(&pts, iterations, tolerance)
    }

    /// The steps [`Self::grid`] takes at every point where it takes the same everywhere;
    /// `None` where each chain takes its own.
    fn grid_steps(
        &self,
        _xs: &[f32],
        _ys: &[f32],
        _iterations: u32,
        _tolerance: f32,
    ) -> Option<u32> {
        None
    }

    /// Continuous decoding of a bilinear [`Patch`] of points, row-major.
    fn patch(&self, patch: &Patch, iterations: u32, tolerance: f32) -> Vec<PointValue> {
        let pts: Vec<[f32; 2]> = (0..patch.height)
            .flat_map(|j| (0..patch.width).map(move |i| patch.at(i, j).map(|t| t as f32)))
            .collect();
        self.points(&pts, iterations, tolerance)
    }

    /// [`decode::point`].
    fn point(&self, p: [f32; 2], iterations: u32) -> PointValue {
        decode::point(self, p, iterations)
    }

    /// The attractor's values at the source's own sample centres where the codec knows them
    /// without iterating, normalised and row-major.
    fn samples(&self) -> Option<&[f32]> {
        None
    }

    /// Keeps continuous answers `values` at unit points `pts` in the neighbourhood of the data,
    /// for codecs whose continuation could leave it; by default they are left as they are.
    fn limit_points(&self, _pts: &[[f32; 2]], _values: &mut [f32]) {}

    /// [`Self::limit_points`] on the separable grid `(xs[i], ys[j])`, row-major.
    fn limit_grid(&self, _xs: &[f32], _ys: &[f32], _values: &mut [f32]) {}

    /// Largest |s| anywhere.
    fn max_contrast(&self) -> f32;

    /// Maps of the operator: ranges, cells or regions.
    fn transforms(&self) -> usize;

    /// Estimated resident bytes of the operator of a plane of `cells` source cells (what a
    /// cache of decoded chunks counts); 16 a cell unless the codec counts its own (the
    /// quadtree's measured 13 B a sample on the 9.3 Mpx mosaic, counted 16).
    fn resident_bytes(&self, cells: u64) -> u64 {
        cells * 16
    }
}
