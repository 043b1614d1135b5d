//! The projected IFS with details on height fields (`projected`): the model of seed 001 (Guérin,
//! Tosan et al.) on a grid. A coarse grid of control points, subdivision masks fitted to the
//! data level by level (the fractal part), and details at every level (the wavelet part), coded
//! the way near-lossless image coders code residuals ([`pyramid`]).
//!
//! Two modes:
//! - **max error** (`--max-error E`): every decoded sample is within E of its source (in source
//!   units), because each detail is quantised in closed loop with a step of 2E (an odd multiple
//!   of the quantum for integer data). The measured ratio is reported beside LERC and JPEG-LS
//!   near-lossless, which make the same promise.
//! - **rate** (`--target-bpp`): the step is found by bisection, and the levels are lifted
//!   ([`lifting`]): each coarse grid holds local means, not samples, which is what approximates
//!   the surface best at a given rate (the pyramid is coded too, and kept where it codes
//!   better: at high rates on images with large flat areas).
//!
//! Past the finest level the surface is continued by a partitioned affine operator of the
//! form every decoder of fractile evaluates ([`ProjectedOperator`]): in each cell between four
//! decoded samples, `f = B1 + rho (f o phi - B2 o phi)`, where B1 interpolates the samples
//! bilinearly, phi maps the cell onto the even-aligned 2 x 2 block of cells that holds it (scale
//! 2), and B2 interpolates the block's corners. At the samples themselves phi lands on samples
//! of the even lattice, where `f - B2` is zero, so the surface passes through every decoded
//! sample; between them it carries the details of the next coarser octave scaled by rho, and
//! so on down every octave: the roughness of the source continues self-similarly. rho is
//! fitted per asset as the ratio of the finest two octaves' detail amplitudes.

mod bands;
pub(crate) mod bound;
#[doc(hidden)] // public as the pyramid is (its walk's two sides), not API
pub mod details;
pub(crate) mod encode;
pub(crate) mod grid;
mod header;
#[doc(hidden)] // public for the crate's own integration tests and benches, not API
pub mod kernel;
#[doc(hidden)] // public for the crate's own integration tests and benches, not API
pub mod lifting;
mod neighbourhood;
mod operator;
pub(crate) mod plane;
mod predict;
#[doc(hidden)] // public for the crate's own integration tests and benches, not API
pub mod pyramid;
pub(crate) mod records;
mod residual;
pub(crate) mod subdivision;

use fractile_proto::AssetKind;

use crate::Error;
use crate::codecs::options::{Named, Options};
use crate::core::entropy::{Decoder, Encoder};
use crate::core::format::FormatError;

pub(crate) use bound::{deliver_plane, finest_bound};
pub use header::{CODEC_NAME, ProjectedHeader};
pub use operator::ProjectedOperator;
pub use pyramid::levels_for;

/// Codes a grid (source units, invalid cells filled) under `header` with a dead zone (the
/// pyramid's) and a rate-distortion weight (rate mode only); returns the stream and the decoded
/// samples.
pub fn encode_grid(
    header: &ProjectedHeader,
    source: &[f64],
    valid: Option<&[bool]>,
    (dead_zone, lambda): (f64, f64),
) -> (Vec<u8>, Vec<f64>) {
    // A promise per sample leaves no room for rate-distortion choices.
    let lambda = if header.max_error == 0.0 && header.quantum == 0.0 {
        lambda
    } else {
        0.0
    };
    let layout = header.layout();
    if let Some(kernel) = layout.order.lifting() {
        return lifting::encode(&lifted_plane(&layout, kernel), source, lambda);
    }
    let mut g = vec![0.0; header.cells()];
    let mut q = details::Quantiser {
        source,
        valid,
        dead_zone,
        lambda,
        encoder: Encoder::new(),
        coders: details::Coders::new(layout.order),
    };
    let target = |i: usize| valid.is_none_or(|v| v[i]).then(|| source[i]);
    pyramid::walk(&layout, &mut g, &mut q, Some(&target));
    (q.encoder.finish(), g)
}

/// A lifted plane's parameters from its layout (its dead zone and step growth are the pyramid's
/// alone: band steps follow from the synthesis gains).
fn lifted_plane(layout: &pyramid::Layout, kernel: kernel::Kernel) -> lifting::Plane {
    lifting::Plane {
        size: layout.size,
        levels: layout.levels,
        step: layout.step,
        kernel,
        ends: kernel::Ends::Mirror,
        code: layout.order.code(),
    }
}

/// Decodes a plane's samples (source units).
pub fn decode_grid(header: &ProjectedHeader, stream: &[u8]) -> Result<Vec<f64>, FormatError> {
    header.validate()?;
    // Every sample costs at least one decision: refuse a header that claims more than the stream
    // can hold before allocating for it.
    let most =
        crate::core::entropy::most_decisions_of(stream.len(), header.order.min_bits_per_sample());
    if header.cells() as u64 > most {
        return Err(FormatError::stream(format!(
            "a projected stream of {} bytes cannot hold {} samples",
            stream.len(),
            header.cells()
        )));
    }
    let layout = header.layout();
    let mut decoder = Decoder::new(stream);
    let g = if let Some(kernel) = layout.order.lifting() {
        lifting::decode(&lifted_plane(&layout, kernel), &mut decoder)
    } else {
        let mut g = vec![0.0; header.cells()];
        let mut r = details::Reader {
            decoder,
            coders: details::Coders::new(layout.order),
        };
        pyramid::walk(&layout, &mut g, &mut r, None);
        decoder = r.decoder;
        g
    };
    if decoder.overrun() || !all_finite(&g) {
        return Err(FormatError::stream("projected stream truncated or corrupt"));
    }
    Ok(g)
}

/// Whether every value is finite: a test of eight at a time without an early way out, which the
/// compiler vectorises (a pass over a decoded grid: 2% of a whole read as `any`).
fn all_finite(g: &[f64]) -> bool {
    g.chunks(8)
        .all(|c| c.iter().fold(true, |ok, v| ok & v.is_finite()))
}

/// The coarse view at `depth` of a coded plane: its multiresolution's samples on multiples of
/// `2^depth`, decoded from the coarse part of its stream alone, in source units, with the
/// header of a plane of that grid (no promise: see below). What a chunked file's derived levels
/// are (`io::chunked`, format 7): the overview of `2^depth` cells a side that no longer needs
/// coding beside the source.
///
/// A lifted plane's coarse samples are the analysis low-pass at that depth (local means of
/// about `2^depth` cells, divided here by the kernel's gain); the pyramid's are decoded samples
/// of the source's own lattice (closed loop, so each within the plane's promise of its source
/// cell). Either stands for the cells around it, not for one cell, so the view's header makes
/// no per-sample promise: its error is measured against the source's box means at encode time.
///
/// Also returns the bytes of the stream it read: the prefix a reader of that depth needs
/// (bands are coded coarsest first).
pub fn decode_coarse(
    header: &ProjectedHeader,
    stream: &[u8],
    depth: u32,
) -> Result<(ProjectedHeader, Vec<f64>, usize), FormatError> {
    header.validate()?;
    if depth == 0 || depth > 12 {
        return Err(FormatError::stream(format!(
            "no coarse view at depth {depth}"
        )));
    }
    // A plane of fewer levels (a thin chunk) is read whole below its coarsest level, and its
    // samples on multiples of 2^depth taken.
    let read = depth.min(u32::from(header.levels));
    let most =
        crate::core::entropy::most_decisions_of(stream.len(), header.order.min_bits_per_sample());
    if (header.cells() >> (2 * depth.min(u32::from(header.levels)))) as u64 > most {
        return Err(FormatError::stream(
            "projected stream too short for its grid",
        ));
    }
    let layout = header.layout();
    let mut decoder = Decoder::new(stream);
    let (g, gain) = if let Some(kernel) = layout.order.lifting() {
        let plane = lifted_plane(&layout, kernel);
        let g = lifting::decode_to(&plane, &mut decoder, read);
        (g, kernel::dc_gain(kernel).powi(2 * read as i32))
    } else {
        let mut g = vec![0.0; header.cells()];
        let mut r = details::Reader {
            decoder,
            coders: details::Coders::new(layout.order),
        };
        pyramid::walk_to(&layout, &mut g, &mut r, None, read);
        decoder = r.decoder;
        (g, 1.0)
    };
    let [w, h] = layout.size;
    let s = 1usize << depth;
    let (cw, ch) = (w.div_ceil(s), h.div_ceil(s));
    let mut coarse = Vec::with_capacity(cw * ch);
    for y in (0..h).step_by(s) {
        coarse.extend((0..w).step_by(s).map(|x| g[y * w + x] / gain));
    }
    if decoder.overrun() || coarse.iter().any(|v| !v.is_finite()) {
        return Err(FormatError::stream("projected stream truncated or corrupt"));
    }
    // A pyramid's coarse samples are source cells within its bound, on its quantum: the view
    // keeps both (its promise on its own samples); a lifted band promises nothing.
    let pyramid = layout.order.lifting().is_none();
    let view = ProjectedHeader {
        samples: [cw as u32, ch as u32],
        levels: header.levels - read as u8,
        max_error: if pyramid { header.max_error } else { 0.0 },
        quantum: if pyramid { header.quantum } else { 0.0 },
        ..header.clone()
    };
    view.validate()?;
    Ok((view, coarse, decoder.consumed()))
}

/// The roughness of the continuation: how much the details of one octave shrink into the next
/// finer one, measured on the decoded grid as the ratio of the RMS residuals of cubic
/// (Catmull-Rom) midpoint prediction at spacings 1 and 2 (`2^-H` for a surface of Hurst
/// exponent H; the smooth part of the surface, which shrinks by 1/4 an octave, is what the
/// cubic predicts and so leaves out), within [0, 0.9].
pub fn fit_roughness(g: &[f64], w: usize, h: usize) -> f32 {
    let rms = |k: usize| {
        let (mut sum, mut n) = (0.0, 0usize);
        let mid = |a: f64, b: f64, c: f64, d: f64| (9.0 * (b + c) - a - d) / 16.0;
        for y in 0..h {
            for x in (3 * k..w.saturating_sub(3 * k)).step_by(2 * k) {
                let i = y * w + x;
                let d = g[i] - mid(g[i - 3 * k], g[i - k], g[i + k], g[i + 3 * k]);
                sum += d * d;
                n += 1;
            }
        }
        for y in (3 * k..h.saturating_sub(3 * k)).step_by(2 * k) {
            for x in 0..w {
                let i = y * w + x;
                let r = |o: usize| g[i - o * w];
                let s = |o: usize| g[i + o * w];
                let d = g[i] - mid(r(3 * k), r(k), s(k), s(3 * k));
                sum += d * d;
                n += 1;
            }
        }
        (sum / n.max(1) as f64).sqrt()
    };
    let (fine, coarse) = (rms(1), rms(2));
    // A surface the cubic predicts to rounding (a plane, a cubic) has no roughness to continue.
    let scale = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if coarse > 1e-9 * scale {
        (fine / coarse).clamp(0.0, 0.9) as f32
    } else {
        0.0
    }
}

/// Settings of the projected encoder.
#[derive(Clone, Debug, PartialEq)]
pub struct ProjectedSettings {
    /// The bound on |decoded - source| at every valid sample, source units (max-error mode).
    pub max_error: Option<f64>,
    /// Rate mode with the interpolating pyramid's closed loop alone, not also the lifted
    /// levels (to measure one against the other: 0.6-1.2 dB worse at 40:1 and 80:1 on DEMs).
    pub pyramid: bool,
    /// Step growth per coarser level in rate mode, with the pyramid.
    pub growth: f64,
    /// Dead zone in rate mode with the pyramid, as a fraction of a step.
    pub dead_zone: f64,
    /// Rate mode: the weight of a bit against squared error in steps^2 when a detail may move
    /// one step towards zero.
    pub lambda: f64,
    /// Under a target rate: the smallest max error whose file fits, every cell within it (the
    /// max-error quantiser, no dead zone), instead of the best PSNR. Costs 1.8 dB at 0.8 bpp
    /// on etopo20 and jacksboro, and gives a bound that holds at every cell.
    pub bounded: bool,
    /// Rate mode at this step and design, no rate control of its own: the chunks of a file
    /// whose rate is the file's ([`crate::encode::rate`]) share one step found for them all.
    pub at_step: Option<AtStep>,
    /// A trial coding whose file is not kept (a rate search's): no source-error map is
    /// measured (the map took most of an encode), the file has none.
    pub trial: bool,
    /// A size: the file at most this many bits a source cell (with `bounded`, or alone:
    /// the best PSNR that fits); `None` with `max_error`.
    pub target_bpp: Option<f64>,
}

/// A step (source units) and the multiresolution that codes at it: a lifted kernel
/// ([`pyramid::Order::LiftedTwoRate`], [`pyramid::Order::Lifted97TwoRate`]; format 9's
/// [`pyramid::Order::Lifted`], [`pyramid::Order::Lifted97`] are still read) or `None`, the pyramid (its order chosen).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AtStep {
    /// The quantiser's step, source units.
    pub step: f64,
    /// The multiresolution.
    pub design: Option<pyramid::Order>,
}

/// The quality every chunk of a file is coded at (`encode::rate`: a file's rate is the
/// file's).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Quality {
    /// Rate mode: a step and a multiresolution.
    Step(AtStep),
    /// Bounded: every valid cell within this of its source (source units).
    Bound(f64),
}

impl Quality {
    /// The quality of the chunks of overview level `l` (cells of 2^l source cells): the step
    /// or bound times 2^l. A coarse cell is 2^l cells wide and is seen at a 2^l times coarser
    /// zoom, so its error may be 2^l times larger, as a terrain level of detail's geometric
    /// error doubles a level (Cesium's, and the error a coarse tile's mesh is simplified to).
    /// At the source's step the overviews took a third of the file (docs/benchmarks.md).
    pub fn at_level(self, l: usize) -> Quality {
        let scale = f64::from(1u32 << l.min(30));
        match self {
            Quality::Step(s) => Quality::Step(AtStep {
                step: s.step * scale,
                design: s.design,
            }),
            Quality::Bound(e) => Quality::Bound(e * scale),
        }
    }

    /// How the encoder's settings name it (what split encodes must agree on).
    pub fn describe(&self) -> String {
        match self {
            Quality::Step(s) => format!("step {} {:?}", s.step, s.design),
            Quality::Bound(e) => format!("max error {e}"),
        }
    }
}

impl ProjectedSettings {
    /// The settings of one chunk of a file whose rate is the file's (`encode::rate`), at its
    /// quality: a step (rate mode, no rate control of its own) or a bound (max-error mode);
    /// `trial`: a coding whose file is not kept, without its source-error map.
    pub fn at(quality: Quality, raster: &crate::io::raster::Raster, trial: bool) -> Self {
        match quality {
            Quality::Step(at) => ProjectedSettings {
                at_step: Some(at),
                trial,
                ..Default::default()
            },
            // The file's bound, no finer than this chunk's range is coded to: finer only where
            // the chunk is constant (its range is then taken as 1) in a file of a range under 1,
            // and a constant is decoded exactly.
            Quality::Bound(e) => ProjectedSettings {
                max_error: Some(e.max(finest_bound(bound::chunk_span(raster)))),
                trial,
                ..Default::default()
            },
        }
    }
}

/// The rate of a height field's default encode: 0.8 bits a cell (20:1 against 16-bit samples),
/// where issue 34's measurements put every bar (bound within 2.7x of the actual error, tiles
/// within 1.4x of TiTiler's bytes).
pub const DEFAULT_HEIGHT_FIELD_BPP: f64 = 0.8;

/// The rate of an image's default encode when none is given: 0.75 bits a pixel, about the
/// bytes the quadtree PIFS wrote by default before images moved to this codec (0.65 bits on
/// camera, 0.70 on astronaut), so that the change of default is a change of quality (+3 to
/// +5 dB there) and not of size. Grey or colour: a colour image's rate counts its pixels.
pub const DEFAULT_IMAGE_BPP: f64 = 0.75;

impl Named for ProjectedSettings {
    const NAMES: &'static [(&'static str, &'static str)] = &[(
        CODEC_NAME,
        "Projected IFS with details on a grid: fitted subdivision plus details (height fields \
         and images; --max-error or --target-bpp).",
    )];
    const TAKES: &'static [&'static str] = &["target-bpp", "max-error", "bounded"];

    /// A max error, or a rate (`bounded`: the smallest max error that fits it; bounded
    /// alone, the height-field default's rate, [`DEFAULT_HEIGHT_FIELD_BPP`]); an image with
    /// neither, [`DEFAULT_IMAGE_BPP`].
    fn named(_name: &str, o: &Options, kind: AssetKind) -> Result<Self, Error> {
        match (o.max_error, o.target_bpp, o.bounded) {
            (Some(_), Some(_), _) => Err(Error::settings(
                "projected takes --max-error or --target-bpp, not both",
            )),
            (Some(_), None, true) => Err(Error::settings(
                "--bounded bounds the error under a rate (--target-bpp B), not under --max-error",
            )),
            (None, None, false) if kind == AssetKind::Image => Ok(ProjectedSettings {
                target_bpp: Some(DEFAULT_IMAGE_BPP),
                ..Default::default()
            }),
            (None, None, false) => Err(Error::settings(
                "projected takes --max-error E (source units) or --target-bpp B",
            )),
            (max_error, target_bpp, bounded) => Ok(ProjectedSettings {
                max_error,
                bounded,
                target_bpp: target_bpp.or(bounded.then_some(DEFAULT_HEIGHT_FIELD_BPP)),
                ..Default::default()
            }),
        }
    }
}

impl Default for ProjectedSettings {
    fn default() -> Self {
        // Measured on etopo20 and jacksboro at 0.2 and 0.8 bpp (docs/benchmarks.md). The
        // pyramid: coarse levels finer (0.65-0.75 a level) gain 1.5 dB at 0.8 bpp and 3 dB at
        // 0.2 bpp on etopo20 over one step for all, since a coarse sample predicts many finer
        // ones; a dead zone of 0.15 step beats none and 0.35 by 0.1-0.6 dB. Both: the
        // rate-distortion choice at lambda 0.1 adds 0.1-0.3 dB (0.05, 0.15, 0.2, 0.25, 0.3 and
        // 0.5 tried; on the lifted levels too).
        ProjectedSettings {
            max_error: None,
            pyramid: false,
            growth: 0.7,
            dead_zone: 0.15,
            lambda: 0.1,
            bounded: false,
            at_step: None,
            trial: false,
            target_bpp: None,
        }
    }
}

#[cfg(test)]
mod tests;
