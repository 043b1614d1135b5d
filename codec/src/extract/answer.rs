//! An answer in one call ([`Asset::answer`]): a request (pixels or points, steps, a tolerance
//! or none) in, the values, the bounds and the tolerance used out, as martin's sources answer
//! `get_tile`; each kind of request ([`Question`]) names its kind of answer. The source error
//! over a raster's pixels is found once and serves both the settled tolerance and the
//! answer's bound (the server asked for it twice a tile, and a chunked asset split the pixels
//! into its chunks for each).

use super::points::settled_over;
use super::volume::DistanceSample;
use super::{PointSample, Resources, SampleError};
use crate::geo::Pixels;
use crate::io::asset::Asset;

/// A request an asset answers ([`Asset::answer`]), and the answer it gets.
pub trait Question {
    /// What the asset answers.
    type Reply;

    /// The answer of `asset`, using `resources`.
    fn ask(&self, asset: &Asset, resources: &Resources<'_>) -> Result<Self::Reply, SampleError>;
}

/// What a raster answer asks.
#[derive(Clone, Copy, Debug)]
pub struct Request<'a> {
    /// Where: a tile's, a region's or a mesh's pixels on the asset.
    pub pixels: &'a Pixels,
    /// The most steps of a chain.
    pub iterations: u32,
    /// Each chain stops once its bound is under this (value units; 0: after `iterations`
    /// steps exactly); `None`: settled over the pixels, as [`Asset::tolerance_over`] says.
    pub tolerance: Option<f32>,
}

/// A raster answer.
#[derive(Clone, Debug)]
pub struct Sampled {
    /// Values per channel, a pixel each (NaN on nodata).
    pub channels: Vec<Vec<f32>>,
    /// The largest bound on |value - attractor| of the pixels (value units).
    pub convergence: f32,
    /// The largest source error over the pixels (the map's, or the codec's promise), where
    /// the asset has one.
    pub source: Option<f32>,
    /// The tolerance the chains stopped at.
    pub tolerance: f32,
}

impl Question for Request<'_> {
    type Reply = Sampled;

    /// The answer at `self.pixels`, with `resources` (a device for its chains, coarse grids
    /// kept, a flag to stop: see [`Asset::sample_with`]). Fails where a chunk under the pixels
    /// cannot be read, or once `resources.given_up` is set.
    fn ask(&self, asset: &Asset, resources: &Resources<'_>) -> Result<Sampled, SampleError> {
        let source = asset
            .source_error_over(self.pixels)
            .map_err(SampleError::Chunk)?;
        let tolerance = self
            .tolerance
            .unwrap_or_else(|| settled_over(asset.default_tolerance(), source));
        let (channels, convergence) =
            asset.sample_with(self.pixels, self.iterations, tolerance, resources)?;
        Ok(Sampled {
            channels,
            convergence,
            source,
            tolerance,
        })
    }
}

/// What a points answer asks: values one by one, each with its own bounds.
#[derive(Clone, Copy, Debug)]
pub struct Points<'a> {
    /// Where, in unit coordinates of the asset.
    pub points: &'a [[f32; 2]],
    /// The most steps of a chain.
    pub iterations: u32,
    /// Each chain stops once its bound is under this (value units; 0: after `iterations`
    /// steps exactly); `None`: the asset's default ([`Asset::default_tolerance`]), what a
    /// point converges to when its request names neither steps nor a tolerance.
    pub tolerance: Option<f32>,
}

impl Question for Points<'_> {
    type Reply = Vec<PointSample>;

    /// Each point's values and bounds, its chains offered to `resources.device`. Fails where a
    /// chunk under the points cannot be read.
    fn ask(
        &self,
        asset: &Asset,
        resources: &Resources<'_>,
    ) -> Result<Vec<PointSample>, SampleError> {
        let tolerance = self.tolerance.unwrap_or_else(|| asset.default_tolerance());
        let device = resources.device.unwrap_or(&|_, _, _, _| None);
        asset
            .try_points_with(self.points, self.iterations, tolerance, device)
            .map_err(SampleError::Chunk)
    }
}

/// What a volume's answer asks: signed distances at world points, each with its bound.
#[derive(Clone, Copy, Debug)]
pub struct Distances<'a> {
    /// Where, in the mesh's (world) units.
    pub points: &'a [[f64; 3]],
    /// The most steps of a chain.
    pub iterations: u32,
    /// Each chain stops once its bound is under this (world units; 0: after `iterations`
    /// steps exactly); `None`: the asset's default ([`Asset::default_tolerance`]).
    pub tolerance: Option<f32>,
}

impl Question for Distances<'_> {
    type Reply = Vec<Option<DistanceSample>>;

    /// Each point's distance and bound (`None` outside the grid); refused by an asset that is
    /// no volume.
    fn ask(
        &self,
        asset: &Asset,
        _resources: &Resources<'_>,
    ) -> Result<Vec<Option<DistanceSample>>, SampleError> {
        let tolerance = self.tolerance.unwrap_or_else(|| asset.default_tolerance());
        asset
            .distances(self.points, self.iterations, tolerance)
            .map_err(SampleError::Refused)
    }
}

impl Asset {
    /// The answer to `question` (the pixels of a tile, a region or a mesh: [`Request`];
    /// points one by one: [`Points`]; a volume's distances: [`Distances`]), using `resources`:
    /// one call whatever the asset's body.
    pub fn answer<Q: Question>(
        &self,
        question: &Q,
        resources: &Resources<'_>,
    ) -> Result<Q::Reply, SampleError> {
        question.ask(self, resources)
    }
}

impl Asset {
    /// `pixels` made a mesh's vertices (a terrain tile's grid at or coarser than the source):
    /// a projected asset (the DEM default) answers a vertex with its decoded samples filtered
    /// over at least one source cell around it, which is bounded against the source filtered
    /// the same way, the same footprint for every tile of a level, so that shared edge vertices
    /// decode alike. Other codecs keep point decodes at the vertices: their filtered pixels
    /// come through a discrete decode at the grid's size, and neighbours' shared edge vertices
    /// came out up to 1.5 m apart.
    pub fn vertex_pixels(&self, mut pixels: Pixels) -> Pixels {
        if self.codec_name() == crate::codecs::projected::CODEC_NAME {
            let (cw, ch) = (self.meta.width.max(1), self.meta.height.max(1));
            let cell = [1.0001 / cw as f32, 1.0001 / ch as f32];
            pixels.footprint = [
                pixels.footprint[0].max(cell[0]),
                pixels.footprint[1].max(cell[1]),
            ];
        }
        pixels
    }
}
