//! The quadtree PIFS as a plane codec: how the container stores its planes and how they are
//! decoded (its operators' cells are lattice boxes, so grids and patches step by blocks).

use fractile_proto::AssetMeta;

use crate::codecs::plane::{Build, PlaneCodec, PlaneDecoder};
use crate::codecs::quadtree::operator::QuadtreeOperator;
use crate::codecs::quadtree::stream::{PlaneHeader, decode_plane, operator};
use crate::core::decode::{self, Patch, PointValue};
use crate::core::format::FormatError;

impl PlaneCodec for PlaneHeader {
    type Operator = QuadtreeOperator;
    const BYTE: u8 = 1;
    const LABEL: &'static str = "quadtree PIFS";
    const NAME: Option<&'static str> = Some("quadtree-pifs");

    fn name(&self) -> &'static str {
        "quadtree-pifs"
    }

    fn cost(&self, meta: &AssetMeta, stream: &[u8]) -> Result<u64, FormatError> {
        self.validate()?;
        check_extent(meta, self.valid)?;
        Ok(self.operator_bytes(stream.len()))
    }

    fn operator(
        &self,
        _meta: &AssetMeta,
        stream: &[u8],
        _build: Build,
    ) -> Result<QuadtreeOperator, FormatError> {
        let leaves = decode_plane(self, stream)?;
        operator(self, &leaves)
    }
}

/// Checks that a plane's coded extent is the metadata's grid (chroma: half of it; a
/// supersampled plane: twice): a file may not claim a grid its planes do not code.
fn check_extent(meta: &AssetMeta, valid: [f32; 2]) -> Result<(), FormatError> {
    let (w, h) = (meta.width as f32, meta.height as f32);
    let fits = [0.5f32, 1.0, 2.0]
        .iter()
        .any(|&k| (valid[0] - k * w).abs() <= 0.5 * k && (valid[1] - k * h).abs() <= 0.5 * k);
    if fits {
        Ok(())
    } else {
        Err(FormatError::header(format!(
            "the plane codes an extent of {}x{} where the metadata says {}x{}",
            valid[0], valid[1], meta.width, meta.height
        )))
    }
}

impl PlaneDecoder for QuadtreeOperator {
    fn grid(&self, xs: &[f32], ys: &[f32], iterations: u32, tolerance: f32) -> Vec<PointValue> {
        decode::grid(self, xs, ys, iterations, tolerance)
    }

    fn patch(&self, patch: &Patch, iterations: u32, tolerance: f32) -> Vec<PointValue> {
        decode::patch(self, patch, iterations, tolerance)
    }

    fn max_contrast(&self) -> f32 {
        self.ranges()
            .iter()
            .fold(0.0f32, |m, r| m.max(r.contrast.abs()))
    }

    fn transforms(&self) -> usize {
        self.ranges().len()
    }
}
