//! What a curve stream needs to be read ([`CurveHeader`]: the scheme and every ring's shape)
//! and its compact form (`compact`).

use super::distance::Metric;
use super::model::{Scheme, SeamCrossing};
use crate::core::format::FormatError;

/// What the stream needs to be read: the scheme and the shape of every ring. Stored in the
/// compact form of [`compact`], right before the stream (12 bytes for one ring, against 75 as
/// plain fixed-width fields with every level's bound, 2.4% of a 2,500-point coastline's bytes).
#[derive(Clone, Debug, PartialEq)]
pub struct CurveHeader {
    /// The scheme (subdivision and detail matrices); the default one is stored as one byte.
    pub scheme: Scheme,
    /// How the tolerance is measured.
    pub metric: Metric,
    /// Largest error of a point (0: lossless), an `f32` value (the encoder rounds the
    /// requested tolerance down to one).
    pub tolerance: f64,
    /// The rings, in input order.
    pub rings: Vec<RingHeader>,
    /// A bound on the Hausdorff distance between the finest level and the source, as stored
    /// (rounded up by [`compact::bound_up`]: still a bound). The coarser levels' bounds follow
    /// from it and the decoded rings ([`crate::codecs::curve::code::level_bounds`]), so they are not stored.
    pub finest_bound: f64,
}

/// The header's bytes. Hand-written rather than bincode's variable-length integers, which
/// would change every codec's format (they share `fractile_proto`'s fixed-width config), and
/// self-delimiting, so that the stream follows with no length field (the asset's payload length
/// ends it): LEB128 counts, one byte for the scheme when it is the default, the tolerance as
/// `f32`, and the finest level's bound as a 16-bit code `k` of `tolerance · 2^(k/256)` (0.27%
/// steps, rounded up; `u16::MAX`: no bound), or as `f32` rounded up when the tolerance is 0.
pub(crate) mod compact {
    use super::{CurveHeader, FormatError, Metric, RingHeader, Scheme, SeamCrossing};

    fn varint(out: &mut Vec<u8>, mut v: u64) {
        loop {
            let byte = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                out.push(byte);
                return;
            }
            out.push(byte | 0x80);
        }
    }

    /// The largest `f32` value at or under `t` (a tolerance as stored: never looser than asked).
    pub(crate) fn tolerance_down(t: f64) -> f64 {
        let f = t as f32;
        f64::from(if f64::from(f) > t { f.next_down() } else { f })
    }

    /// The smallest stored bound at or above `b` for tolerance `tol`.
    pub(crate) fn bound_up(tol: f64, b: f64) -> f64 {
        decode_bound(tol, encode_bound(tol, b))
    }

    fn encode_bound(tol: f64, b: f64) -> u32 {
        if tol == 0.0 {
            let f = b as f32;
            let f = if f64::from(f) < b { f.next_up() } else { f };
            return f.to_bits();
        }
        if b.is_nan() || b <= tol {
            return 0; // bounds are never under the tolerance
        }
        let mut k = ((b / tol).log2() * 256.0).ceil().max(0.0);
        if k >= f64::from(u16::MAX) {
            return u32::from(u16::MAX);
        }
        while decode_bound(tol, k as u32) < b {
            k += 1.0;
        }
        (k as u32).min(u32::from(u16::MAX))
    }

    fn decode_bound(tol: f64, k: u32) -> f64 {
        if tol == 0.0 {
            return f64::from(f32::from_bits(k));
        }
        if k >= u32::from(u16::MAX) {
            return f64::INFINITY;
        }
        tol * (f64::from(k) / 256.0).exp2()
    }

    /// The header's bytes (the tolerance must be an `f32` value, as [`tolerance_down`] makes it).
    pub(crate) fn write(h: &CurveHeader) -> Vec<u8> {
        let mut out = Vec::with_capacity(16 + 4 * h.rings.len());
        if h.scheme == Scheme::default() {
            out.push(0);
        } else {
            out.push(1);
            for w in h.scheme.t.iter().flatten() {
                out.extend_from_slice(&w.to_le_bytes());
            }
            for w in h.scheme.u.iter().flatten().flatten() {
                out.extend_from_slice(&w.to_le_bytes());
            }
        }
        out.push(match h.metric {
            Metric::Plane => 0,
            Metric::Sphere => 1,
        });
        out.extend_from_slice(&(h.tolerance as f32).to_le_bytes());
        varint(&mut out, h.rings.len() as u64);
        for r in &h.rings {
            // Bit 7: a seam follows; bit 6: a start (levels take at most 5 bits above the
            // closed bit).
            let seam = u8::from(!r.seam.is_empty()) << 7;
            let start = u8::from(r.start.is_some()) << 6;
            out.push(seam | start | (r.levels << 1) | u8::from(r.closed));
            varint(&mut out, u64::from(r.pieces));
            varint(&mut out, u64::from(r.inserted));
            if let Some(s) = r.start {
                varint(&mut out, u64::from(s));
            }
            if !r.seam.is_empty() {
                varint(&mut out, r.seam.len() as u64);
                let mut at = 0;
                for c in &r.seam {
                    // The gap to the previous crossing, with two bits for the turn: +1, -1
                    // (one step between vertices within 180° of each other never turns more),
                    // or another (a zigzag varint follows).
                    let gap = u64::from(c.at - at) << 2;
                    at = c.at;
                    match c.turns {
                        1 => varint(&mut out, gap),
                        -1 => varint(&mut out, gap | 1),
                        t => {
                            varint(&mut out, gap | 2);
                            varint(&mut out, ((t << 1) ^ (t >> 31)) as u32 as u64);
                        }
                    }
                }
            }
        }
        let k = encode_bound(h.tolerance, h.finest_bound);
        if h.tolerance == 0.0 {
            out.extend_from_slice(&k.to_le_bytes());
        } else {
            out.extend_from_slice(&(k as u16).to_le_bytes());
        }
        out
    }

    struct Reader<'a>(&'a [u8]);

    impl Reader<'_> {
        fn bytes<const N: usize>(&mut self) -> Result<[u8; N], FormatError> {
            if self.0.len() < N {
                return Err(FormatError::stream("the curve header is truncated"));
            }
            let (head, rest) = self.0.split_at(N);
            self.0 = rest;
            Ok(head.try_into().expect("N bytes"))
        }

        fn f64(&mut self) -> Result<f64, FormatError> {
            Ok(f64::from_le_bytes(self.bytes()?))
        }

        fn varint(&mut self) -> Result<u64, FormatError> {
            let mut v = 0u64;
            for shift in (0..64).step_by(7) {
                let [byte] = self.bytes()?;
                v |= u64::from(byte & 0x7f) << shift;
                if byte & 0x80 == 0 {
                    return Ok(v);
                }
            }
            Err(FormatError::stream(
                "a count in the curve header is too long",
            ))
        }

        /// A count that cannot exceed the bytes left (each entry takes at least one).
        fn count(&mut self) -> Result<usize, FormatError> {
            let n = self.varint()?;
            if n > self.0.len() as u64 {
                return Err(FormatError::stream(format!(
                    "the curve header claims {n} entries"
                )));
            }
            Ok(n as usize)
        }
    }

    /// Reads a header from the front of `bytes` (refusing a truncated one;
    /// [`CurveHeader::validate`] checks the rest); returns it and the bytes after it.
    pub(crate) fn read(bytes: &[u8]) -> Result<(CurveHeader, &[u8]), FormatError> {
        let mut r = Reader(bytes);
        let scheme = match r.bytes::<1>()? {
            [0] => Scheme::default(),
            [1] => {
                let mut s = Scheme::default();
                for w in s.t.iter_mut().flatten() {
                    *w = r.f64()?;
                }
                for w in s.u.iter_mut().flatten().flatten() {
                    *w = r.f64()?;
                }
                s
            }
            [b] => return Err(FormatError::stream(format!("unknown scheme tag {b}"))),
        };
        let metric = match r.bytes::<1>()? {
            [0] => Metric::Plane,
            [1] => Metric::Sphere,
            [b] => return Err(FormatError::stream(format!("unknown metric {b}"))),
        };
        let tolerance = f64::from(f32::from_le_bytes(r.bytes()?));
        let n = r.count()?;
        let mut rings = Vec::with_capacity(n);
        for _ in 0..n {
            let [flags] = r.bytes()?;
            let pieces =
                u32::try_from(r.varint()?).map_err(|_| FormatError::stream("too many pieces"))?;
            let inserted = u32::try_from(r.varint()?)
                .map_err(|_| FormatError::stream("too many inserted points"))?;
            let start = if flags & 0x40 != 0 {
                Some(
                    u32::try_from(r.varint()?)
                        .map_err(|_| FormatError::stream("a start index is too large"))?,
                )
            } else {
                None
            };
            let mut seam = Vec::new();
            if flags & 0x80 != 0 {
                let n = r.count()?;
                let mut at = 0u64;
                for _ in 0..n {
                    let v = r.varint()?;
                    at += v >> 2;
                    let turns = match v & 3 {
                        0 => 1,
                        1 => -1,
                        2 => {
                            let z = u32::try_from(r.varint()?)
                                .map_err(|_| FormatError::stream("a seam turn is too large"))?;
                            ((z >> 1) as i32) ^ -((z & 1) as i32)
                        }
                        _ => return Err(FormatError::stream("unknown seam turn code")),
                    };
                    seam.push(SeamCrossing {
                        at: u32::try_from(at)
                            .map_err(|_| FormatError::stream("a seam index is too large"))?,
                        turns,
                    });
                }
            }
            rings.push(RingHeader {
                closed: flags & 1 == 1,
                pieces,
                levels: (flags >> 1) & 0x1f,
                inserted,
                seam,
                start,
            });
        }
        let k = if tolerance == 0.0 {
            u32::from_le_bytes(r.bytes()?)
        } else {
            u32::from(u16::from_le_bytes(r.bytes()?))
        };
        let header = CurveHeader {
            scheme,
            metric,
            tolerance,
            rings,
            finest_bound: decode_bound(tolerance, k),
        };
        Ok((header, r.0))
    }
}

/// The shape of one ring.
#[derive(Clone, Debug, PartialEq)]
pub struct RingHeader {
    /// Closed ring or open polyline.
    pub closed: bool,
    /// Base pieces `K`.
    pub pieces: u32,
    /// Detail levels `L` (at most 127: stored in 7 bits).
    pub levels: u8,
    /// Points inserted on input segments.
    pub inserted: u32,
    /// Where the ring crosses the antimeridian ([`SeamCrossing`]; empty for most rings).
    pub seam: Vec<SeamCrossing>,
    /// The input vertex the coded ring starts at ([`crate::codecs::curve::Ring::start`]).
    pub start: Option<u32>,
}

/// Most points a curve asset may decode to at its finest level (a tiny hostile header must not
/// make a reader allocate gigabytes).
pub(crate) const MAX_POINTS: u64 = 1 << 26;

impl CurveHeader {
    /// Refuses inconsistent or oversized headers.
    pub fn validate(&self) -> Result<(), FormatError> {
        self.scheme.validate()?;
        if !(self.tolerance.is_finite() && self.tolerance >= 0.0) {
            return Err(FormatError::header(format!(
                "tolerance {} is not a distance",
                self.tolerance
            )));
        }
        let mut total = 0u64;
        for (i, r) in self.rings.iter().enumerate() {
            if r.pieces == 0 || r.levels as usize > super::prepare::MAX_LEVELS {
                return Err(FormatError::header(format!(
                    "ring {i}: {} pieces, {} levels",
                    r.pieces, r.levels
                )));
            }
            let n = (r.pieces as u64) << (r.levels as u32 + 1);
            if r.inserted as u64 >= n {
                return Err(FormatError::header(format!(
                    "ring {i}: more inserted points than points"
                )));
            }
            let fine_len = n + u64::from(!r.closed);
            if r.seam.windows(2).any(|w| w[0].at >= w[1].at)
                || r.seam
                    .iter()
                    .any(|c| c.at as u64 >= fine_len || c.turns == 0 || c.turns.abs() > 1 << 20)
            {
                return Err(FormatError::header(format!(
                    "ring {i}: bad antimeridian crossings"
                )));
            }
            if r.start.is_some_and(|s| s as u64 >= fine_len) {
                return Err(FormatError::header(format!(
                    "ring {i}: start vertex past its points"
                )));
            }
            total = total.saturating_add(n);
        }
        if total > MAX_POINTS {
            return Err(FormatError::header(format!(
                "{total} points is more than this build reads ({MAX_POINTS})"
            )));
        }
        if self.finest_bound.is_nan() || self.finest_bound < 0.0 {
            return Err(FormatError::header(format!(
                "bad error bound {}",
                self.finest_bound
            )));
        }
        Ok(())
    }
}
