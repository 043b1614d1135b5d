//! A raster answer in one call ([`Asset::answer`]): a request (pixels, steps, a tolerance or
//! none) in, the values, the bounds and the tolerance used out, as martin's sources answer
//! `get_tile`. The source error over the pixels is found once and serves both the settled
//! tolerance and the answer's bound (the server asked for it twice a tile, and a chunked
//! asset split the pixels into its chunks for each).

use super::points::settled_over;
use super::{Resources, SampleError};
use crate::geo::Pixels;
use crate::io::asset::Asset;

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

impl Asset {
    /// The answer at `request.pixels`, using `resources` (a device for its chains, coarse
    /// grids kept, a flag to stop: see [`Asset::sample_with`]). Fails where a chunk under the
    /// pixels cannot be read, or once `resources.given_up` is set.
    pub fn answer(
        &self,
        request: &Request<'_>,
        resources: &Resources<'_>,
    ) -> Result<Sampled, SampleError> {
        let pixels = request.pixels;
        let source = self.source_error_over(pixels).map_err(SampleError::Chunk)?;
        let tolerance = request
            .tolerance
            .unwrap_or_else(|| settled_over(self.default_tolerance(), source));
        let (channels, convergence) =
            self.sample_with(pixels, request.iterations, tolerance, resources)?;
        Ok(Sampled {
            channels,
            convergence,
            source,
            tolerance,
        })
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
