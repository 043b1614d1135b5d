//! The codecs, one folder each: how a codec partitions its support, searches its maps, codes
//! them and states them as an [`crate::operator::Operator`]. A codec depends on the
//! layers below it (`core`; `geo`, `mesh`, `render` and the input rasters, ARCHITECTURE.md
//! "Layers"); the asset container ([`crate::asset`]) depends on the codecs. A plane codec's
//! encoder returns coded planes ([`coded::Coded`]) and asks what needs the layers above (its
//! planes decoded as a reader decodes them, the source-error map) of a [`coded::Measure`].
//!
//! | codec | asset kinds | folder |
//! |---|---|---|
//! | quadtree PIFS (codec 1) | images, height fields | [`quadtree`] |
//! | fractal interpolation surfaces (codec 2) | height fields | [`fis`] |
//! | projected IFS with details on surfaces (codec 3) | height fields | [`psa`] |
//! | IFS3D on signed distance fields (octree, codec 4) | volumes (meshes) | [`ifs3d`] |
//! | projected IFS with details on curves (codec 5) | curves | [`curve`] |
//! | projected IFS with details on grids (codec 6) | height fields, grey images | [`projected`] |

//!
//! A codec of planes (images, height fields) implements [`plane::PlaneCodec`] on its header,
//! [`plane::PlaneDecoder`] on its operator and [`coded::PlaneEncoder`] on its settings, in its
//! folder, and adds one line to `plane_codecs!` (below); the container, the decoders, the encoder's
//! entry (`encode::encode`) and the GPU take it from there.

/// The plane codecs, one line each: the variant's name (in [`registry::Codec`],
/// [`registry::Coding`], [`registry::PlaneOperator`] and `encode::CodecSettings`), its header
/// (a [`plane::PlaneCodec`]) and its settings (a [`coded::PlaneEncoder`]). Hands the list to
/// `$then!`, so that the registry and the encoder's entry are made from this one list.
macro_rules! plane_codecs {
    ($then:ident) => {
        $then! {
            /// Quadtree partitioned IFS (images and height fields).
            Quadtree(
                crate::codecs::quadtree::stream::PlaneHeader,
                crate::codecs::quadtree::settings::QuadtreeSettings
            ),
            /// Fractal interpolation surface (height fields), any layout of the vertical scaling.
            Fis(crate::codecs::fis::FisHeader, crate::codecs::fis::FisSettings),
            /// Piecewise self-affine model (psa2d), grey images and heights.
            Psa(crate::codecs::psa::PsaHeader, crate::codecs::psa::PsaSettings),
            /// Projected IFS with details on a grid (height fields, grey and colour images).
            Projected(
                crate::codecs::projected::ProjectedHeader,
                crate::codecs::projected::ProjectedSettings
            ),
        }
    };
}

pub mod coded;
pub mod curve;
pub mod fis;
pub mod ifs3d;
pub(crate) mod lattice;
pub mod options;
pub mod plane;
pub mod projected;
pub mod psa;
pub mod quadtree;
pub(crate) mod registry;
pub(crate) mod source;
