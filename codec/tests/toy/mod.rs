//! A codec for the new-codec test (`tests/new_codec.sh`, issue 76), not part of the build: the
//! script copies the workspace, puts this file at `codec/src/codecs/toy/mod.rs`, adds its
//! `mod` line and its line in `plane_codecs!`, and runs the CLI, the server and Python on it
//! with no other edit. It is the projected codec under another byte and name, coded to a max
//! error: a real operator, written in this folder alone.

use fractile_proto::{AssetKind, AssetMeta};
use serde::{Deserialize, Serialize};

use crate::Error;
use crate::codecs::coded::{Coded, Measure, PlaneEncoder};
use crate::codecs::options::{Named, Options};
use crate::codecs::plane::{Build, PlaneCodec};
use crate::core::format::FormatError;
use crate::codecs::projected::{ProjectedHeader, ProjectedOperator, ProjectedSettings};
use crate::codecs::registry::Coding;
use crate::core::metrics::Errors;
use crate::io::raster::Raster;

/// The toy codec's name.
pub const NAME: &str = "toy";

/// A plane's header: the projected codec's.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ToyHeader(ProjectedHeader);

impl PlaneCodec for ToyHeader {
    type Operator = ProjectedOperator;
    const BYTE: u8 = 8;
    const LABEL: &'static str = "toy";
    const NAME: Option<&'static str> = Some(NAME);

    fn name(&self) -> &'static str {
        NAME
    }

    fn cost(&self, meta: &AssetMeta, stream: &[u8]) -> Result<u64, FormatError> {
        self.0.cost(meta, stream)
    }

    fn operator(
        &self,
        meta: &AssetMeta,
        stream: &[u8],
        build: Build,
    ) -> Result<ProjectedOperator, FormatError> {
        self.0.operator(meta, stream, build)
    }
}

/// The toy codec's settings: a max error, source units.
#[derive(Clone, Debug, PartialEq)]
pub struct ToySettings {
    /// Every valid decoded cell within this of its source.
    pub max_error: f64,
}

impl Default for ToySettings {
    fn default() -> Self {
        ToySettings { max_error: 1.0 }
    }
}

impl PlaneEncoder for ToySettings {
    fn encode(
        &self,
        raster: &Raster,
        measure: &dyn Measure,
        progress: &(dyn Fn(u64, u64) + Sync),
    ) -> Result<(Coded, Errors), Error> {
        let projected = ProjectedSettings {
            max_error: Some(self.max_error),
            ..Default::default()
        };
        let (coded, errors) = projected.encode(raster, measure, progress)?;
        let planes = coded
            .planes
            .into_iter()
            .map(|p| match p.coding {
                Coding::Projected { header, stream } => Ok((ToyHeader(header), stream)),
                _ => Err(Error::settings("the toy codec wraps projected planes")),
            })
            .collect::<Result<Vec<_>, Error>>()?;
        let mut toy = Coded::new(coded.meta, planes, coded.mask, Build::Whole)?;
        toy.meta.encoder = format!("{NAME} max_error={}", self.max_error);
        toy.source_error = coded.source_error;
        Ok((toy, errors))
    }

    fn reader_bytes_per_cell(&self) -> u64 {
        56
    }
}

impl Named for ToySettings {
    const NAMES: &'static [(&'static str, &'static str)] =
        &[(NAME, "The new-codec test's codec (the projected codec renamed).")];
    const TAKES: &'static [&'static str] = &["max-error"];

    fn named(_name: &str, o: &Options, _kind: AssetKind) -> Result<Self, Error> {
        Ok(ToySettings {
            max_error: o.max_error.unwrap_or(ToySettings::default().max_error),
        })
    }
}
