//! The projected IFS with details as a plane codec: how the container stores its planes (a
//! colour asset's chroma at half resolution) and how they are decoded, through its own
//! chains, grids by subdivision and the neighbourhood limit.

use fractile_proto::{AssetMeta, ColourModel};

use crate::codecs::plane::{Build, PlaneCodec, PlaneDecoder};
use crate::codecs::projected::{CODEC_NAME, ProjectedHeader, ProjectedOperator, decode_grid};
use crate::core::decode::PointValue;
use crate::core::format::FormatError;

impl PlaneCodec for ProjectedHeader {
    type Operator = ProjectedOperator;
    const BYTE: u8 = 6;
    const LABEL: &'static str = "projected";
    const NAME: Option<&'static str> = Some(CODEC_NAME);

    fn name(&self) -> &'static str {
        CODEC_NAME
    }

    fn cost(&self, _meta: &AssetMeta, _stream: &[u8]) -> Result<u64, FormatError> {
        self.validate()?;
        // The decoded grid as f64 while decoding, then the samples as f32 and g at nine
        // half-lattice points a cell: about 48 bytes a sample.
        let samples = u64::from(self.samples[0]) * u64::from(self.samples[1]);
        Ok(samples.saturating_mul(48))
    }

    fn operator(
        &self,
        meta: &AssetMeta,
        stream: &[u8],
        build: Build,
    ) -> Result<ProjectedOperator, FormatError> {
        let (w, h) = (meta.width, meta.height);
        // Chroma of a colour asset is coded at half resolution (as the quadtree's).
        let chroma =
            meta.colour == ColourModel::YCbCr && self.samples == [w.div_ceil(2), h.div_ceil(2)];
        if self.samples != [w, h] && !chroma {
            return Err(FormatError::Header(
                "sample grid and metadata disagree".into(),
            ));
        }
        let grid = decode_grid(self, stream)?;
        let mut operator = match build {
            Build::Whole => ProjectedOperator::new(self, &grid),
            Build::Lazy => ProjectedOperator::lazy(self, grid),
        }?;
        if chroma && self.samples != [w, h] {
            operator = operator.with_valid([w as f32 / 2.0, h as f32 / 2.0]);
        }
        Ok(operator)
    }
}

impl PlaneDecoder for ProjectedOperator {
    fn points(&self, pts: &[[f32; 2]], iterations: u32, tolerance: f32) -> Vec<PointValue> {
        ProjectedOperator::points(self, pts, iterations, tolerance)
    }

    fn grid(&self, xs: &[f32], ys: &[f32], iterations: u32, tolerance: f32) -> Vec<PointValue> {
        ProjectedOperator::grid(self, xs, ys, iterations, tolerance)
    }

    fn grid_steps(&self, xs: &[f32], ys: &[f32], iterations: u32, tolerance: f32) -> Option<u32> {
        ProjectedOperator::grid_steps(self, xs, ys, iterations, tolerance)
    }

    fn point(&self, p: [f32; 2], iterations: u32) -> PointValue {
        // Through its own chains, which end on the bilinear interpolant (see
        // `ProjectedOperator::run_chains`), so that one point and a batch agree.
        ProjectedOperator::points(self, &[p], iterations, 0.0)[0]
    }

    fn samples(&self) -> Option<&[f32]> {
        Some(ProjectedOperator::samples(self))
    }

    fn limit_points(&self, pts: &[[f32; 2]], values: &mut [f32]) {
        ProjectedOperator::limit_points(self, pts, values);
    }

    fn limit_grid(&self, xs: &[f32], ys: &[f32], values: &mut [f32]) {
        ProjectedOperator::limit_grid(self, xs, ys, values);
    }

    fn max_contrast(&self) -> f32 {
        self.roughness()
    }

    fn transforms(&self) -> usize {
        self.cells()
    }

    fn resident_bytes(&self, _cells: u64) -> u64 {
        ProjectedOperator::resident_bytes(self)
    }
}
