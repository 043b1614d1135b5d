//! The piecewise self-affine model (psa2d) as a plane codec: how the container stores its
//! planes and how they are decoded.

use fractile_proto::AssetMeta;

use crate::codecs::plane::{Build, PlaneCodec, PlaneDecoder};
use crate::codecs::psa::{PsaHeader, PsaOperator, codec_name, decode_params};
use crate::core::format::FormatError;

impl PlaneCodec for PsaHeader {
    type Operator = PsaOperator;
    const BYTE: u8 = 3;
    const LABEL: &'static str = "psa2d";
    const NAME: Option<&'static str> = None;

    fn name(&self) -> &'static str {
        codec_name(self.tiling)
    }

    fn cost(&self, _meta: &AssetMeta, _stream: &[u8]) -> Result<u64, FormatError> {
        self.validate()?;
        // Vertex heights and region maps, about 64 bytes a vertex.
        let vertices: u64 = self.vertices().iter().map(|&n| n as u64).product();
        Ok(vertices.saturating_mul(64))
    }

    fn operator(
        &self,
        meta: &AssetMeta,
        stream: &[u8],
        _build: Build,
    ) -> Result<PsaOperator, FormatError> {
        if self.samples != [meta.width, meta.height] {
            return Err(FormatError::Header(
                "sample grid and metadata disagree".into(),
            ));
        }
        let params = decode_params(self, stream)?;
        PsaOperator::new(self, &params)
    }
}

impl PlaneDecoder for PsaOperator {
    fn max_contrast(&self) -> f32 {
        self.max_scaling()
    }

    fn transforms(&self) -> usize {
        self.regions()
    }
}
