//! What a plane codec's encoder ([`PlaneEncoder`]) makes: coded planes ([`Coded`]), each with
//! the operator a reader decodes from its stream, the payload they make and the size of their
//! file. Below the asset container (`io::asset`), which holds them: an encoder codes, sizes
//! and weighs planes here, and asks what it cannot do from this layer, decoding them as a
//! reader of the file would and measuring their source-error map, of a [`Measure`] that
//! `encode` lends it (as rav1e's encoder is driven by a context it is handed).

use fractile_proto::AssetMeta;
use serde::{Deserialize, Serialize};

use crate::Error;
use crate::codecs::plane::Build;
use crate::codecs::quadtree::stream::PlaneHeader;
use crate::codecs::registry::{self, Codec, Coding, PlaneOperator, Registered, Visit};
use crate::core::fidelity::SourceError;
use crate::core::metrics::{Errors, compare};
use crate::io::frame::assemble;
use crate::io::mask::Mask;
use crate::io::raster::Raster;

/// A coded plane: how it is coded and the operator decoded from that.
#[derive(Clone, Debug)]
pub struct Plane {
    /// Header and stream, as stored.
    pub coding: Coding,
    /// The decoding operator.
    pub operator: PlaneOperator,
}

impl Plane {
    /// The largest |decoded sample - source| the encoder promised at every valid sample centre
    /// (source units), for codecs that promise one (projected under `--max-error`).
    pub fn promise(&self) -> Option<f32> {
        match &self.coding {
            Coding::Projected { header, .. } => header.promise().map(|e| e as f32),
            _ => None,
        }
    }

    /// The quadtree header, for quadtree planes.
    pub fn header(&self) -> Option<&PlaneHeader> {
        match &self.coding {
            Coding::Quadtree { header, .. } => Some(header),
            _ => None,
        }
    }
}

/// The payload of a plane codec: its planes (header and stream) and the mask. One generic
/// struct for every codec: bincode writes a struct as its fields, so every codec's payload
/// has this layout.
#[derive(Serialize, Deserialize)]
pub(crate) struct Payload<H> {
    pub(crate) planes: Vec<(H, Vec<u8>)>,
    pub(crate) mask: Option<Vec<u8>>,
}

/// Planes as a plane codec's encoder returns them: the asset's metadata, every plane coded
/// and decoded into its operator (so that what is weighed and served is what a reader of the
/// file gets), the nodata mask, and the source-error map once measured ([`Measure::kept`]).
/// `io::asset::Asset` holds them as they are.
#[derive(Clone, Debug)]
pub struct Coded {
    /// What the asset is (its stats once kept).
    pub meta: AssetMeta,
    /// One plane per coded channel (Y, Cb, Cr for colour).
    pub planes: Vec<Plane>,
    /// Source validity, for height fields with nodata.
    pub mask: Option<Mask>,
    /// Each block's measured error against the source, once kept.
    pub source_error: Option<SourceError>,
}

impl Coded {
    /// Decodes every stream of the codec whose header is `H` into its operator, built as
    /// `build` says (errors name the plane).
    pub fn new<H: Registered>(
        meta: AssetMeta,
        planes: Vec<(H, Vec<u8>)>,
        mask: Option<Mask>,
        build: Build,
    ) -> Result<Coded, Error> {
        H::accepts(&meta)?;
        let planes = planes
            .into_iter()
            .enumerate()
            .map(|(i, (header, stream))| {
                let operator = header
                    .operator(&meta, &stream, build)
                    .map_err(|e| Error::asset(format!("plane {i}: {e}")))?;
                Ok(Plane {
                    operator: H::plane_operator(operator),
                    coding: header.coding(stream),
                })
            })
            .collect::<Result<Vec<_>, Error>>()?;
        Ok(Coded {
            meta,
            planes,
            mask,
            source_error: None,
        })
    }

    /// Size in bytes of the file the same parts make, without decoding the streams or building
    /// operators: rate control asks it of every trial partition and decodes the one it keeps.
    pub fn file_size_of<H: Registered>(
        meta: &AssetMeta,
        planes: Vec<(H, Vec<u8>)>,
        mask: Option<&Mask>,
    ) -> usize {
        let payload = fractile_proto::encode(&Payload {
            planes,
            mask: mask.map(Mask::encode),
        });
        assemble(meta, H::BYTE, &payload, &[]).len()
    }

    /// The codec of the planes.
    pub fn codec(&self) -> Codec {
        self.planes
            .first()
            .map_or(Codec::Quadtree, |p| p.coding.codec())
    }

    /// The file's bytes: the frame, the payload and the source-error map if measured.
    pub fn to_bytes(&self) -> Vec<u8> {
        let codec = self.codec();
        let payload = payload(codec, &self.planes, self.mask.as_ref());
        file_bytes(&self.meta, codec, &payload, self.source_error.as_ref())
    }

    /// Size of the file in bytes.
    pub fn file_size(&self) -> usize {
        self.to_bytes().len()
    }

    /// Ranges (or cells) over all planes.
    pub fn transforms(&self) -> usize {
        self.planes.iter().map(|p| p.operator.transforms()).sum()
    }

    /// The errors of the planes decoded at the source's size against `source` (valid cells,
    /// source units), with the planes back.
    pub fn errors(self, source: &Raster, measure: &dyn Measure) -> (Coded, Errors) {
        let (coded, decoded) = measure.decoded(self);
        let errors = compare(
            &source.channels,
            &decoded,
            source.valid.as_deref(),
            coded.meta.psnr_peak(),
        );
        (coded, errors)
    }
}

/// The file of a payload of `codec`: its frame, and the source-error map after the payload.
pub(crate) fn file_bytes(
    meta: &AssetMeta,
    codec: Codec,
    payload: &[u8],
    source_error: Option<&SourceError>,
) -> Vec<u8> {
    let section = source_error.map(SourceError::encode).unwrap_or_default();
    assemble(meta, codec.byte(), payload, &section)
}

/// The payload of `codec`'s `planes` (each holds its header and stream) and the mask.
pub(crate) fn payload(codec: Codec, planes: &[Plane], mask: Option<&Mask>) -> Vec<u8> {
    registry::visit(
        codec,
        WritePayload {
            planes,
            mask: mask.map(Mask::encode),
        },
    )
    .expect("a codec of planes")
}

/// Writes the planes of a plane codec as its payload.
struct WritePayload<'a> {
    planes: &'a [Plane],
    mask: Option<Vec<u8>>,
}

impl Visit for WritePayload<'_> {
    type Output = Vec<u8>;

    fn visit<H: Registered>(self) -> Vec<u8> {
        fractile_proto::encode(&Payload {
            planes: self
                .planes
                .iter()
                .filter_map(|p| H::of(&p.coding))
                .map(|(header, stream)| (header.clone(), stream.to_vec()))
                .collect(),
            mask: self.mask,
        })
    }
}

/// What an encoder asks of the asset its planes become, which it cannot do from the codecs'
/// layer: decode them at the source's size as a reader of the file does (`extract`), and
/// measure the source-error map that a kept file carries (`encode::fidelity`, with the
/// continuous decoder). `encode` lends one to every encode, timed from its start. The planes
/// move in and back out: no copy.
pub trait Measure: Sync {
    /// The planes decoded at the source's size, in source units (NaN where the mask is not
    /// valid), and the planes back.
    fn decoded(&self, coded: Coded) -> (Coded, Vec<Vec<f32>>);

    /// The planes as a file keeps them: their source-error map measured against `source` and
    /// the encode's figures (`errors`, transforms, seconds so far) in the metadata's stats.
    fn kept(&self, coded: Coded, source: &Raster, errors: &Errors) -> Coded;
}

/// A plane codec's encoder, implemented by its settings: what the entry point
/// (`encode::encode`) runs for the codec the settings name.
pub trait PlaneEncoder {
    /// Codes `raster` into planes as a file keeps them ([`Measure::kept`]: with their
    /// source-error map, unless the settings ask for a trial coding), with the errors of their
    /// decode against the source; `measure` decodes what the encoder weighs, and
    /// `progress(done, total)` is called as work is done, where the codec counts it.
    fn encode(
        &self,
        raster: &Raster,
        measure: &dyn Measure,
        progress: &(dyn Fn(u64, u64) + Sync),
    ) -> Result<(Coded, Errors), Error>;

    /// What a reader of this codec's file takes a cell at least (its `PlaneCodec::cost` and
    /// the discrete decode's two f32 grids): `encode::encode` refuses up front a raster in one
    /// piece that readers would refuse, rather than after coding it. A lower bound: the file
    /// itself is checked before it is written (`Encoded::write`).
    fn reader_bytes_per_cell(&self) -> u64 {
        8
    }
}
