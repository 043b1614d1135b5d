//! The registry of the plane codecs: what the container and the decoders know of them, made
//! from the one list in `codecs/mod.rs` (`plane_codecs!`): the codec byte ([`Codec`]), how a
//! plane is coded ([`Coding`]) and its operator ([`PlaneOperator`]), each dispatching to the
//! codec's [`PlaneCodec`] and [`PlaneDecoder`]. A new codec adds its line to the list; nothing
//! here names a codec but the quadtree's ranges and the two codecs without planes.

use crate::codecs::plane::{PlaneCodec, PlaneDecoder};
use crate::codecs::quadtree::operator::RangeMap;
use crate::core::decode::{Patch, PointValue};
use crate::core::operator::{Chain, Operator, Step};
use crate::core::pieces::{Flat, Flatten, PieceTable};

/// The codec byte of IFS3D volumes (octree PIFS of a signed distance field), which have no
/// planes.
pub(crate) const OCTREE_BYTE: u8 = 4;
/// The codec byte of curve sets (projected IFS with details of curves), which have no planes.
pub(crate) const CURVE_BYTE: u8 = 5;
/// The codec byte of a chunked container (`io::layout`), which names no codec: its chunks do.
/// No plane codec may take it (a file of that byte is read as chunked): checked when the
/// registry is built.
pub(crate) const CHUNKED_BYTE: u8 = 7;

/// A plane codec as the registry lists it: its header, with how a header and stream become a
/// [`Coding`] and an operator a [`PlaneOperator`] (made by the registry for every codec).
pub trait Registered: PlaneCodec {
    /// This codec's [`Coding`] of a plane.
    fn coding(self, stream: Vec<u8>) -> Coding;
    /// The header and stream of a plane coded by this codec.
    fn of(coding: &Coding) -> Option<(&Self, &[u8])>;
    /// This codec's [`PlaneOperator`].
    fn plane_operator(operator: Self::Operator) -> PlaneOperator;
}

/// Work done for whichever plane codec a file names: generic over it, so that the container
/// reads and writes every codec's planes with one function.
pub(crate) trait Visit {
    /// What the work gives.
    type Output;
    /// The work, for the plane codec whose header is `H`.
    fn visit<H: Registered>(self) -> Self::Output;
}

macro_rules! registry {
    ($( $(#[$doc:meta])* $name:ident($header:ty, $settings:ty) ),* $(,)?) => {
        // A plane codec's byte is none of those reserved (the enum below refuses two codecs of
        // one byte).
        const _: () = {
            $(
                assert!(
                    <$header as PlaneCodec>::BYTE != CHUNKED_BYTE,
                    "a plane codec's byte is that of the chunked container (7)"
                );
            )*
        };

        /// The codec of an asset's payload (the container's byte at offset 11, which is the
        /// discriminant: `codec as u8` is its byte).
        #[derive(Clone, Copy, Debug, PartialEq, Eq)]
        #[repr(u8)]
        pub enum Codec {
            $( $(#[$doc])* $name = <$header as PlaneCodec>::BYTE, )*
            /// Octree partitioned IFS of a signed distance volume (IFS3D).
            Octree = OCTREE_BYTE,
            /// Projected IFS with details of a set of curves.
            Curve = CURVE_BYTE,
        }

        impl Codec {
            /// Every codec this build reads.
            pub const ALL: &'static [Codec] = &[$(Codec::$name,)* Codec::Octree, Codec::Curve];

            /// The codec byte.
            pub fn byte(self) -> u8 {
                self as u8
            }

            /// The codec of a codec byte.
            pub fn from_byte(byte: u8) -> Option<Codec> {
                Codec::ALL.iter().copied().find(|c| c.byte() == byte)
            }

            /// How an error that lists what a build reads names the codec.
            pub fn label(self) -> &'static str {
                match self {
                    $( Codec::$name => <$header as PlaneCodec>::LABEL, )*
                    Codec::Octree => "IFS3D",
                    Codec::Curve => "curves",
                }
            }

            /// The codec's name as the CLI and the API spell it, where its byte tells it.
            pub fn name(self) -> Option<&'static str> {
                match self {
                    $( Codec::$name => <$header as PlaneCodec>::NAME, )*
                    Codec::Octree => Some("ifs3d-octree"),
                    Codec::Curve => Some("curve-pifs"),
                }
            }
        }

        /// How a plane is coded: the header a reader needs and the entropy-coded stream.
        #[derive(Clone, Debug)]
        pub enum Coding {
            $(
                $(#[$doc])*
                $name {
                    /// What a reader needs before the stream.
                    header: $header,
                    /// The coded parameters.
                    stream: Vec<u8>,
                },
            )*
        }

        impl Coding {
            /// The codec.
            pub fn codec(&self) -> Codec {
                match self {
                    $( Coding::$name { .. } => Codec::$name, )*
                }
            }

            /// The coded stream.
            pub fn stream(&self) -> &[u8] {
                match self {
                    $( Coding::$name { stream, .. } => stream, )*
                }
            }

            /// The codec's name as the CLI and the API spell it.
            pub fn name(&self) -> &'static str {
                match self {
                    $( Coding::$name { header, .. } => header.name(), )*
                }
            }
        }

        /// The decoding operator of a plane, whichever codec made it. Decoders see only
        /// [`Operator`]; batch calls resolve the codec once (see [`PlaneDecoder`]).
        #[derive(Clone, Debug)]
        pub enum PlaneOperator {
            $( $(#[$doc])* $name(<$header as PlaneCodec>::Operator), )*
        }

        $(
            impl Registered for $header {
                fn coding(self, stream: Vec<u8>) -> Coding {
                    Coding::$name { header: self, stream }
                }
                fn of(coding: &Coding) -> Option<(&Self, &[u8])> {
                    match coding {
                        Coding::$name { header, stream } => Some((header, stream)),
                        #[allow(unreachable_patterns)]
                        _ => None,
                    }
                }
                fn plane_operator(operator: Self::Operator) -> PlaneOperator {
                    PlaneOperator::$name(operator)
                }
            }
        )*

        /// Runs `work` for the plane codec `codec` (`None` for codecs without planes).
        pub(crate) fn visit<V: Visit>(codec: Codec, work: V) -> Option<V::Output> {
            match codec {
                $( Codec::$name => Some(work.visit::<$header>()), )*
                Codec::Octree | Codec::Curve => None,
            }
        }


        impl PlaneOperator {
            /// [`PlaneDecoder::points`] of the codec's operator.
            pub fn points(&self, pts: &[[f32; 2]], iterations: u32, tolerance: f32) -> Vec<PointValue> {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::points(o, pts, iterations, tolerance), )* }
            }

            /// [`PlaneDecoder::grid`]: the separable grid `(xs[i], ys[j])`, row-major.
            pub fn grid(&self, xs: &[f32], ys: &[f32], iterations: u32, tolerance: f32) -> Vec<PointValue> {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::grid(o, xs, ys, iterations, tolerance), )* }
            }

            /// [`PlaneDecoder::grid_steps`]: the steps [`Self::grid`] takes at every point where it
            /// takes the same everywhere. A device asked for the grid is asked for that many steps
            /// exactly, so that it answers as the CPU does.
            pub fn grid_steps(&self, xs: &[f32], ys: &[f32], iterations: u32, tolerance: f32) -> Option<u32> {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::grid_steps(o, xs, ys, iterations, tolerance), )* }
            }

            /// [`PlaneDecoder::patch`]: a bilinear [`Patch`] of points, row-major.
            pub fn patch(&self, patch: &Patch, iterations: u32, tolerance: f32) -> Vec<PointValue> {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::patch(o, patch, iterations, tolerance), )* }
            }

            /// [`PlaneDecoder::point`].
            pub fn point(&self, p: [f32; 2], iterations: u32) -> PointValue {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::point(o, p, iterations), )* }
            }

            /// [`PlaneDecoder::samples`]: the attractor at the source's sample centres, where known.
            pub fn samples(&self) -> Option<&[f32]> {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::samples(o), )* }
            }

            /// [`PlaneDecoder::limit_points`], applied to every continuous answer, the CPU's and a
            /// device's alike.
            pub fn limit_points(&self, pts: &[[f32; 2]], values: &mut [f32]) {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::limit_points(o, pts, values), )* }
            }

            /// [`PlaneDecoder::limit_grid`].
            pub fn limit_grid(&self, xs: &[f32], ys: &[f32], values: &mut [f32]) {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::limit_grid(o, xs, ys, values), )* }
            }

            /// Largest |s| anywhere.
            pub fn max_contrast(&self) -> f32 {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::max_contrast(o), )* }
            }

            /// Maps of the operator: ranges, cells or regions.
            pub fn transforms(&self) -> usize {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::transforms(o), )* }
            }

            /// [`PlaneDecoder::resident_bytes`] of a plane of `cells` source cells.
            pub fn resident_bytes(&self, cells: u64) -> u64 {
                match self { $( PlaneOperator::$name(o) => PlaneDecoder::resident_bytes(o, cells), )* }
            }
        }

        impl Flatten for PlaneOperator {
            fn pieces(&self) -> PieceTable {
                match self { $( PlaneOperator::$name(o) => o.pieces(), )* }
            }

            fn flat(&self) -> Flat {
                match self { $( PlaneOperator::$name(o) => o.flat(), )* }
            }
        }

        impl Operator<2> for PlaneOperator {
            fn frame(&self) -> [f32; 2] {
                match self { $( PlaneOperator::$name(o) => o.frame(), )* }
            }
            fn valid(&self) -> [f32; 2] {
                match self { $( PlaneOperator::$name(o) => o.valid(), )* }
            }
            fn expansion(&self) -> u32 {
                match self { $( PlaneOperator::$name(o) => o.expansion(), )* }
            }
            #[inline]
            fn step(&self, p: [f32; 2]) -> Step<2> {
                match self { $( PlaneOperator::$name(o) => o.step(p), )* }
            }
            fn invariant_interval(&self) -> (f32, f32) {
                match self { $( PlaneOperator::$name(o) => o.invariant_interval(), )* }
            }
            fn run_chains(&self, chains: &mut [Chain<2>], iterations: u32, tolerance: f32) {
                match self { $( PlaneOperator::$name(o) => o.run_chains(chains, iterations, tolerance), )* }
            }
        }
    };
}

plane_codecs!(registry);

impl PlaneOperator {
    /// The quadtree's ranges (empty for other codecs).
    pub fn ranges(&self) -> &[RangeMap] {
        match self {
            PlaneOperator::Quadtree(q) => q.ranges(),
            _ => &[],
        }
    }
}
