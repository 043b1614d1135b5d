//! What reading a plane codec's payload costs, from its headers, before any stream is
//! decoded: what a reader checks against [`AssetLimits`](super::container::AssetLimits) and a
//! writer checks before it writes (`io::asset::check_opens`).

use fractile_proto::AssetMeta;

use crate::Error;
use crate::codecs::coded::Payload;
use crate::codecs::registry::{Registered, Visit};

/// What decoding a plane codec's payload takes, from its headers, before anything is decoded:
/// its operators, its mask (a byte per cell and a small summary) and one full-resolution
/// discrete decode (two f32 grids per plane).
pub(crate) fn payload_cost<H: Registered>(meta: &AssetMeta, p: &Payload<H>) -> Result<u64, Error> {
    let (w, h) = (u64::from(meta.width), u64::from(meta.height));
    let mut operators = 0u64;
    for (i, (header, stream)) in p.planes.iter().enumerate() {
        let bytes = header
            .cost(meta, stream)
            .map_err(|e| Error::asset(format!("plane {i}: {e}")))?;
        operators = operators.saturating_add(bytes);
    }
    let mask_bytes = p.mask.as_ref().map_or(0, |_| w * h + w * h / 64);
    let discrete = 8 * w * h * p.planes.len() as u64;
    Ok(operators.saturating_add(mask_bytes + discrete))
}

/// [`payload_cost`] of a payload's bytes.
pub(crate) struct PayloadCost<'a> {
    pub(crate) meta: &'a AssetMeta,
    pub(crate) payload: &'a [u8],
}

impl Visit for PayloadCost<'_> {
    type Output = Result<u64, Error>;

    fn visit<H: Registered>(self) -> Result<u64, Error> {
        let p: Payload<H> =
            fractile_proto::decode(self.payload).map_err(|e| Error::asset(e.to_string()))?;
        payload_cost(self.meta, &p)
    }
}
