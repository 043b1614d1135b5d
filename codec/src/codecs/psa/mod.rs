//! The piecewise self-affine model on a rectangular lattice (`psa2d`, "Two methods for
//! representing discrete image data on rectangular lattices using fractal surfaces"), written as
//! the shared partitioned affine operator.
//!
//! Vertices every `region` (delta) samples carry heights; each region (a delta x delta cell of
//! the vertex lattice) is the image of a domain of `ratio` x `ratio` regions (Delta = a delta)
//! whose corners are vertices, found by search and stored as an address. For p in a region with
//! local coordinates (u, v) in [0, 1]^2, phi is the scaling of the region onto its domain (no
//! rotation) and
//!
//! `(W f)(p) = alpha u + beta v + gamma + s f(phi(p))`
//!
//! with the vertical map fitted so that W sends the domain's corner heights to the region's:
//! the surface passes through every vertex.
//!
//! - Rectangular tiling: four corners fix alpha, beta, gamma and s. A plane has no twist
//!   (`z00 - z10 - z01 + z11`), so `s = twist(region) / twist(domain)` and the plane follows.
//!   When the domain has no twist (the system is singular) or s would not contract, the region
//!   is degenerate. The paper then takes the least-squares plane of the corners; that plane
//!   misses a corner whenever the region twists, which would break the interpolation property
//!   this codec must keep, so a degenerate region here is the bilinear patch of its corners
//!   (s = 0): the least-squares plane plus the twist term, exact at all four. When the region has
//!   no twist either (the indefinite case), both are the same plane.
//! - Triangular tiling: each region is two triangles (split along the diagonal from (1, 0) to
//!   (0, 1)), each mapped from the same half of the domain. Three corners leave s free: it is
//!   fitted by least squares, clamped to the contraction bound and stored (the plane then
//!   follows from the corners). Both halves share the region's domain address.
//! - Domains: touching (domains tile the lattice: addresses on multiples of the ratio) or
//!   overlapping (any vertex may start a domain), searched within `radius` of the region.

pub(crate) mod encode;
pub(crate) mod fit;
pub(crate) mod plane;

use serde::{Deserialize, Serialize};

use crate::core::entropy::{Bit, Decoder, Encoder};
use crate::core::format::FormatError;
use crate::core::lattice::{
    IntCoder, get_grid, lattice_frame, lattice_locate, put_grid, top_index,
};
use crate::core::operator::{Operator, Step};

/// How regions are split.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Tiling {
    /// One map per rectangle, fixed by its four corners.
    Rectangular,
    /// Two triangles per rectangle, each with its own fitted s.
    Triangular,
}

pub use crate::codecs::options::Domains;

/// What a reader needs to decode a plane's stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PsaHeader {
    /// Source width and height in samples.
    pub samples: [u32; 2],
    /// Samples between vertices (delta).
    pub region: u32,
    /// Domain side in regions (a, so Delta = a delta).
    pub ratio: u32,
    /// Rectangles or triangles.
    pub tiling: Tiling,
    /// Touching or overlapping domains.
    pub domains: Domains,
    /// Search radius, in address steps (regions for overlapping, domains for touching).
    pub radius: u32,
    /// Vertex heights are multiples of this (normalised units).
    pub height_step: f32,
    /// Bits of a stored s (triangular tiling).
    pub scaling_bits: u8,
    /// Largest |s|, below 1.
    pub max_scaling: f32,
}

impl PsaHeader {
    /// Vertices along x and y.
    pub fn vertices(&self) -> [usize; 2] {
        let n = |s: u32| ((s.max(2) - 1).div_ceil(self.region) + 1) as usize;
        [n(self.samples[0]), n(self.samples[1])]
    }

    /// Rejects headers no encoder writes.
    pub fn validate(&self) -> Result<(), FormatError> {
        let [w, h] = self.samples;
        if !(2..=1 << 16).contains(&w) || !(2..=1 << 16).contains(&h) {
            return Err(FormatError::header(format!(
                "bad psa2d sample grid {w}x{h}"
            )));
        }
        if !(1..=4096).contains(&self.region) || !(2..=16).contains(&self.ratio) {
            return Err(FormatError::header(format!(
                "bad psa2d region {} or ratio {}",
                self.region, self.ratio
            )));
        }
        if self.radius > 4096 || !(self.height_step > 1e-9 && self.height_step <= 1.0) {
            return Err(FormatError::header("bad psa2d radius or height step"));
        }
        let contracts = self.max_scaling > 0.0 && self.max_scaling < 1.0;
        if !(2..=12).contains(&self.scaling_bits) || !contracts {
            return Err(FormatError::header("bad psa2d scaling quantiser"));
        }
        Ok(())
    }

    fn levels(&self) -> i32 {
        (1 << (self.scaling_bits - 1)) - 1
    }

    fn scaling_of(&self, q: i32) -> f32 {
        q as f32 / self.levels() as f32 * self.max_scaling
    }

    fn scaling_index(&self, s: f32) -> i32 {
        let l = self.levels();
        ((s / self.max_scaling * l as f32).round() as i32).clamp(-l, l)
    }

    /// Address step in vertices.
    fn step(&self) -> usize {
        match self.domains {
            Domains::Touching => self.ratio as usize,
            Domains::Overlapping => 1,
        }
    }

    /// The address a region's offsets count from (a domain over the region, in the lattice).
    fn home(&self, ci: usize, cj: usize) -> Option<(i64, i64)> {
        let [nx, ny] = self.vertices();
        let a = self.ratio as usize;
        if nx <= a || ny <= a {
            return None;
        }
        let st = self.step();
        let h = |c: usize, n: usize| -> i64 {
            let top = (n - 1 - a) / st * st;
            (c.saturating_sub(a / 2) / st * st).min(top) as i64
        };
        Some((h(ci, nx), h(cj, ny)))
    }

    /// The domain's top-left vertex for offsets (in address steps), if inside the lattice.
    fn address(&self, ci: usize, cj: usize, dx: i32, dy: i32) -> Option<(usize, usize)> {
        let [nx, ny] = self.vertices();
        let (hx, hy) = self.home(ci, cj)?;
        let st = self.step() as i64;
        let (x, y) = (hx + dx as i64 * st, hy + dy as i64 * st);
        let a = self.ratio as i64;
        (x >= 0 && y >= 0 && x + a < nx as i64 && y + a < ny as i64)
            .then_some((x as usize, y as usize))
    }
}

/// One region's coding: no domain (degenerate: the bilinear patch), or a domain address with,
/// for triangles, an s index per half.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RegionCode {
    /// The bilinear patch of the corners, s = 0.
    Patch,
    /// A domain at offsets (dx, dy) from the region's home, and the two halves' s indices
    /// (triangular tiling; 0 for rectangles).
    Mapped {
        /// Offset in x (address steps).
        dx: i32,
        /// Offset in y.
        dy: i32,
        /// s index of the lower-left triangle.
        s0: i32,
        /// s index of the upper-right triangle.
        s1: i32,
    },
}

/// Coded parameters: vertex height indices and one code per region.
#[derive(Clone, Debug, PartialEq)]
pub struct PsaParams {
    /// Row-major vertex heights (indices of `height_step`).
    pub heights: Vec<i32>,
    /// Row-major region codes.
    pub regions: Vec<RegionCode>,
}

/// Codes the parameters: heights by MED prediction, then per region a mapped flag, the offsets
/// and (triangles) the two s indices, each predicted by the previous region's.
pub fn encode_params(header: &PsaHeader, p: &PsaParams) -> Vec<u8> {
    let mut enc = Encoder::new();
    put_grid(&mut enc, &p.heights, header.vertices()[0]);
    let (mut flag, mut ox, mut oy, mut sc) = (
        Bit::default(),
        IntCoder::new(),
        IntCoder::new(),
        IntCoder::new(),
    );
    let mut last = (0, 0);
    for r in &p.regions {
        match *r {
            RegionCode::Patch => enc.bit(&mut flag, false),
            RegionCode::Mapped { dx, dy, s0, s1 } => {
                enc.bit(&mut flag, true);
                ox.put(&mut enc, dx);
                oy.put(&mut enc, dy);
                if header.tiling == Tiling::Triangular {
                    sc.put(&mut enc, s0 - last.0);
                    sc.put(&mut enc, s1 - last.1);
                    last = (s0, s1);
                }
            }
        }
    }
    enc.finish()
}

/// Reads the parameters back; a truncated or hostile stream is an error.
pub fn decode_params(header: &PsaHeader, bytes: &[u8]) -> Result<PsaParams, FormatError> {
    header.validate()?;
    let [nx, ny] = header.vertices();
    let mut dec = Decoder::new(bytes);
    let top = top_index(header.height_step);
    let heights = get_grid(&mut dec, [nx, ny], 0..=top, "vertex height index")?;
    let (mut flag, mut ox, mut oy, mut sc) = (
        Bit::default(),
        IntCoder::new(),
        IntCoder::new(),
        IntCoder::new(),
    );
    let mut last = (0, 0);
    let l = header.levels();
    let mut regions = Vec::with_capacity((nx - 1) * (ny - 1));
    for cj in 0..ny - 1 {
        if dec.overrun() {
            return Err(FormatError::stream("the psa2d stream is truncated"));
        }
        for ci in 0..nx - 1 {
            if !dec.bit(&mut flag) {
                regions.push(RegionCode::Patch);
                continue;
            }
            let (dx, dy) = (ox.get(&mut dec), oy.get(&mut dec));
            if header.address(ci, cj, dx, dy).is_none() {
                return Err(FormatError::stream(format!(
                    "region ({ci}, {cj}): domain offset ({dx}, {dy}) outside"
                )));
            }
            let (s0, s1) = if header.tiling == Tiling::Triangular {
                let s0 = last.0 + sc.get(&mut dec);
                let s1 = last.1 + sc.get(&mut dec);
                if !(-l..=l).contains(&s0) || !(-l..=l).contains(&s1) {
                    return Err(FormatError::stream("scaling index out of range"));
                }
                last = (s0, s1);
                (s0, s1)
            } else {
                (0, 0)
            };
            regions.push(RegionCode::Mapped { dx, dy, s0, s1 });
        }
    }
    if dec.overrun() {
        return Err(FormatError::stream("the psa2d stream is truncated"));
    }
    Ok(PsaParams { heights, regions })
}

/// A region's map, ready for decoding: g as a bilinear `c0 + cu u + cv v + cuv u v` per half
/// (rectangles use half 0 only; cuv is nonzero only for patches), s per half, and the domain.
#[derive(Clone, Copy, Debug)]
struct RegionMap {
    g: [[f32; 4]; 2],
    s: [f32; 2],
    /// Domain top-left in samples; `None` for patches.
    domain: Option<[f32; 2]>,
}

/// Twist of four corner values in the order (0,0), (1,0), (0,1), (1,1).
fn twist(z: [f32; 4]) -> f32 {
    z[0] - z[1] - z[2] + z[3]
}

/// The bilinear patch through four corners.
fn patch(z: [f32; 4]) -> [f32; 4] {
    [z[0], z[1] - z[0], z[2] - z[0], twist(z)]
}

/// The plane through three corner values of a triangle: half 0 has corners (0,0), (1,0), (0,1);
/// half 1 has (1,0), (0,1), (1,1).
fn plane(half: usize, z: [f32; 4]) -> [f32; 4] {
    if half == 0 {
        [z[0], z[1] - z[0], z[2] - z[0], 0.0]
    } else {
        // z = c0 + cu u + cv v through (1,0), (0,1), (1,1): cu = z11 - z01, cv = z11 - z10.
        let (cu, cv) = (z[3] - z[2], z[3] - z[1]);
        [z[1] - cu, cu, cv, 0.0]
    }
}

fn eval(g: [f32; 4], u: f32, v: f32) -> f32 {
    g[0] + g[1] * u + g[2] * v + g[3] * u * v
}

/// The rectangle's map from its corners and its domain's: `Some((g, s))` when the four-vertex
/// system has a contractive solution.
fn rectangle(zc: [f32; 4], zd: [f32; 4], max_scaling: f32) -> Option<([f32; 4], f32)> {
    let td = twist(zd);
    if td.abs() < 1e-12 {
        return None;
    }
    let s = twist(zc) / td;
    // NaN (an infinite twist ratio) fails this test too.
    if s.is_nan() || s.abs() > max_scaling {
        return None;
    }
    let r: [f32; 4] = std::array::from_fn(|k| zc[k] - s * zd[k]);
    // r has no twist (up to rounding): its plane passes through all four.
    Some(([r[0], r[1] - r[0], r[2] - r[0], 0.0], s))
}

/// The decoding operator of a piecewise self-affine surface.
#[derive(Clone, Debug)]
pub struct PsaOperator {
    vertices: [usize; 2],
    region: f32,
    ratio: f32,
    triangular: bool,
    valid: [f32; 2],
    maps: Vec<RegionMap>,
    max_scaling: f32,
    interval: (f32, f32),
}

impl PsaOperator {
    /// Builds the operator of decoded parameters.
    pub fn new(header: &PsaHeader, params: &PsaParams) -> Result<PsaOperator, FormatError> {
        header.validate()?;
        let [nx, ny] = header.vertices();
        if params.heights.len() != nx * ny || params.regions.len() != (nx - 1) * (ny - 1) {
            return Err(FormatError::stream(
                "psa2d parameter counts do not match the header",
            ));
        }
        let z: Vec<f32> = params
            .heights
            .iter()
            .map(|&q| q as f32 * header.height_step)
            .collect();
        let corners = |i: usize, j: usize, a: usize| -> [f32; 4] {
            [
                z[j * nx + i],
                z[j * nx + i + a],
                z[(j + a) * nx + i],
                z[(j + a) * nx + i + a],
            ]
        };
        let a = header.ratio as usize;
        let mut maps = Vec::with_capacity(params.regions.len());
        for cj in 0..ny - 1 {
            for ci in 0..nx - 1 {
                let zc = corners(ci, cj, 1);
                let code = params.regions[cj * (nx - 1) + ci];
                let m = match code {
                    RegionCode::Patch => RegionMap {
                        g: [patch(zc); 2],
                        s: [0.0; 2],
                        domain: None,
                    },
                    RegionCode::Mapped { dx, dy, s0, s1 } => {
                        let (di, dj) = header.address(ci, cj, dx, dy).ok_or_else(|| {
                            FormatError::stream("domain address outside the lattice")
                        })?;
                        let zd = corners(di, dj, a);
                        let domain = Some([
                            (di as u32 * header.region) as f32,
                            (dj as u32 * header.region) as f32,
                        ]);
                        match header.tiling {
                            Tiling::Rectangular => match rectangle(zc, zd, header.max_scaling) {
                                Some((g, s)) => RegionMap {
                                    g: [g; 2],
                                    s: [s; 2],
                                    domain,
                                },
                                // A coded map must solve; an encoder never writes one that
                                // does not (a corrupt file does).
                                None => {
                                    return Err(FormatError::stream(
                                        "a mapped region has no contractive map",
                                    ));
                                }
                            },
                            Tiling::Triangular => {
                                let s = [header.scaling_of(s0), header.scaling_of(s1)];
                                let g = std::array::from_fn(|h| {
                                    let r: [f32; 4] = std::array::from_fn(|k| zc[k] - s[h] * zd[k]);
                                    plane(h, r)
                                });
                                RegionMap { g, s, domain }
                            }
                        }
                    }
                };
                maps.push(m);
            }
        }
        let max_scaling = maps
            .iter()
            .flat_map(|m| m.s)
            .fold(0.0f32, |acc, s| acc.max(s.abs()));
        let mut op = PsaOperator {
            vertices: [nx, ny],
            region: header.region as f32,
            ratio: header.ratio as f32,
            triangular: header.tiling == Tiling::Triangular,
            valid: [header.samples[0] as f32, header.samples[1] as f32],
            maps,
            max_scaling,
            interval: (0.0, 1.0),
        };
        let bounds: Vec<(f32, f32, f32)> = op
            .maps
            .iter()
            .flat_map(|m| {
                (0..2).map(move |h| {
                    let c = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)];
                    let (lo, hi) =
                        c.iter()
                            .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &(u, v)| {
                                let g = eval(m.g[h], u, v);
                                (a.min(g), b.max(g))
                            });
                    (m.s[h], lo, hi)
                })
            })
            .collect();
        op.interval = crate::core::operator::invariant_interval(bounds.into_iter());
        Ok(op)
    }

    /// Largest |s|.
    pub fn max_scaling(&self) -> f32 {
        self.max_scaling
    }

    /// Regions (maps) of the lattice.
    pub fn regions(&self) -> usize {
        self.maps.len()
    }

    /// Regions coded as bilinear patches (degenerate or not worth a domain).
    pub fn patches(&self) -> usize {
        self.maps.iter().filter(|m| m.domain.is_none()).count()
    }

    #[inline]
    fn locate(&self, t: [f32; 2]) -> (usize, usize, f32, f32) {
        lattice_locate(self.vertices, self.region, t)
    }
}

impl Operator<2> for PsaOperator {
    fn frame(&self) -> [f32; 2] {
        lattice_frame(self.vertices, self.region)
    }

    fn valid(&self) -> [f32; 2] {
        self.valid
    }

    /// 1: the maps are fitted on point samples (as for interpolation surfaces).
    fn expansion(&self) -> u32 {
        1
    }

    #[inline]
    fn step(&self, p: [f32; 2]) -> Step<2> {
        let (ci, cj, u, v) = self.locate([p[0] - 0.5, p[1] - 0.5]);
        let m = &self.maps[cj * (self.vertices[0] - 1) + ci];
        let h = usize::from(self.triangular && u + v > 1.0);
        let offset = eval(m.g[h], u, v);
        match m.domain {
            None => Step {
                offset,
                contrast: 0.0,
                next: p,
            },
            Some([dx, dy]) => {
                let span = self.ratio * self.region;
                Step {
                    offset,
                    contrast: m.s[h],
                    next: [dx + u * span + 0.5, dy + v * span + 0.5],
                }
            }
        }
    }

    fn invariant_interval(&self) -> (f32, f32) {
        self.interval
    }
}

impl crate::core::pieces::Flatten for PsaOperator {
    /// One piece per region, or two (split on the diagonal) for triangles.
    fn pieces(&self) -> crate::core::pieces::PieceTable {
        use crate::core::pieces::{Piece, PieceTable, SPLIT};
        let [nx, ny] = self.vertices;
        let d = self.region;
        let span = self.ratio * d;
        let halves = if self.triangular { 2 } else { 1 };
        let mut pieces = Vec::with_capacity(self.maps.len() * halves);
        let mut lut = Vec::with_capacity(self.maps.len());
        for cj in 0..ny - 1 {
            for ci in 0..nx - 1 {
                let m = &self.maps[cj * (nx - 1) + ci];
                let origin = [0.5 + ci as f32 * d, 0.5 + cj as f32 * d];
                let first = pieces.len() as u32;
                lut.push(if self.triangular {
                    first | SPLIT
                } else {
                    first
                });
                for h in 0..halves {
                    let (next_x, next_y) = match m.domain {
                        Some([dx, dy]) => ([dx + 0.5, span, 0.0, 0.0], [dy + 0.5, 0.0, span, 0.0]),
                        // s = 0: phi is never followed; the identity keeps it in the frame.
                        None => ([origin[0], d, 0.0, 0.0], [origin[1], 0.0, d, 0.0]),
                    };
                    pieces.push(Piece {
                        origin,
                        inv_size: [1.0 / d; 2],
                        g: m.g[h],
                        s: [m.s[h], 0.0, 0.0, 0.0],
                        next_x,
                        next_y,
                    });
                }
            }
        }
        PieceTable {
            frame: self.frame(),
            valid: self.valid,
            lut_origin: [0.5; 2],
            lut_cell: [d; 2],
            lut_size: [(nx - 1) as u32, (ny - 1) as u32],
            lut,
            pieces,
            interval: self.interval,
        }
    }
}

/// Settings of the psa2d encoder.
#[derive(Clone, Debug, PartialEq)]
pub struct PsaSettings {
    /// Rectangles or triangles.
    pub tiling: Tiling,
    /// Touching or overlapping domains.
    pub domains: Domains,
    /// Samples between vertices (delta).
    pub region: u32,
    /// Domain side in regions (a).
    pub ratio: u32,
    /// Search radius in address steps.
    pub radius: u32,
    /// Bits of a stored s (triangles).
    pub scaling_bits: u8,
    /// Largest |s|.
    pub max_scaling: f32,
    /// Rate control: at most this many bits a source cell, picking the region size (see
    /// `codecs::lattice`).
    pub target_bpp: Option<f64>,
}

impl Default for PsaSettings {
    fn default() -> Self {
        PsaSettings {
            tiling: Tiling::Rectangular,
            domains: Domains::Overlapping,
            region: 4,
            ratio: 2,
            // +-8 regions: measured, a wider search gains under 0.1 dB on the DEMs for 4x time.
            radius: 8,
            scaling_bits: 5,
            max_scaling: 0.9,
            target_bpp: None,
        }
    }
}

/// The codec's name (`fractile encode --codec NAME`).
pub fn codec_name(tiling: Tiling) -> &'static str {
    match tiling {
        Tiling::Rectangular => "psa2d-rect",
        Tiling::Triangular => "psa2d-tri",
    }
}
