//! Adaptive binary range coding of the transform stream.
//!
//! Hand-written because no maintained crate offers what this needs in a few lines: adaptive
//! *binary* contexts (one probability per quadtree level, per bit position of a parameter),
//! as in LZMA and CABAC. (`constriction` codes with static categorical models; adaptive
//! contexts would have to be rebuilt per symbol.) The coder is the LZMA range coder: 32-bit
//! range, 11-bit probabilities, carry propagation through a cache byte.
//!
//! Decoding never panics: reading past the end yields zero bytes, and [`Decoder::overrun`]
//! tells the caller that the stream was too short (a truncated or corrupt asset).

const PROB_BITS: u32 = 11;
const PROB_ONE: u16 = 1 << PROB_BITS;
const ADAPT_SHIFT: u32 = 5;
const TOP: u32 = 1 << 24;

/// An adaptive binary context: where the coder splits its range for the next bit, and how
/// it learns from the bit. Two kinds exist because asset streams are frozen by their format:
/// [`Bit`] (every codec's contexts) and [`CountedBit`] (curves, which have few symbols per
/// context and so pay mostly for learning).
pub trait Model: Clone {
    /// The part of `range` given to a 0 bit (strictly between 0 and `range`).
    fn bound(&self, range: u32) -> u32;
    /// Learns from a coded bit.
    fn update(&mut self, bit: bool);
    /// What coding `bit` would cost now, in bits (for encoders that choose between symbols
    /// by their rate).
    fn cost(&self, bit: bool) -> f64;
}

/// The probability that the next bit is 0, adapted after every bit by a fixed 1/32 of the way
/// (LZMA's context).
#[derive(Clone, Copy, Debug)]
pub struct Bit(u16);

impl Default for Bit {
    fn default() -> Self {
        Bit(PROB_ONE / 2)
    }
}

impl Model for Bit {
    #[inline]
    fn bound(&self, range: u32) -> u32 {
        (range >> PROB_BITS) * self.0 as u32
    }

    #[inline]
    fn update(&mut self, bit: bool) {
        if bit {
            self.0 -= self.0 >> ADAPT_SHIFT;
        } else {
            self.0 += (PROB_ONE - self.0) >> ADAPT_SHIFT;
        }
    }

    fn cost(&self, bit: bool) -> f64 {
        let p0 = f64::from(self.0) / f64::from(PROB_ONE);
        -(if bit { 1.0 - p0 } else { p0 }).log2()
    }
}

impl Bit {
    /// What coding `bit` would cost now, in bits.
    pub fn cost(&self, bit: bool) -> f64 {
        Model::cost(self, bit)
    }
}

/// A context that learns fast while it is young: its `n`-th bit moves the probability by
/// 1/2^(1 + log2(n + 1)) of the way (about 1/(n + 1), the running frequency), down to a floor of
/// 1/32, with 15-bit probabilities. A fixed 1/32 pays about 6 bits per context before it has
/// learnt anything; on the 40 Natural Earth coastlines, whose curve contexts see a few hundred
/// symbols each, this codes the five longest rings 1.5-9% smaller (the shorter, the more).
#[derive(Clone, Copy, Debug)]
pub(crate) struct CountedBit {
    p0: u16,
    seen: u8,
}

const COUNTED_BITS: u32 = 15;
const COUNTED_ONE: u16 = 1 << COUNTED_BITS;
/// The floor of the learning rate, 1/2^5 (1/2^6 coded the coastlines the same).
const COUNTED_SLOWEST: u32 = 5;

impl Default for CountedBit {
    fn default() -> Self {
        CountedBit {
            p0: COUNTED_ONE / 2,
            seen: 0,
        }
    }
}

impl Model for CountedBit {
    #[inline]
    fn bound(&self, range: u32) -> u32 {
        // p0 stays in 1..COUNTED_ONE (a step never reaches either end), so the bound is
        // strictly inside a range of at least 2^24.
        (range >> COUNTED_BITS) * self.p0 as u32
    }

    #[inline]
    fn update(&mut self, bit: bool) {
        let shift = (1 + (u32::from(self.seen) + 1).ilog2()).min(COUNTED_SLOWEST);
        self.seen = self.seen.saturating_add(1);
        if bit {
            self.p0 -= self.p0 >> shift;
        } else {
            self.p0 += (COUNTED_ONE - self.p0) >> shift;
        }
    }

    fn cost(&self, bit: bool) -> f64 {
        let p0 = f64::from(self.p0) / f64::from(COUNTED_ONE);
        -(if bit { 1.0 - p0 } else { p0 }).log2()
    }
}

/// Codes a value of `bits` bits, most significant first, each bit in the context of the bits
/// above it (a binary tree of contexts), so any distribution over `0..2^bits` is learnt.
#[derive(Clone, Debug)]
pub struct BitTree<M = Bit> {
    bits: u32,
    probs: Vec<M>,
}

impl<M: Model + Default> BitTree<M> {
    /// A tree for values in `0..2^bits`.
    pub fn new(bits: u32) -> Self {
        BitTree {
            bits,
            probs: vec![M::default(); 1 << bits],
        }
    }

    /// Number of bits of the values it codes.
    pub fn bits(&self) -> u32 {
        self.bits
    }

    /// What coding `value` would cost now, in bits.
    pub fn cost(&self, value: u32) -> f64 {
        let mut node = 1usize;
        let mut bits = 0.0;
        for i in (0..self.bits).rev() {
            let b = (value >> i) & 1 == 1;
            bits += self.probs[node].cost(b);
            node = (node << 1) | b as usize;
        }
        bits
    }
}

/// Writes bits into a byte vector.
pub struct Encoder {
    low: u64,
    range: u32,
    cache: u8,
    cache_size: u64,
    out: Vec<u8>,
}

impl Default for Encoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Encoder {
    /// An empty stream.
    pub fn new() -> Self {
        Encoder {
            low: 0,
            range: u32::MAX,
            cache: 0,
            cache_size: 1,
            out: Vec::new(),
        }
    }

    fn shift_low(&mut self) {
        if (self.low as u32) < 0xFF00_0000 || (self.low >> 32) != 0 {
            let carry = (self.low >> 32) as u8;
            let mut temp = self.cache;
            loop {
                self.out.push(temp.wrapping_add(carry));
                temp = 0xFF;
                self.cache_size -= 1;
                if self.cache_size == 0 {
                    break;
                }
            }
            self.cache = ((self.low >> 24) & 0xFF) as u8;
        }
        self.cache_size += 1;
        self.low = (self.low & 0x00FF_FFFF) << 8;
    }

    /// Codes one bit with an adaptive probability.
    pub fn bit<M: Model>(&mut self, p: &mut M, bit: bool) {
        let bound = p.bound(self.range);
        if !bit {
            self.range = bound;
        } else {
            self.low += bound as u64;
            self.range -= bound;
        }
        p.update(bit);
        while self.range < TOP {
            self.range <<= 8;
            self.shift_low();
        }
    }

    /// Codes `value` (< 2^bits) through a bit tree.
    pub fn tree<M: Model>(&mut self, tree: &mut BitTree<M>, value: u32) {
        debug_assert!(value < (1 << tree.bits));
        let mut node = 1usize;
        for i in (0..tree.bits).rev() {
            let b = (value >> i) & 1 == 1;
            self.bit(&mut tree.probs[node], b);
            node = (node << 1) | b as usize;
        }
    }

    /// Bytes written so far (a lower bound of the final size, for rate estimates).
    pub fn len(&self) -> usize {
        self.out.len() + self.cache_size as usize + 4
    }

    /// Whether nothing was coded yet.
    pub fn is_empty(&self) -> bool {
        self.out.is_empty()
    }

    /// Flushes and returns the stream.
    pub fn finish(mut self) -> Vec<u8> {
        for _ in 0..5 {
            self.shift_low();
        }
        self.out
    }
}

/// Reads bits written by [`Encoder`].
pub struct Decoder<'a> {
    data: &'a [u8],
    pos: usize,
    range: u32,
    code: u32,
    overrun: usize,
}

impl<'a> Decoder<'a> {
    /// Starts reading a stream.
    pub fn new(data: &'a [u8]) -> Self {
        let mut d = Decoder {
            data,
            pos: 0,
            range: u32::MAX,
            code: 0,
            overrun: 0,
        };
        for _ in 0..5 {
            d.code = (d.code << 8) | d.byte() as u32;
        }
        d
    }

    #[inline]
    fn byte(&mut self) -> u8 {
        match self.data.get(self.pos) {
            Some(&b) => {
                self.pos += 1;
                b
            }
            None => {
                self.overrun += 1;
                0
            }
        }
    }

    /// Decodes one bit (inlined: a call a decision was a tenth of a projected decode).
    #[inline(always)]
    pub fn bit<M: Model>(&mut self, p: &mut M) -> bool {
        let bound = p.bound(self.range);
        let bit = if self.code < bound {
            self.range = bound;
            false
        } else {
            self.code -= bound;
            self.range -= bound;
            true
        };
        p.update(bit);
        while self.range < TOP {
            self.range <<= 8;
            self.code = (self.code << 8) | self.byte() as u32;
        }
        bit
    }

    /// Decodes a value through a bit tree.
    pub fn tree<M: Model>(&mut self, tree: &mut BitTree<M>) -> u32 {
        let mut node = 1usize;
        for _ in 0..tree.bits {
            let b = self.bit(&mut tree.probs[node]);
            node = (node << 1) | b as usize;
        }
        (node - (1 << tree.bits)) as u32
    }

    /// Length of the stream being read, in bytes.
    pub fn stream_len(&self) -> usize {
        self.data.len()
    }

    /// Bytes read so far: all a decoder of the same symbols needs (a partial decode's prefix).
    pub fn consumed(&self) -> usize {
        self.pos
    }

    /// Whether the decoder read past the end of the stream (beyond the flush bytes).
    pub fn overrun(&self) -> bool {
        self.overrun > 4
    }
}

/// The fewest bits of stream that one binary decision through a [`Bit`] context can take: its
/// probability saturates at `(2^11 - 31) / 2^11` (the adaptation step rounds to zero there), so
/// the likelier symbol costs at least `log2(2048 / 2017)` = 0.0220 bits. Readers use it to refuse,
/// before allocating anything, a header that claims more symbols than its stream can hold.
pub(crate) const MIN_BITS_PER_DECISION: f64 = 0.0219;

/// The most binary decisions through [`Bit`] contexts that a stream of `bytes` bytes can hold
/// (with the coder's flush bytes and the reader's tolerated overrun).
pub(crate) fn most_decisions(bytes: usize) -> u64 {
    most_decisions_of(bytes, MIN_BITS_PER_DECISION)
}

/// [`most_decisions`] of decisions of at least `min_bits` bits each.
pub(crate) fn most_decisions_of(bytes: usize, min_bits: f64) -> u64 {
    (((bytes as f64 + 9.0) * 8.0) / min_bits).ceil() as u64
}

/// One direction of the coder. The stream walks ([`crate::codecs::quadtree::stream`], [`crate::codecs::ifs3d::octree`]) are one
/// function each that codes in either direction, so that encoder and decoder cannot drift apart.
pub(crate) enum Dir<'a, 'b> {
    /// Writing: the values given are coded and returned.
    Enc(&'a mut Encoder),
    /// Reading: the values given are ignored and the decoded ones returned.
    Dec(&'a mut Decoder<'b>),
}

impl Dir<'_, '_> {
    /// Whether a reader ran past the end of its stream ([`Decoder::overrun`]); never for a
    /// writer. Stream walks test it as they go, so that a short stream claiming a large frame
    /// stops within a few thousand symbols instead of decoding the whole claim from zeros.
    pub(crate) fn overrun(&self) -> bool {
        match self {
            Dir::Enc(_) => false,
            Dir::Dec(d) => d.overrun(),
        }
    }

    /// Codes one bit.
    pub(crate) fn bit<M: Model>(&mut self, p: &mut M, v: bool) -> bool {
        match self {
            Dir::Enc(e) => {
                e.bit(p, v);
                v
            }
            Dir::Dec(d) => d.bit(p),
        }
    }

    /// Codes a value through a bit tree.
    pub(crate) fn tree<M: Model>(&mut self, t: &mut BitTree<M>, v: u32) -> u32 {
        match self {
            Dir::Enc(e) => {
                e.tree(t, v);
                v
            }
            Dir::Dec(d) => d.tree(t),
        }
    }

    /// Codes a wide index (see [`WideIndex`]).
    pub(crate) fn wide(&mut self, w: &mut WideIndex, v: u32) -> u32 {
        let nlow = w.low.len() as u32;
        let mut out = self.tree(&mut w.high, v >> nlow) << nlow;
        for (i, bit) in w.low.iter_mut().enumerate() {
            let shift = nlow - 1 - i as u32;
            out |= u32::from(self.bit(bit, (v >> shift) & 1 == 1)) << shift;
        }
        out
    }
}

/// An index of up to 32 bits (a domain's): its high bits through a bit tree of at most
/// `tree_bits`, then one adaptive bit per remaining low bit. A full tree over 2^30 values would
/// need gigabytes of contexts; the high bits carry what is predictable.
pub(crate) struct WideIndex {
    high: BitTree,
    low: Vec<Bit>,
}

impl WideIndex {
    /// Models for values in `0..2^bits`.
    pub(crate) fn new(bits: u32, tree_bits: u32) -> Self {
        let high = bits.min(tree_bits);
        WideIndex {
            high: BitTree::new(high),
            low: vec![Bit::default(); (bits - high) as usize],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The cheapest stream there is (one context, always its likelier symbol) is still no
    /// denser than [`MIN_BITS_PER_DECISION`], so [`most_decisions`] never refuses a real stream;
    /// and a reader of an empty stream reports the overrun within a bounded number of symbols.
    #[test]
    fn decisions_cost_at_least_the_floor() {
        for n in [1usize, 1_000, 100_000, 1_000_000] {
            let mut enc = Encoder::new();
            let mut b = Bit::default();
            for _ in 0..n {
                enc.bit(&mut b, false);
            }
            let bytes = enc.finish();
            assert!(
                most_decisions(bytes.len()) >= n as u64,
                "{n} decisions in {} bytes",
                bytes.len()
            );
            // Saturated: about the floor, within 10% once learning is paid for.
            if n >= 100_000 {
                let per = bytes.len() as f64 * 8.0 / n as f64;
                assert!(per < MIN_BITS_PER_DECISION * 1.1, "{per} bits a decision");
            }
        }
        let mut dec = Decoder::new(&[]);
        let mut b = Bit::default();
        let read = (0..100_000).take_while(|_| {
            dec.bit(&mut b);
            !dec.overrun()
        });
        assert!(read.count() < most_decisions(0) as usize);
    }

    proptest! {
        #[test]
        fn bits_and_trees_round_trip(values in proptest::collection::vec((0u32..1000, any::<bool>()), 0..2000)) {
            // Both kinds of context, interleaved on one stream.
            let mut enc = Encoder::new();
            let (mut t, mut b) = (BitTree::<Bit>::new(10), Bit::default());
            let (mut ct, mut cb) = (BitTree::<CountedBit>::new(10), CountedBit::default());
            for &(v, bit) in &values {
                enc.tree(&mut t, v);
                enc.bit(&mut b, bit);
                enc.tree(&mut ct, v);
                enc.bit(&mut cb, bit);
            }
            let bytes = enc.finish();
            let mut dec = Decoder::new(&bytes);
            let (mut t, mut b) = (BitTree::<Bit>::new(10), Bit::default());
            let (mut ct, mut cb) = (BitTree::<CountedBit>::new(10), CountedBit::default());
            for &(v, bit) in &values {
                prop_assert_eq!(dec.tree(&mut t), v);
                prop_assert_eq!(dec.bit(&mut b), bit);
                prop_assert_eq!(dec.tree(&mut ct), v);
                prop_assert_eq!(dec.bit(&mut cb), bit);
            }
            prop_assert!(!dec.overrun());
        }
    }

    #[test]
    fn skewed_source_codes_below_its_raw_size() {
        // 10,000 bits with P(1) = 1/20: entropy is 0.286 bit/bit, i.e. about 358 bytes.
        let mut enc = Encoder::new();
        let mut p = Bit::default();
        let mut state = 12345u32;
        for _ in 0..10_000 {
            state = state.wrapping_mul(1_103_515_245).wrapping_add(12345);
            enc.bit(&mut p, (state >> 16).is_multiple_of(20));
        }
        let n = enc.finish().len();
        assert!(n < 450, "{n} bytes for a 0.286-bit/bit source");
    }

    /// Codes `contexts` fresh contexts of `per` skewed bits each; returns the stream's bytes.
    fn young_contexts<M: Model + Default>(contexts: usize, per: usize) -> usize {
        let mut enc = Encoder::new();
        let mut state = 777u32;
        for _ in 0..contexts {
            let mut p = M::default();
            for _ in 0..per {
                state = state.wrapping_mul(1_103_515_245).wrapping_add(12345);
                enc.bit(&mut p, (state >> 16).is_multiple_of(20));
            }
        }
        enc.finish().len()
    }

    #[test]
    fn counted_contexts_learn_faster_and_end_as_good() {
        // 100 contexts of 30 bits, P(1) = 1/20 (what a curve's rarely used contexts see): a
        // fixed 1/32 step is still paying for its start; the counted one has learnt.
        let (fixed, counted) = (
            young_contexts::<Bit>(100, 30),
            young_contexts::<CountedBit>(100, 30),
        );
        assert!(
            (counted as f64) < 0.8 * fixed as f64,
            "counted {counted} B, fixed {fixed} B"
        );
        // One long-lived context: both near the entropy (358 bytes for 10,000 bits).
        let (fixed, counted) = (
            young_contexts::<Bit>(1, 10_000),
            young_contexts::<CountedBit>(1, 10_000),
        );
        assert!(
            counted < 450 && fixed < 450,
            "counted {counted} B, fixed {fixed} B"
        );
    }
}

/// A context that mixes a fast and a slow estimate (probabilities moved 1/16 and 1/128 of the
/// way a bit, at the running frequency while young), on 15 bits kept 2^-10 from either end: a
/// [`Bit`] costs at least 0.022 bits a symbol, half a file at high ratios; one rate on 15 bits
/// lost on fast-changing data (the projected pyramid's details, format 9; docs/asset-format.md).
#[derive(Clone, Copy, Debug)]
pub(crate) struct TwoRateBit {
    fast: u16,
    slow: u16,
    seen: u8,
}

const TWO_RATE_SHIFTS: (u32, u32) = (4, 7); // 4/8 within 0.2%; 5/7 +1.6% on topobathy
/// How near a probability may come to 0 or 1, in 2^-15 (2^-10: a symbol costs at most 10 bits).
const TWO_RATE_EDGE: u32 = 32;
/// The fewest bits one decision through a [`TwoRateBit`] takes: `-log2(1 - 2^-10)`.
pub(crate) const MIN_BITS_PER_TWO_RATE_DECISION: f64 = 0.00140;

impl Default for TwoRateBit {
    fn default() -> Self {
        TwoRateBit {
            fast: 1 << 15,
            slow: 1 << 15,
            seen: 0,
        }
    }
}

impl TwoRateBit {
    /// The probability of a 0, in 2^-15: in [2^5, 2^15 - 2^5], so that the bound is strictly
    /// inside a range of at least 2^24.
    #[inline]
    fn p0(&self) -> u32 {
        ((u32::from(self.fast) + u32::from(self.slow)) >> 2)
            .clamp(TWO_RATE_EDGE, COUNTED_ONE as u32 - TWO_RATE_EDGE)
    }
}

impl Model for TwoRateBit {
    #[inline]
    fn bound(&self, range: u32) -> u32 {
        (range >> COUNTED_BITS) * self.p0()
    }

    #[inline]
    fn update(&mut self, bit: bool) {
        let young = 1 + (u32::from(self.seen) + 1).ilog2();
        self.seen = self.seen.saturating_add(1);
        let adapt = |p: &mut u16, shift: u32| {
            let v = u32::from(*p);
            *p = if bit {
                v - (v >> shift)
            } else {
                v + ((u32::from(u16::MAX) - v) >> shift)
            } as u16;
        };
        adapt(&mut self.fast, young.min(TWO_RATE_SHIFTS.0));
        adapt(&mut self.slow, young.min(TWO_RATE_SHIFTS.1));
    }

    fn cost(&self, bit: bool) -> f64 {
        let p0 = f64::from(self.p0()) / f64::from(COUNTED_ONE);
        -(if bit { 1.0 - p0 } else { p0 }).log2()
    }
}
