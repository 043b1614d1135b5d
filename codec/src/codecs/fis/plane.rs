//! Fractal interpolation surfaces as a plane codec: how the container stores their planes
//! (height fields only) and how they are decoded.

use fractile_proto::{AssetKind, AssetMeta};

use crate::Error;
use crate::codecs::fis::{FisHeader, FisOperator, codec_name, decode_params};
use crate::codecs::plane::{Build, PlaneCodec, PlaneDecoder};
use crate::core::format::FormatError;

impl PlaneCodec for FisHeader {
    type Operator = FisOperator;
    const BYTE: u8 = 2;
    const LABEL: &'static str = "FIS";
    const NAME: Option<&'static str> = None;

    fn name(&self) -> &'static str {
        codec_name(self.scaling)
    }

    fn accepts(meta: &AssetMeta) -> Result<(), Error> {
        if meta.kind == AssetKind::HeightField {
            Ok(())
        } else {
            Err(Error::asset(
                "fractal interpolation surfaces code height fields only",
            ))
        }
    }

    fn cost(&self, _meta: &AssetMeta, _stream: &[u8]) -> Result<u64, FormatError> {
        self.validate()?;
        // Node heights, scalings and a piece per cell, about 64 bytes a node.
        let nodes: u64 = self.nodes().iter().map(|&n| n as u64).product();
        Ok(nodes.saturating_mul(64))
    }

    fn operator(
        &self,
        meta: &AssetMeta,
        stream: &[u8],
        _build: Build,
    ) -> Result<FisOperator, FormatError> {
        if self.samples != [meta.width, meta.height] {
            return Err(FormatError::Header(
                "sample grid and metadata disagree".into(),
            ));
        }
        let params = decode_params(self, stream)?;
        FisOperator::new(self, &params)
    }
}

impl PlaneDecoder for FisOperator {
    fn max_contrast(&self) -> f32 {
        self.max_scaling()
    }

    fn transforms(&self) -> usize {
        self.cells()
    }
}
