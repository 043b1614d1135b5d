//! An encode of a raster planned from a codec's name and its options, as rav1e's
//! `EncoderConfig` becomes a `Context`: the codec's settings ([`CodecSettings::named`]), the
//! raster whole or in chunks, the chunks at one quality for the whole file where the codec
//! offers one ([`rate::file_target`]) or each at its share of the rate ([`chunk_bpp`]), and the
//! fingerprint every part of a split encode must share. The command line and Python build one
//! from their arguments and run it: the options are read once, and each chunk is coded by the
//! codec's settings, not by a closure of the caller.

use std::path::Path;

use super::chunked::{
    DEFAULT_CHUNK, EncodeLevel, Progress, Share, chunk_bpp, encode_chunked_file,
    encode_chunked_file_at, wants_chunks,
};
use super::parts::{PartWritten, Recipe, encode_chunked_part, encode_chunked_part_at, recipe_of};
use super::rate::{self, Quality, Target, encode_at};
use super::{CodecSettings, Options, Written, encode};
use crate::Error;
use crate::io::raster::Raster;
use crate::io::rows::{Header, Rows};

/// A raster's encode, planned ([`Plan::new`]) and then run whole ([`Plan::settings`] with
/// [`encode`]), in chunks ([`Plan::encode_chunks`]) or as one part of a split encode
/// ([`Plan::encode_part`]).
#[derive(Clone, Debug)]
pub struct Plan {
    /// The codec's settings for the raster whole.
    settings: CodecSettings,
    /// The chunks' side; `None`: the raster whole.
    chunk: Option<u32>,
    /// In chunks: the one quality of the file's chunks, where the codec offers one.
    file: Option<Target>,
    /// In chunks without one: each chunk's settings, at its share of the file's rate.
    per_chunk: CodecSettings,
    /// The codec's name and options, as given: a split encode's parts keep them, for
    /// `fractile assemble` to code the overviews alike.
    recipe: Recipe,
}

impl Plan {
    /// The plan of the codec `codec` with `options` for the raster `header` describes. `chunk`:
    /// `Some(0)` whole, `Some(c)` in chunks of `c`, `None` the default: chunks of
    /// [`DEFAULT_CHUNK`] for a raster over twice that on a side, else whole. An unknown codec, or
    /// an option it does not read, is refused by name.
    pub fn new(
        codec: &str,
        options: &Options,
        chunk: Option<u32>,
        header: &Header,
    ) -> Result<Plan, Error> {
        let (width, height) = (header.width, header.height);
        let settings = CodecSettings::named(codec, options, header.kind)?;
        let chunk = match chunk {
            Some(0) => None,
            Some(c) => Some(c),
            None => wants_chunks(width, height, DEFAULT_CHUNK).then_some(DEFAULT_CHUNK),
        };
        let (file, per_chunk) = match chunk {
            None => (None, settings.clone()),
            Some(c) => {
                let file = rate::file_target(&settings, header.channels);
                // The file's rate, overviews and table included, spread over its chunks.
                let share = Options {
                    target_bpp: options.target_bpp.map(|b| chunk_bpp(width, height, c, b)),
                    ..options.clone()
                };
                let per_chunk = match file {
                    Some(_) => settings.clone(),
                    None => CodecSettings::named(codec, &share, header.kind)?,
                };
                (file, per_chunk)
            }
        };
        Ok(Plan {
            settings,
            chunk,
            file,
            per_chunk,
            recipe: Recipe {
                codec: codec.to_string(),
                options: options.clone(),
                quality: None,
            },
        })
    }

    /// The codec's settings for the raster whole.
    pub fn settings(&self) -> &CodecSettings {
        &self.settings
    }

    /// The chunks' side, or `None` for the raster whole.
    pub fn chunk(&self) -> Option<u32> {
        self.chunk
    }

    /// What every part of a split encode must share, to be assembled: the settings, the
    /// chunks and the file's quality (`encode::parts` stores it in each part file).
    pub fn fingerprint(&self) -> String {
        format!("{:?} {:?} {:?}", self.per_chunk, self.chunk, self.file)
    }

    /// Codes the raster `rows` reads in chunks into the file `output`, streamed (a file of any
    /// size); `progress(done, total)` as chunks are coded. Whole (no chunks planned): an
    /// error, since [`encode`] with [`Plan::settings`] does that.
    pub fn encode_chunks(
        &self,
        rows: &mut dyn Rows,
        output: &Path,
        progress: &Progress<'_>,
    ) -> Result<Written, Error> {
        let c = self.chunked()?;
        match self.file {
            Some(target) => encode_chunked_file_at(rows, c, (target, &encode_at), progress, output),
            None => {
                let one = |r: &Raster| encode(r, &self.per_chunk, &|_, _| {});
                encode_chunked_file(rows, c, &one, progress, output)
            }
        }
    }

    /// Codes the chunks of `share` of the raster `rows` reads into the part file `output`
    /// (`fractile assemble` joins the parts into the file [`Plan::encode_chunks`] writes).
    pub fn encode_part(
        &self,
        rows: &mut dyn Rows,
        share: Share,
        output: &Path,
        progress: &Progress<'_>,
    ) -> Result<PartWritten, Error> {
        let c = self.chunked()?;
        let fingerprint = self.fingerprint();
        let how = (c, share, fingerprint.as_str(), Some(&self.recipe));
        match self.file {
            Some(target) => {
                encode_chunked_part_at(rows, how, (target, &encode_at), progress, output)
            }
            None => {
                let one = |r: &Raster| encode(r, &self.per_chunk, &|_, _| {});
                encode_chunked_part(rows, how, &one, progress, output)
            }
        }
    }

    /// How a chunk of level `l` is coded: at `quality` (the parts' own, found on their sample
    /// or given) where the file has one, else by the chunks' settings.
    fn level_encoder(&self, quality: Option<Quality>) -> Result<Box<EncodeLevel<'static>>, Error> {
        Ok(match self.file {
            Some(_) => {
                let q = quality.ok_or_else(|| {
                    Error::input("the parts do not say the quality their chunks were coded at")
                })?;
                Box::new(move |l, r: &Raster| encode_at(r, q.at_level(l), false))
            }
            None => {
                let settings = self.per_chunk.clone();
                Box::new(move |_, r: &Raster| encode(r, &settings, &|_, _| {}))
            }
        })
    }

    /// The chunks' side, or the error of a plan of the raster whole.
    fn chunked(&self) -> Result<u32, Error> {
        self.chunk.ok_or_else(|| {
            Error::settings("a split encode codes chunks, and this one is whole: give a chunk size")
        })
    }
}

/// `fractile assemble`: the part files `parts` of a split encode joined into the asset
/// `output` ([`super::assembly::assemble`]), its overviews coded as the parts' plan codes them
/// (the codec and options each part keeps); `progress(done, total)` counts the overview chunks.
pub fn assemble(
    parts: &[std::path::PathBuf],
    output: &Path,
    progress: &Progress<'_>,
) -> Result<Written, Error> {
    let Some(first) = parts.first() else {
        return Err(Error::input("assemble: no part files given"));
    };
    let (recipe, settings, chunk, header) = recipe_of(first)?;
    let Some(recipe) = recipe else {
        return Err(Error::input(format!(
            "{}: a part coded by a caller's own function (assemble it with encode::assembly::assemble and that function)",
            first.display()
        )));
    };
    let plan = Plan::new(&recipe.codec, &recipe.options, Some(chunk), &header)?;
    if !settings.starts_with(&plan.fingerprint()) {
        return Err(Error::input(format!(
            "{}: its settings ({settings}) are not those its codec and options make here ({}): made by another version of fractile?",
            first.display(),
            plan.fingerprint()
        )));
    }
    let encode_level = plan.level_encoder(recipe.quality)?;
    super::assembly::assemble(parts, output, &*encode_level, progress)
}
