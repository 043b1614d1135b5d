//! What a reader needs to decode a projected plane's stream ([`ProjectedHeader`]).

use serde::{Deserialize, Serialize};

use crate::codecs::projected::pyramid;
use crate::core::format::FormatError;

/// What a reader needs to decode a plane's stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProjectedHeader {
    /// Source width and height in samples.
    pub samples: [u32; 2],
    /// Refinement levels: the control grid has a sample every `2^levels`.
    pub levels: u8,
    /// Quantiser step of the finest level, source units.
    pub step: f64,
    /// Step growth per coarser level (1 in max-error mode).
    pub growth: f64,
    /// The source's quantum (0 for continuous values).
    pub quantum: f64,
    /// Lowest value of the coding range (source units): decoded samples are normalised by it.
    pub value_min: f64,
    /// Width of the coding range.
    pub value_span: f64,
    /// The detail scaling of the continuation past the finest level, in [0, 0.95].
    pub roughness: f32,
    /// The bound the encoder promised (source units); 0 with a quantum is lossless, 0 without
    /// one is rate mode (no promise, see [`ProjectedHeader::promise`]).
    pub max_error: f64,
    /// The multiresolution: the pyramid's order of each level's passes (the encoder keeps the
    /// one that codes smaller), or a lifted kernel (rate mode).
    pub order: pyramid::Order,
}

impl ProjectedHeader {
    /// Rejects headers no encoder writes.
    pub fn validate(&self) -> Result<(), FormatError> {
        let [w, h] = self.samples;
        if !(2..=1 << 16).contains(&w) || !(2..=1 << 16).contains(&h) {
            return Err(FormatError::header(format!(
                "bad projected sample grid {w}x{h}"
            )));
        }
        if self.levels > 12 {
            return Err(FormatError::header(format!(
                "bad projected level count {}",
                self.levels
            )));
        }
        let finite = [
            self.step,
            self.growth,
            self.quantum,
            self.value_min,
            self.value_span,
        ];
        if finite.iter().any(|v| !v.is_finite()) || self.step <= 0.0 {
            return Err(FormatError::header("bad projected quantiser"));
        }
        if !(0.5..=4.0).contains(&self.growth) || self.quantum < 0.0 || self.value_span <= 0.0 {
            return Err(FormatError::header(
                "bad projected step growth, quantum or value range",
            ));
        }
        if !(0.0..=0.95).contains(&self.roughness) {
            return Err(FormatError::header(format!(
                "bad projected roughness {}",
                self.roughness
            )));
        }
        if self.order.lifting().is_some() && (self.max_error != 0.0 || self.quantum != 0.0) {
            return Err(FormatError::header(
                "a lifted projected plane makes no per-sample promise",
            ));
        }
        Ok(())
    }

    pub(super) fn layout(&self) -> pyramid::Layout {
        pyramid::Layout {
            size: [self.samples[0] as usize, self.samples[1] as usize],
            levels: u32::from(self.levels),
            step: self.step,
            growth: self.growth,
            quantum: self.quantum,
            order: self.order,
        }
    }

    /// The encoder's promise at every valid sample, source units: `max_error` in max-error mode
    /// (which sets a quantum, or a positive bound on continuous data); none under rate control.
    /// It holds in what readers receive: the step keeps the bound less the float32 roundings
    /// of an answer on a continuous source, and answers on a quantum are rounded onto it
    /// (`bound::delivery_margin`).
    pub fn promise(&self) -> Option<f64> {
        (self.max_error > 0.0 || self.quantum > 0.0).then_some(self.max_error)
    }

    /// The quantum the samples lie on where the encoder promised a bound on one (max-error and
    /// bounded modes), with how near an answer must be to be delivered onto it: its float32
    /// roundings ([`super::bound::delivery_margin`]), far under half a quantum.
    pub(crate) fn delivered_quantum(&self) -> Option<(f64, f64)> {
        let near = super::bound::delivery_margin(self.value_min, self.value_span);
        (self.quantum > 0.0 && near < 0.25 * self.quantum).then_some((self.quantum, near))
    }

    /// Samples in all.
    pub fn cells(&self) -> usize {
        self.samples[0] as usize * self.samples[1] as usize
    }
}

/// The codec's name (`fractile encode --codec projected`).
pub const CODEC_NAME: &str = "projected";
