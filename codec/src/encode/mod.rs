//! Inputs into assets. The entry point of the plane codecs is [`encode`]: a [`Raster`] and
//! the settings of one codec ([`CodecSettings`], or a codec's own settings), each codec's
//! encoder in its folder (`codecs/<name>/encode.rs`, a [`PlaneEncoder`]) returning coded
//! planes, which become the [`Encoded`] asset here (`encoded`: the asset and what was
//! measured; the [`Measure`] lent to the encoders). Here too is what runs any of them
//! (`chunked`, `rate`, `parts`), the source error map (`fidelity`) and the encoders of meshes
//! (`volume`) and curves (`curve`).

pub mod assembly;
mod band;
pub mod chunked;
pub mod curve;
mod encoded;
pub(crate) mod fidelity;
pub mod parts;
pub mod plan;
mod pyramid;
pub mod rate;
mod spill;
mod summary;
mod tally;
mod views;
pub mod volume;

pub use crate::codecs::coded::{Coded, Measure, PlaneEncoder};
pub use crate::codecs::options::{Domains, Named, Options, Search};

pub use encoded::{Encoded, Written};
pub use plan::Plan;

use fractile_proto::AssetKind;

use crate::Error;

use crate::codecs::projected::ProjectedSettings;
use crate::codecs::registry::Codec;
use crate::core::metrics::Errors;
use crate::io::raster::Raster;

macro_rules! settings {
    ($( $(#[$doc:meta])* $name:ident($header:ty, $settings:ty) ),* $(,)?) => {
        /// The settings of one plane codec: which codec codes a raster, and how.
        #[derive(Clone, Debug, PartialEq)]
        pub enum CodecSettings {
            $( $(#[$doc])* $name($settings), )*
        }

        impl CodecSettings {
            /// The default settings of a plane codec (`None` for volumes and curves).
            pub fn default_for(codec: Codec) -> Option<CodecSettings> {
                match codec {
                    $( Codec::$name => Some(CodecSettings::$name(<$settings>::default())), )*
                    Codec::Octree | Codec::Curve => None,
                }
            }

            /// The codec these settings name.
            pub fn codec(&self) -> Codec {
                match self {
                    $( CodecSettings::$name(_) => Codec::$name, )*
                }
            }

            /// Every plane codec's names (`--codec`, Python's `codec=`), each with a line of
            /// help, in the registry's order.
            pub fn names() -> Vec<(&'static str, &'static str)> {
                [$( <$settings as Named>::NAMES, )*].concat()
            }

            /// The options the codec `name` reads (`None`: no plane codec is so named).
            pub fn takes(name: &str) -> Option<&'static [&'static str]> {
                $(
                    if <$settings as Named>::NAMES.iter().any(|(n, _)| *n == name) {
                        return Some(<$settings as Named>::TAKES);
                    }
                )*
                None
            }

            /// The settings of the plane codec `name` with `options`, for a raster of `kind`;
            /// an unknown name, or an option the codec does not read, is refused by name.
            pub fn named(name: &str, options: &Options, kind: AssetKind) -> Result<CodecSettings, Error> {
                $(
                    if <$settings as Named>::NAMES.iter().any(|(n, _)| *n == name) {
                        options.refuse_untaken(name, <$settings as Named>::TAKES)?;
                        return <$settings as Named>::named(name, options, kind).map(CodecSettings::$name);
                    }
                )*
                let names: Vec<&str> = CodecSettings::names().iter().map(|(n, _)| *n).collect();
                Err(Error::settings(format!(
                    "unknown codec {name:?}; the plane codecs are {}",
                    names.join(", ")
                )))
            }
        }

        impl PlaneEncoder for CodecSettings {
            fn encode(
                &self,
                raster: &Raster,
                measure: &dyn Measure,
                progress: &(dyn Fn(u64, u64) + Sync),
            ) -> Result<(Coded, Errors), Error> {
                match self {
                    $( CodecSettings::$name(s) => s.encode(raster, measure, progress), )*
                }
            }

            fn reader_bytes_per_cell(&self) -> u64 {
                match self {
                    $( CodecSettings::$name(s) => s.reader_bytes_per_cell(), )*
                }
            }
        }

        $(
            impl From<$settings> for CodecSettings {
                fn from(settings: $settings) -> CodecSettings {
                    CodecSettings::$name(settings)
                }
            }
        )*
    };
}

plane_codecs!(settings);

/// Encodes a raster with the codec `settings` name ([`CodecSettings`], or one codec's own
/// settings); `progress(done, total)` is called as work is done, where the codec counts it.
pub fn encode(
    raster: &Raster,
    settings: &(impl PlaneEncoder + ?Sized),
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<Encoded, Error> {
    // A raster in one piece that readers under the default limits would refuse is refused
    // before it is coded (an 8640 x 8640 DEM was coded for minutes, then not opened).
    let cells = (raster.width as u64).saturating_mul(raster.height as u64);
    let limits = crate::AssetLimits::default();
    limits
        .check_pixels("a grid", cells)
        .and_then(|()| limits.check_cost(cells.saturating_mul(settings.reader_bytes_per_cell())))
        .map_err(|e| {
            Error::settings(format!(
                "{} x {} cells in one piece: readers would refuse it ({}); encode it in chunks \
                 (--chunk 1024, Python's chunk=1024)",
                raster.width,
                raster.height,
                e.message()
            ))
        })?;
    let context = encoded::Context::new();
    let (coded, errors) = settings.encode(raster, &context, progress)?;
    context.encoded(coded, errors)
}

pub use crate::codecs::projected::DEFAULT_HEIGHT_FIELD_BPP;

/// What `fractile encode` writes when no codec is named, at `target_bpp` bits a source cell: for
/// a height field the projected IFS with details under a bounded rate (the smallest max error
/// whose file fits, so every cell is within the `error_bound` it answers: the quadtree's
/// per-block bounds are 9 to 19 times its actual errors on DEMs, and its PSNR is 2-3 dB lower
/// at the same bytes); for an image the same codec under the rate (the best PSNR that fits:
/// 1-3 dB over the quadtree PIFS at the same bytes, and no blocks when zoomed past its pixels;
/// `QuadtreeSettings` keeps the seed's method). The server's demo and the benches encode this
/// way.
pub fn encode_default(
    raster: &Raster,
    target_bpp: f64,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<Encoded, Error> {
    let settings = ProjectedSettings {
        bounded: raster.kind == AssetKind::HeightField,
        target_bpp: Some(target_bpp),
        ..Default::default()
    };
    encode(raster, &settings, progress)
}
