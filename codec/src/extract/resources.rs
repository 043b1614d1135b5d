//! What an answer may use besides the calling thread ([`Resources`]): a device for its chains,
//! the coarse decodes kept from earlier answers ([`CoarseGrids`]), and a flag that says the
//! asker gave up. All of them are data or a device; the caller hands the codec no code of its
//! own (the server's coarse cache, its keys and the grids it derives by block means were the
//! server's; they are the codec's now, and the server holds one `CoarseGrids`).

use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use super::ChainDevice;
use crate::core::decode::{DiscreteReport, Grid};
use crate::io::asset::Asset;
use crate::io::cache::{KeyedMap, get_or_make, keyed_map};

/// What [`Asset::sample_with`] and [`Asset::answer`] may use besides the calling thread.
#[derive(Clone, Copy)]
pub struct Resources<'a> {
    /// A device that decodes the continuous chains of a plane (a GPU), or `None`: the CPU.
    /// The device is the one thing the codec calls out to: it lives in a crate the codec does
    /// not depend on (the browser's and the CLI's builds have none), and whoever holds it
    /// decides when its waits may give the core back.
    pub device: Option<&'a ChainDevice<'a>>,
    /// Coarse decodes kept between answers, and the key of this asset among them (its caller
    /// knows the asset by a name and a checksum; any `u64` that changes with the file). `None`:
    /// a coarse answer decodes its grid itself.
    pub coarse: Option<(&'a CoarseGrids, u64)>,
    /// Set by the asker when it gives up (a server's request that timed out, or whose client
    /// left): the work stops between two bands instead of running on.
    pub given_up: Option<&'a AtomicBool>,
}

impl Resources<'static> {
    /// The CPU alone, nothing kept, never given up.
    pub const CPU: Resources<'static> = Resources {
        device: None,
        coarse: None,
        given_up: None,
    };
}

impl Resources<'_> {
    /// Whether the asker has given up.
    pub(crate) fn asker_gave_up(&self) -> bool {
        self.given_up.is_some_and(|g| g.load(Ordering::Relaxed))
    }
}

/// The planes of an asset decoded discretely at one size, with their reports.
type Planes = Vec<(Grid, DiscreteReport)>;

/// `(asset key, width, height, iterations, tolerance bits)`.
type CoarseKey = (u64, usize, usize, u32, u32);

/// Discrete decodes of whole assets at the sizes of coarse zoom levels, bounded in bytes: every
/// tile of a zoom coarser than the source samples the same grid, so it is decoded once
/// (concurrent answers wait for it), and a grid 2, 4 or 8 times finer on either axis, where
/// one is kept, gives it by block means in a pass instead of a decode.
pub struct CoarseGrids {
    map: KeyedMap<CoarseKey, Planes>,
    /// Hits, derived, misses.
    counts: [AtomicU64; 3],
}

/// How often [`CoarseGrids`] answered from a kept grid, from a finer one, or decoded.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CoarseCounts {
    /// Answered by a kept grid.
    pub hits: u64,
    /// Answered by block means of a finer kept grid.
    pub derived: u64,
    /// Decoded.
    pub misses: u64,
}

impl CoarseGrids {
    /// Grids of at most `bytes` in all (4 bytes a value).
    pub fn new(bytes: u64) -> CoarseGrids {
        CoarseGrids {
            map: keyed_map(bytes, |planes: &Planes| {
                planes.iter().map(|(g, _)| g.values.len() as u64 * 4).sum()
            }),
            counts: Default::default(),
        }
    }

    /// The counts so far.
    pub fn counts(&self) -> CoarseCounts {
        let [h, d, m] = &self.counts;
        CoarseCounts {
            hits: h.load(Ordering::Relaxed),
            derived: d.load(Ordering::Relaxed),
            misses: m.load(Ordering::Relaxed),
        }
    }

    /// How many grids are kept (after moka's pending evictions).
    pub fn len(&self) -> u64 {
        #[cfg(feature = "moka")]
        {
            self.map.run_pending_tasks();
            self.map.entry_count()
        }
        #[cfg(not(feature = "moka"))]
        {
            self.map.len() as u64
        }
    }

    /// How many grids of the asset known as `key` are kept (moka's map alone lists its keys).
    #[cfg(feature = "moka")]
    pub fn len_of(&self, key: u64) -> u64 {
        self.map.run_pending_tasks();
        self.map.iter().filter(|(k, _)| k.0 == key).count() as u64
    }

    /// Whether none is kept.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// [`Asset::discrete_planes`] of `asset` (known as `key`) at `(width, height, iterations,
    /// tolerance)`, kept.
    pub(crate) fn planes(
        &self,
        (asset, key): (&Asset, u64),
        (width, height): (usize, usize),
        (iterations, tolerance): (u32, f32),
    ) -> Arc<Planes> {
        let at = |w, h| (key, w, h, iterations, tolerance.to_bits());
        // 0: hit, 1: derived, 2: miss.
        let result = Cell::new(0);
        let planes = get_or_make(&self.map, at(width, height), || {
            let finer = (0..=3)
                .flat_map(|i| (0..=3).map(move |j| (i, j)))
                .filter(|&ij| ij != (0, 0))
                .find_map(|(i, j)| Some(((i, j), self.map.get(&at(width << i, height << j))?)));
            if let Some(((i, j), fine)) = finer {
                let shrunk: Option<Planes> = fine
                    .iter()
                    .map(|(g, r)| Some((g.shrink(1 << i, 1 << j)?, *r)))
                    .collect();
                if let Some(planes) = shrunk {
                    result.set(1);
                    return Arc::new(planes);
                }
            }
            result.set(2);
            Arc::new(asset.discrete_planes(width, height, iterations, tolerance))
        });
        self.counts[result.get()].fetch_add(1, Ordering::Relaxed);
        planes
    }
}
