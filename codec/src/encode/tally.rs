//! Chunks handed over by the pyramid (or a part's band) as their rows arrive, coded a batch
//! at a time on every core, each file spilled as it is coded ([`Tally`]).

use std::sync::atomic::{AtomicU64, Ordering};

use rayon::prelude::*;

use super::spill::Spill;
use super::summary::{ChunkRecord, Coded};
use super::views::{EncodeLevel, view_maps};
use crate::Error;
use crate::io::chunked::ChunkEntry;
use crate::io::raster::Raster;

/// Counts chunks coded: `progress(done, total)`.
pub type Progress<'a> = dyn Fn(u64, u64) + Sync + 'a;

/// Which chunks a process codes, by level and index: every coded one in an encode whole; a
/// band of level 0's, or the overviews, in a split one.
pub(super) type Wants<'a> = dyn Fn(usize, u32) -> bool + Sync + 'a;

/// Chunks waiting to be coded (a batch of a chunk a core), and the records of those coded.
pub(super) struct Tally<'w, 's> {
    pub(super) records: Vec<Vec<Option<(ChunkRecord, u64)>>>,
    wants: &'w Wants<'w>,
    queue: Vec<(usize, u32, Raster)>,
    work: (&'w EncodeLevel<'w>, &'w Progress<'w>),
    spill: &'s mut Spill,
    done: AtomicU64,
    total: u64,
    /// Overview levels 1 to `views` are views of the source chunks, not coded.
    views: usize,
}

impl<'w, 's> Tally<'w, 's> {
    /// The tally of a table of `entries` (every level's chunks) with `views` view levels, of
    /// the chunks `wants` names (never a view's: those are not coded).
    pub(super) fn new(
        (entries, views): (&[Vec<ChunkEntry>], usize),
        wants: &'w Wants<'w>,
        work: (&'w EncodeLevel<'w>, &'w Progress<'w>),
        spill: &'s mut Spill,
    ) -> Self {
        let view = |l: usize| l >= 1 && l <= views;
        let total = (0..entries.len())
            .filter(|&l| !view(l))
            .map(|l| {
                (0..entries[l].len() as u32)
                    .filter(|&i| wants(l, i))
                    .count() as u64
            })
            .sum();
        (work.1)(0, total);
        Tally {
            records: entries.iter().map(|l| vec![None; l.len()]).collect(),
            wants,
            queue: Vec::new(),
            work,
            spill,
            done: AtomicU64::new(0),
            total,
            views,
        }
    }

    /// Queues chunk `i` of level `l` if this process codes it; codes the queue once it holds
    /// a chunk a core.
    pub(super) fn push(&mut self, l: usize, i: u32, part: Raster) -> Result<(), Error> {
        if !(self.wants)(l, i) || (l >= 1 && l <= self.views) {
            return Ok(());
        }
        self.queue.push((l, i, part));
        if self.queue.len() >= rayon::current_num_threads().max(1) {
            self.flush()?;
        }
        Ok(())
    }

    /// Codes every queued chunk on all cores and spills each.
    pub(super) fn flush(&mut self) -> Result<(), Error> {
        let jobs = std::mem::take(&mut self.queue);
        let (encode_one, progress) = self.work;
        let (done, total, views) = (&self.done, self.total, self.views);
        // One chunk a task: a core waiting inside a chunk's own parallel work would otherwise
        // steal further chunks, and hold more of them in memory than there are cores.
        let coded: Vec<_> = jobs
            .into_par_iter()
            .with_max_len(1)
            .map(|(l, i, part)| {
                let any_valid = part.valid.as_ref().is_none_or(|v| v.contains(&true));
                let enc = if any_valid {
                    let enc = encode_one(l, &part).map_err(|e| match e {
                        Error::Input { .. } => e.within(format_args!("chunk {i} of level {l}")),
                        e => e,
                    })?;
                    let maps = if l == 0 && views > 0 {
                        view_maps(&enc, &part, views)
                            .map_err(|e| Error::input(format!("the views of chunk {i}: {e}")))?
                    } else {
                        Vec::new()
                    };
                    Some(Coded::of(enc, l, i, maps))
                } else {
                    None
                };
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                Ok((l, i, enc))
            })
            .collect::<Result<_, Error>>()?;
        for (l, i, c) in coded {
            if let Some(c) = c {
                let at = self
                    .spill
                    .push(&c.bytes)
                    .map_err(|e| Error::output(format!("spilling a chunk: {e}")))?;
                self.records[l][i as usize] = Some((c.record, at));
            }
        }
        Ok(())
    }
}
