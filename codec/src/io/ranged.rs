//! GeoTIFFs read by range from where they lie (an object in a bucket, a file on a web server:
//! any [`ChunkSource`]), so that what crosses the network is a cloud-optimized GeoTIFF's
//! header and the tiles a band of rows crosses, and nothing else (issue 78).
//!
//! `tiff` reads through `Read + Seek`; [`RangeReader`] gives it that over a [`RangedFile`],
//! which keeps the small blocks the header was read from (a band opens a decoder again, and
//! reads the header again from them) and holds the bytes of the band's tiles, fetched ahead
//! in as few requests as their layout allows ([`RangedFile::fetch_ahead`]). Written here
//! because no crate offers a blocking `Read + Seek` over ranged reads with that prefetch.

use std::io::{Read, Seek, SeekFrom};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use crate::io::layout::ChunkSource;

/// The bytes a read that misses fetches: a header's IFD and its tag arrays lie together in a
/// COG (GDAL writes them first), so a few blocks hold them.
const BLOCK: u64 = 4096;

/// Header blocks kept at most (256 KiB): a file read strip by strip without a prefetch would
/// otherwise keep every block it read.
const KEPT: usize = 64;

/// Two chunks' byte spans this close are fetched in one request (the gap fetched too): a
/// request costs more than a few KiB on any network.
const GAP: u64 = 16 * 1024;

/// How many bytes of chunks the files of one encode keep once decoded, all together: an
/// encode reads its rows more than once (the rate's sample of chunks, then the chunks), and
/// a chunk row kept is one not fetched again. The first bytes kept stay (no eviction): the
/// budget bounds memory whatever the number of inputs; past it, bytes are fetched again.
pub struct KeptBudget {
    most: u64,
    used: AtomicU64,
}

impl KeptBudget {
    /// A budget of `most` bytes.
    pub fn new(most: u64) -> Arc<KeptBudget> {
        Arc::new(KeptBudget {
            most,
            used: AtomicU64::new(0),
        })
    }

    /// Takes `n` bytes of the budget if they fit.
    fn take(&self, n: u64) -> bool {
        self.used
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |u| {
                (u + n <= self.most).then_some(u + n)
            })
            .is_ok()
    }

    /// Bytes kept now.
    pub fn used(&self) -> u64 {
        self.used.load(Ordering::Relaxed)
    }
}

/// The most bytes one band's chunks may ask to fetch ahead: a file whose byte counts lie (or a
/// band of tiles larger than any real DEM's) is refused before anything is allocated.
const MOST_AHEAD: u64 = 512 << 20;

/// A file read by range, with what it has fetched so far counted.
pub struct RangedFile {
    source: Box<dyn ChunkSource>,
    /// Blocks read on a miss (the header's), oldest first.
    kept: Mutex<Vec<(u64, Arc<[u8]>)>>,
    /// Spans fetched ahead for the band in progress.
    ahead: Mutex<Vec<(u64, Arc<[u8]>)>>,
    /// Spans fetched ahead and kept once decoded, within `budget`.
    decoded: Mutex<Vec<(u64, Arc<[u8]>)>>,
    budget: Arc<KeptBudget>,
    fetched: AtomicU64,
    requests: AtomicU64,
}

impl RangedFile {
    /// `source` read by range, keeping nothing once decoded.
    pub fn new(source: Box<dyn ChunkSource>) -> RangedFile {
        RangedFile::with_budget(source, KeptBudget::new(0))
    }

    /// `source` read by range, keeping decoded chunks' bytes within `budget` (shared by the
    /// files of one encode).
    pub fn with_budget(source: Box<dyn ChunkSource>, budget: Arc<KeptBudget>) -> RangedFile {
        RangedFile {
            source,
            kept: Mutex::new(Vec::new()),
            ahead: Mutex::new(Vec::new()),
            decoded: Mutex::new(Vec::new()),
            budget,
            fetched: AtomicU64::new(0),
            requests: AtomicU64::new(0),
        }
    }

    /// What of `[offset, offset + len)` is not held yet: the span less the start that blocks
    /// or spans already held cover (a small file's chunks lie in its header's block, a chunk
    /// row read before in what was kept once decoded).
    fn missing(&self, mut offset: u64, len: u64) -> (u64, u64) {
        let end = offset + len;
        let (kept, decoded) = (lock(&self.kept), lock(&self.decoded));
        while offset < end {
            let Some(reach) = kept
                .iter()
                .chain(decoded.iter())
                .filter(|(s, b)| offset >= *s && offset < *s + b.len() as u64)
                .map(|(s, b)| *s + b.len() as u64)
                .max()
            else {
                break;
            };
            offset = reach.min(end);
        }
        (offset, end - offset)
    }

    /// Where the bytes are, for messages.
    pub fn describe(&self) -> String {
        self.source.describe()
    }

    /// Bytes fetched so far, and in how many requests.
    pub fn fetched(&self) -> (u64, u64) {
        (
            self.fetched.load(Ordering::Relaxed),
            self.requests.load(Ordering::Relaxed),
        )
    }

    fn fetch(&self, offset: u64, len: usize) -> std::io::Result<Arc<[u8]>> {
        let bytes = self.source.read(offset, len)?;
        self.fetched
            .fetch_add(bytes.len() as u64, Ordering::Relaxed);
        self.requests.fetch_add(1, Ordering::Relaxed);
        Ok(bytes.into())
    }

    /// Fetches the byte spans `(offset, length)` (a band's chunks) ahead of the decoder's
    /// reads, spans closer than 16 KiB in one request; replaces what was fetched ahead before.
    pub fn fetch_ahead(&self, spans: &[(u64, u64)]) -> std::io::Result<()> {
        let mut spans: Vec<(u64, u64)> = spans.iter().copied().filter(|s| s.1 > 0).collect();
        spans.sort_unstable();
        let mut merged: Vec<(u64, u64)> = Vec::new();
        for (offset, len) in spans {
            match merged.last_mut() {
                Some((o, l)) if offset <= *o + *l + GAP => *l = (*l).max(offset + len - *o),
                _ => merged.push((offset, len)),
            }
        }
        let total: u64 = merged.iter().map(|s| s.1).sum();
        if total > MOST_AHEAD {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("{total} bytes of chunks in one band (at most {MOST_AHEAD} are read)"),
            ));
        }
        let mut ahead = Vec::with_capacity(merged.len());
        for (offset, len) in merged {
            let len = len.min(self.source.len().saturating_sub(offset));
            let (offset, len) = self.missing(offset, len);
            if len > 0 {
                ahead.push((offset, self.fetch(offset, len as usize)?));
            }
        }
        *lock(&self.ahead) = ahead;
        Ok(())
    }

    /// The band is decoded: what was fetched ahead is kept while the budget allows, else
    /// dropped.
    pub fn release(&self) {
        let ahead = std::mem::take(&mut *lock(&self.ahead));
        let mut decoded = lock(&self.decoded);
        for (offset, bytes) in ahead {
            if self.budget.take(bytes.len() as u64) {
                decoded.push((offset, bytes));
            }
        }
    }

    /// Bytes from `pos` into `buf`: from a span fetched ahead, a kept block, or a new block.
    fn read_at(&self, pos: u64, buf: &mut [u8]) -> std::io::Result<usize> {
        let len = self.source.len();
        if pos >= len || buf.is_empty() {
            return Ok(0);
        }
        let copy = |start: u64, bytes: &[u8], buf: &mut [u8]| {
            let from = (pos - start) as usize;
            let n = buf.len().min(bytes.len() - from);
            buf[..n].copy_from_slice(&bytes[from..from + n]);
            n
        };
        let within =
            |start: u64, bytes: &Arc<[u8]>| pos >= start && pos < start + bytes.len() as u64;
        if let Some((s, b)) = lock(&self.ahead).iter().find(|(s, b)| within(*s, b)) {
            return Ok(copy(*s, b, buf));
        }
        if let Some((s, b)) = lock(&self.decoded).iter().find(|(s, b)| within(*s, b)) {
            return Ok(copy(*s, b, buf));
        }
        let mut kept = lock(&self.kept);
        if let Some((s, b)) = kept.iter().find(|(s, b)| within(*s, b)) {
            return Ok(copy(*s, b, buf));
        }
        let start = pos - pos % BLOCK;
        let want = (pos + buf.len() as u64).next_multiple_of(BLOCK).min(len) - start;
        let block = self.fetch(start, want as usize)?;
        let n = copy(start, &block, buf);
        if kept.len() == KEPT {
            kept.remove(0);
        }
        kept.push((start, block));
        Ok(n)
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A reader that panicked mid-copy leaves whole blocks: the data is still good.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// `Read + Seek` over a [`RangedFile`], for `tiff`'s decoder.
pub struct RangeReader {
    file: Arc<RangedFile>,
    pos: u64,
}

impl RangeReader {
    /// A reader at the start of `file`.
    pub fn new(file: Arc<RangedFile>) -> RangeReader {
        RangeReader { file, pos: 0 }
    }
}

impl Read for RangeReader {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.file.read_at(self.pos, buf)?;
        self.pos += n as u64;
        Ok(n)
    }
}

impl Seek for RangeReader {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        let len = self.file.source.len();
        let pos = match to {
            SeekFrom::Start(p) => Some(p),
            SeekFrom::End(d) => len.checked_add_signed(d),
            SeekFrom::Current(d) => self.pos.checked_add_signed(d),
        };
        self.pos = pos.ok_or_else(|| {
            std::io::Error::new(std::io::ErrorKind::InvalidInput, "a seek before the start")
        })?;
        Ok(self.pos)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::layout::InMemory;

    /// Reads through the blocks and the spans fetched ahead give the file's bytes, wherever
    /// they start and end, and spans fetched ahead are fetched once, merged across small gaps.
    #[test]
    fn reads_are_the_files_bytes_and_spans_are_fetched_once() {
        let bytes: Vec<u8> = (0..100_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let file = Arc::new(RangedFile::new(Box::new(InMemory(bytes.clone().into()))));
        let mut r = RangeReader::new(file.clone());
        for (at, n) in [(0u64, 10usize), (4090, 20), (99_990, 50), (50_000, 9000)] {
            r.seek(SeekFrom::Start(at)).unwrap();
            let mut buf = vec![0u8; n];
            let mut got = 0;
            while got < n {
                let k = r.read(&mut buf[got..]).unwrap();
                if k == 0 {
                    break;
                }
                got += k;
            }
            let end = (at as usize + n).min(bytes.len());
            assert_eq!(&buf[..got], &bytes[at as usize..end], "at {at}");
        }
        let (before, _) = file.fetched();
        file.fetch_ahead(&[(20_000, 1000), (22_000, 500), (80_000, 300)])
            .unwrap();
        let (after, requests) = file.fetched();
        // 20,000..22,500 in one request (a gap under GAP), 80,000..80,300 in another.
        assert_eq!(after - before, 2500 + 300);
        r.seek(SeekFrom::Start(21_500)).unwrap();
        let mut buf = vec![0u8; 1000];
        r.read_exact(&mut buf).unwrap();
        assert_eq!(&buf[..], &bytes[21_500..22_500]);
        assert_eq!(
            file.fetched(),
            (after, requests),
            "read from what was fetched ahead"
        );
        // Without a budget nothing is kept once decoded: the same spans are fetched again.
        file.release();
        file.fetch_ahead(&[(20_000, 1000)]).unwrap();
        assert_eq!(file.fetched().0, after + 1000);
        // With one, a span read again is not fetched again, until the budget is spent.
        let budget = KeptBudget::new(1500);
        let file = RangedFile::with_budget(Box::new(InMemory(bytes.into())), budget.clone());
        for _ in 0..3 {
            file.fetch_ahead(&[(30_000, 1000)]).unwrap();
            file.release();
        }
        assert_eq!(file.fetched(), (1000, 1));
        file.fetch_ahead(&[(60_000, 1000)]).unwrap();
        file.release();
        file.fetch_ahead(&[(60_000, 1000)]).unwrap();
        assert_eq!(file.fetched(), (3000, 3), "over the budget: fetched again");
        assert_eq!(budget.used(), 1000);
        // Byte counts no real band has are refused before anything is fetched.
        let (fetched, _) = file.fetched();
        assert!(file.fetch_ahead(&[(0, MOST_AHEAD + 1)]).is_err());
        assert_eq!(file.fetched().0, fetched);
    }
}
