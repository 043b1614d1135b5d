//! How the pyramid's details are coded: the contexts of a walk (of the kind its order names)
//! and the walk's two sides, the encoder's [`Quantiser`] and the decoder's [`Reader`].

use super::pyramid::{CONTEXTS, Details, FEATURES, Order, Sample, WEIGHT_LIMIT};
use crate::core::entropy::{Bit, Decoder, Encoder, TwoRateBit};
use crate::core::lattice::IntCoder;

/// The coders of one walk: per pass a set of contexts, plus the weights' coder.
pub struct Coders {
    passes: Contexts,
    weights: IntCoder,
}

/// The details' contexts of a walk, of the kind its order codes with.
enum Contexts {
    /// One-rate contexts, signs in one context (formats up to 8).
    Bit(Vec<IntCoder<Bit>>),
    /// Two-rate contexts, signs in context (format 9).
    TwoRate(Vec<IntCoder<TwoRateBit>>),
}

impl Coders {
    /// Fresh contexts for a walk of `order`.
    pub fn new(order: Order) -> Coders {
        let n = 4 * CONTEXTS;
        Coders {
            passes: if order.two_rate() {
                Contexts::TwoRate((0..n).map(|_| IntCoder::fresh()).collect())
            } else {
                Contexts::Bit((0..n).map(|_| IntCoder::fresh()).collect())
            },
            weights: IntCoder::new(),
        }
    }

    /// Codes the detail `q` of `s`.
    fn put(&mut self, encoder: &mut Encoder, s: &Sample, q: i32) {
        match &mut self.passes {
            Contexts::Bit(c) => c[s.context].put(encoder, q),
            Contexts::TwoRate(c) => c[s.context].put_signed(encoder, q, s.sign),
        }
    }

    /// Reads the detail of `s`.
    fn get(&mut self, decoder: &mut Decoder, s: &Sample) -> i32 {
        match &mut self.passes {
            Contexts::Bit(c) => c[s.context].get(decoder),
            Contexts::TwoRate(c) => c[s.context].get_signed(decoder, s.sign),
        }
    }

    /// What coding `q` at `s` would cost now, in bits.
    fn cost(&self, s: &Sample, q: i32) -> f64 {
        match &self.passes {
            Contexts::Bit(c) => c[s.context].cost(q, 0),
            Contexts::TwoRate(c) => c[s.context].cost(q, s.sign),
        }
    }
}

/// The encoder's side: quantises each source sample against its prediction and codes the detail.
pub struct Quantiser<'a> {
    /// The source (filled where invalid), source units.
    pub source: &'a [f64],
    /// Which samples count (invalid ones take their prediction: a zero detail).
    pub valid: Option<&'a [bool]>,
    /// Fraction of a step the dead zone adds around zero (0 in max-error mode).
    pub dead_zone: f64,
    /// Rate-distortion weight of a bit, in squared steps (0: plain rounding; max-error mode).
    pub lambda: f64,
    /// The stream.
    pub encoder: Encoder,
    /// Contexts.
    pub coders: Coders,
}

impl Details for Quantiser<'_> {
    fn sample(&mut self, s: &Sample) -> (f64, i32) {
        let valid = self.valid.is_none_or(|v| v[s.index]);
        let q = if valid {
            let r = (self.source[s.index] - s.prediction) / s.step;
            let m = (r.abs() + 0.5 - self.dead_zone).floor().max(0.0);
            let q = (m.min(f64::from(i32::MAX / 2)) as i32) * if r < 0.0 { -1 } else { 1 };
            if self.lambda > 0.0 && q != 0 {
                // Rate-distortion choice between q and one step nearer zero, in units of
                // step^2: the squared error plus lambda per bit the context would spend.
                let nearer = q - q.signum();
                let cost =
                    |q: i32| (r - f64::from(q)).powi(2) + self.lambda * self.coders.cost(s, q);
                if cost(nearer) < cost(q) { nearer } else { q }
            } else {
                q
            }
        } else {
            0
        };
        self.coders.put(&mut self.encoder, s, q);
        (s.prediction + f64::from(q) * s.step, q)
    }

    fn weights(&mut self, fitted: Option<[i32; FEATURES]>) -> [i32; FEATURES] {
        let w = fitted.unwrap_or([0; FEATURES]);
        for v in w {
            self.coders.weights.put(&mut self.encoder, v);
        }
        w
    }
}

/// The decoder's side.
pub struct Reader<'a> {
    /// The stream.
    pub decoder: Decoder<'a>,
    /// Contexts.
    pub coders: Coders,
}

impl Details for Reader<'_> {
    fn sample(&mut self, s: &Sample) -> (f64, i32) {
        let q = self.coders.get(&mut self.decoder, s);
        (s.prediction + f64::from(q) * s.step, q)
    }

    fn weights(&mut self, _fitted: Option<[i32; FEATURES]>) -> [i32; FEATURES] {
        let mut w = [0; FEATURES];
        for v in &mut w {
            *v = self
                .coders
                .weights
                .get(&mut self.decoder)
                .clamp(-WEIGHT_LIMIT, WEIGHT_LIMIT);
        }
        w
    }
}
