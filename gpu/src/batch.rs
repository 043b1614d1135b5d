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
//! same parameters, its own ranges of the round's buffers), so answers are bit for bit those
//! of an unbatched dispatch.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, mpsc};

use wgpu::util::DeviceExt;

use crate::{Gpu, GpuError, GpuOperator, GridValues, Params, WORKGROUP, map_read};

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

/// A round's buffers, shared by its grids, and each grid's share of them.
struct Round {
    /// Every grid's values, each at its range.
    values: wgpu::Buffer,
    /// Every grid's summary (bound and steps; 16 bytes bound), one `summary_stride` apart.
    summary: wgpu::Buffer,
    summary_stride: u64,
    /// Each grid's (offset, bytes) in the axes buffer, then in `values`.
    ranges: Vec<[(u64, u64); 2]>,
    /// Each grid's workgroups.
    groups: Vec<(u32, u32)>,
    /// Each grid's bind group.
    binds: Vec<wgpu::BindGroup>,
    /// Uniforms, axes and the unused results binding: held until the round is recorded.
    _inputs: [wgpu::Buffer; 3],
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

    /// One submission and one read-back for `items`, their inputs and outputs in buffers
    /// shared by the round, each grid bound to its own ranges of them.
    ///
    /// Why shared: on an H100 a round's period grew by 0.155 ms a grid whatever its size
    /// (rounds of 4.7, 8.8 and 16.7 grids: 0.73, 1.4 and 2.6 ms), and rounds are led one at a
    /// time, so uncached tiles stopped near 6,500 a second with a third of the cores idle. A
    /// grid made five buffers of its own (and dropped them after), each an allocation under
    /// wgpu's device locks: the serial work that grew with the round. Now a round makes six buffers whatever its size, and a grid
    /// only its bind group: 5,985-6,149 -> 6,672-7,164 tiles a second at 64 clients
    /// (docs/benchmarks.md).
    fn decode_round(
        &self,
        items: &[Item],
        pass: PassLead<'_>,
    ) -> Result<Vec<GridValues>, GpuError> {
        let round = self.round_buffers(items);
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("decode2d round"),
            });
        {
            let mut compute = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("decode2d round"),
                timestamp_writes: None,
            });
            for ((it, bind), &(gx, gy)) in items.iter().zip(&round.binds).zip(&round.groups) {
                compute.set_pipeline(self.kernel2d(&it.op));
                compute.set_bind_group(0, bind, &[]);
                compute.dispatch_workgroups(gx, gy, 1);
            }
        }
        // The values, then the summaries.
        let (values_total, stride) = (round.values.size(), round.summary_stride);
        let summaries = round.summary.size();
        let readback = self.readback(values_total + summaries);
        encoder.copy_buffer_to_buffer(&round.values, 0, &readback, 0, values_total);
        encoder.copy_buffer_to_buffer(&round.summary, 0, &readback, values_total, summaries);
        self.queue.submit([encoder.finish()]);
        let mapped = map_read(&readback);
        drop(pass);
        self.wait_mapped(&mapped)?;
        let view = readback
            .slice(..)
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let answers = items
            .iter()
            .zip(&round.ranges)
            .enumerate()
            .map(|(k, (it, &[_, (o, _)]))| {
                let (o, n) = (o as usize, it.params.count as usize * 4);
                let s = (values_total + k as u64 * stride) as usize;
                let word = |w: usize| {
                    u32::from_le_bytes(view[s + 4 * w..s + 4 * w + 4].try_into().unwrap())
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

    /// The buffers of a round of `items` and each grid's bind group to its ranges of them.
    fn round_buffers(&self, items: &[Item]) -> Round {
        let dev = &self.device;
        let limits = dev.limits();
        // One alignment for every range: a uniform's and a storage binding's offset alike.
        let align = u64::from(
            limits
                .min_uniform_buffer_offset_alignment
                .max(limits.min_storage_buffer_offset_alignment),
        );
        let up = |n: u64| n.div_ceil(align) * align;
        let params_bytes = std::mem::size_of::<Params>() as u64;
        // Each grid's share of the round's buffers: (offset, bytes) of its axes and values.
        let mut at = (0, 0);
        let ranges: Vec<[(u64, u64); 2]> = items
            .iter()
            .map(|it| {
                let axes = (it.axes.len() as u64 * 4).max(16);
                let values = (u64::from(it.params.count) * 4).max(16);
                let r = [(at.0, axes), (at.1, values)];
                at = (at.0 + up(axes), at.1 + up(values));
                r
            })
            .collect();
        let (axes_total, values_total) = at;
        let n = items.len() as u64;
        let mut uniforms = vec![0u8; (n * up(params_bytes)) as usize];
        let mut axes = vec![0u8; axes_total as usize];
        let mut groups = Vec::with_capacity(items.len());
        for (k, (it, [(a_at, _), _])) in items.iter().zip(&ranges).enumerate() {
            let count = it.params.count.div_ceil(WORKGROUP);
            let gx = count.min(65_535);
            groups.push((gx, count.div_ceil(gx)));
            let p = Params {
                row: gx * WORKGROUP,
                ..it.params
            };
            let u = k * up(params_bytes) as usize;
            uniforms[u..u + params_bytes as usize].copy_from_slice(bytemuck::bytes_of(&p));
            let a = *a_at as usize;
            axes[a..a + it.axes.len() * 4].copy_from_slice(bytemuck::cast_slice(&it.axes));
        }
        let init = |label, contents: &[u8], usage| {
            dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            })
        };
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let uniform = init("round params", &uniforms, wgpu::BufferUsages::UNIFORM);
        let input = init("round points", &axes, wgpu::BufferUsages::STORAGE);
        // Zeroed: the kernel takes maxima into a grid's summary.
        let summary_stride = up(16);
        let summary = init(
            "round summaries",
            &vec![0u8; (n * summary_stride) as usize],
            storage,
        );
        let output = |label, size| {
            dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: storage,
                mapped_at_creation: false,
            })
        };
        let values = output("round values", values_total);
        // Values-only dispatches do not write the four-float results (bound as a few bytes).
        let results = output("round results", 16);
        let range = |buffer, (offset, size): (u64, u64)| {
            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer,
                offset,
                size: wgpu::BufferSize::new(size),
            })
        };
        let binds: Vec<wgpu::BindGroup> = items
            .iter()
            .zip(&ranges)
            .enumerate()
            .map(|(k, (it, &[a, v]))| {
                let k = k as u64;
                dev.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("decode2d round grid"),
                    layout: &self.layout,
                    entries: &[
                        (0, range(&uniform, (k * up(params_bytes), params_bytes))),
                        (1, it.op.lut.as_entire_binding()),
                        (2, it.op.pieces.as_entire_binding()),
                        (3, range(&input, a)),
                        (4, results.as_entire_binding()),
                        (5, range(&values, v)),
                        (6, range(&summary, (k * summary_stride, 16))),
                    ]
                    .map(|(binding, resource)| wgpu::BindGroupEntry { binding, resource }),
                })
            })
            .collect();
        Round {
            values,
            summary,
            summary_stride,
            ranges,
            groups,
            binds,
            _inputs: [uniform, input, results],
        }
    }
}
