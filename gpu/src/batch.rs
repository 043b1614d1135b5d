//! Small grids of concurrent requests decoded together: one submission, one read-back and one
//! wait for several grids (issue 32: uncached tiles).
//!
//! A tile's kernel takes microseconds on a GPU, its round trip (buffers, a submission, the
//! fence, the mapping, the waiting thread's wake-up) a fraction of a millisecond, paid by each
//! request. Here requests queue their grid; the first to find no round being gathered leads
//! one: it takes the queue (its own grid and any others waiting, up to [`ROUND_POINTS`]),
//! records a dispatch for each into one command buffer, copies every result into one read-back
//! buffer, submits once, hands the lead to the first grid that arrived meanwhile, then waits
//! once and gives each grid of its round its values. A lone request is a round of one and
//! waits for nobody.
//!
//! The lead passes at submission, not at completion, so that rounds overlap on the device:
//! on lavapipe (`cargo bench -p fractile-gpu --bench gpu -- host`, 16 threads), passing it at
//! completion made rounds of 8 grids, but 256 x 256 grids took 9.2 ms each against 6.2 ms
//! unbatched (the device idled while the next round was recorded); at submission rounds hold
//! 5.5 grids, 256 x 256 grids take 6.8-7.0 ms, and a 1-point grid costs 135-143 us of CPU
//! against 220 unbatched (129 at completion).
//!
//! Each grid's dispatch is the one [`Gpu::grid_values`] records for it alone (same kernel,
//! same parameters), so answers are bit for bit those of an unbatched dispatch.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, mpsc};

use crate::{Dispatch, Gpu, GpuError, GpuOperator, GridValues, Params, Read, map_read};

/// Largest grid sent through rounds: a 512-pixel tile with a margin and filtering to spare.
pub(crate) const GRID_POINTS: usize = 1 << 19;

/// Most points in one round (8 MiB of values): the rest wait for the next.
const ROUND_POINTS: usize = 1 << 21;

/// The queue of grids and who leads.
#[derive(Default)]
pub(crate) struct Batcher {
    queue: Mutex<Queue>,
    rounds: AtomicU64,
    grids: AtomicU64,
}

#[derive(Default)]
struct Queue {
    waiting: VecDeque<Item>,
    /// A round is under way, or its lead was handed to the first waiting grid.
    leading: bool,
}

/// One grid: its operator, its dispatch's uniforms and its axes.
struct Item {
    op: GpuOperator,
    params: Params,
    axes: Vec<f32>,
    reply: mpsc::Sender<Reply>,
}

/// What a waiting grid hears.
enum Reply {
    /// Lead the next round (this grid is in it).
    Lead,
    /// Its answer.
    Done(Result<GridValues, String>),
}

impl Batcher {
    fn queue(&self) -> std::sync::MutexGuard<'_, Queue> {
        // The queue is left whole by every panic point (pushes and pops): poison is moot.
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Rounds run and grids decoded in them, since the device was opened.
    pub(crate) fn stats(&self) -> (u64, u64) {
        (
            self.rounds.load(Ordering::Relaxed),
            self.grids.load(Ordering::Relaxed),
        )
    }
}

/// Hands the lead on when a round ends, panicking or not: to the first grid waiting, or to
/// nobody.
struct PassLead<'a>(&'a Batcher);

impl Drop for PassLead<'_> {
    fn drop(&mut self) {
        let mut q = self.0.queue();
        // A grid whose thread is gone cannot lead: drop it and ask the next.
        while let Some(next) = q.waiting.front() {
            if next.reply.send(Reply::Lead).is_ok() {
                return;
            }
            q.waiting.pop_front();
        }
        q.leading = false;
    }
}

impl Gpu {
    /// Decodes one grid (`params.count` points, at most [`GRID_POINTS`]) in the next round.
    pub(crate) fn grid_values_in_round(
        &self,
        op: &GpuOperator,
        params: Params,
        axes: Vec<f32>,
    ) -> Result<GridValues, GpuError> {
        let (reply, answer) = mpsc::channel();
        let mut lead = {
            let mut q = self.batcher.queue();
            q.waiting.push_back(Item {
                op: op.clone(),
                params,
                axes,
                reply,
            });
            !std::mem::replace(&mut q.leading, true)
        };
        loop {
            // The lead comes to a grid still queued, which is first in line: the round it
            // leads holds it.
            if std::mem::take(&mut lead) {
                self.round();
            }
            match answer.recv() {
                Ok(Reply::Done(r)) => return r.map_err(GpuError::Readback),
                Ok(Reply::Lead) => lead = true,
                Err(_) => return Err(GpuError::Readback("a round of grids was lost".into())),
            }
        }
    }

    /// Leads one round: takes the queue's first grids, decodes them together, answers each.
    fn round(&self) {
        let pass = PassLead(&self.batcher);
        let items: Vec<Item> = {
            let mut q = self.batcher.queue();
            let mut points = 0;
            let mut items = Vec::new();
            while let Some(item) = q.waiting.front() {
                points += item.params.count as usize;
                if !items.is_empty() && points > ROUND_POINTS {
                    break;
                }
                items.extend(q.waiting.pop_front());
            }
            items
        };
        self.batcher.rounds.fetch_add(1, Ordering::Relaxed);
        self.batcher
            .grids
            .fetch_add(items.len() as u64, Ordering::Relaxed);
        match self.decode_round(&items, pass) {
            Ok(answers) => {
                for (item, a) in items.iter().zip(answers) {
                    let _ = item.reply.send(Reply::Done(Ok(a)));
                }
            }
            Err(e) => {
                for item in &items {
                    let _ = item.reply.send(Reply::Done(Err(e.to_string())));
                }
            }
        }
    }

    /// One submission and one read-back for `items`.
    fn decode_round(
        &self,
        items: &[Item],
        pass: PassLead<'_>,
    ) -> Result<Vec<GridValues>, GpuError> {
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("decode2d round"),
            });
        let recorded: Vec<_> = items
            .iter()
            .map(|it| {
                self.record(
                    &mut encoder,
                    Dispatch {
                        pipeline: self.kernel2d(&it.op),
                        op: &it.op,
                        count: it.params.count as usize,
                        uniform: &|row| bytemuck::bytes_of(&Params { row, ..it.params }).to_vec(),
                        points: bytemuck::cast_slice(&it.axes),
                        read: Read::Values,
                    },
                )
            })
            .collect();
        // Each grid's values then its summary's two words, one after another (all multiples of
        // four bytes, as copies need).
        let offsets: Vec<u64> = recorded
            .iter()
            .scan(0, |at, r| {
                let o = *at;
                *at += r.readback_bytes();
                Some(o)
            })
            .collect();
        let size = recorded.iter().map(|r| r.readback_bytes()).sum();
        let readback = self.readback(size);
        for (r, &o) in recorded.iter().zip(&offsets) {
            r.copy_to(&mut encoder, &readback, o);
        }
        self.queue.submit([encoder.finish()]);
        let mapped = map_read(&readback);
        drop(pass);
        self.wait_mapped(&mapped)?;
        let view = readback
            .slice(..)
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let answers = recorded
            .iter()
            .zip(offsets)
            .map(|(r, o)| {
                let (o, n) = (o as usize, r.values_bytes as usize);
                let word = |k: usize| {
                    u32::from_le_bytes(view[o + n + 4 * k..o + n + 4 * k + 4].try_into().unwrap())
                };
                let bound = f32::from_bits(word(0));
                GridValues {
                    values: bytemuck::cast_slice(&view[o..o + n]).to_vec(),
                    // As `grid_values` reduces chunks: NaN (a chain whose contrast product is
                    // NaN) wins.
                    error_bound: if bound.is_nan() {
                        bound
                    } else {
                        bound.max(0.0)
                    },
                    iterations: word(1),
                }
            })
            .collect();
        drop(view);
        readback.unmap();
        Ok(answers)
    }
}
