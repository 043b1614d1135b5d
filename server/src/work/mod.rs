//! Where decoding runs, and what it may cost at once.
//!
//! Two lanes keep cheap requests responsive while heavy ones run:
//! - **light** work (a tile, a batch of points, anything estimated under [`LIGHT_BYTES`]) takes
//!   one of a slot per core and runs on the blocking pool and rayon's global pool;
//! - **heavy** work (large regions, meshes, uploads being validated) takes its estimated bytes
//!   from a weighted budget (`max_decode_mib`) and runs on a rayon pool of its own, whose
//!   threads run at a lower priority (nice 10), so a burst of heavy requests neither starves
//!   the light lane's threads of their queue nor of the CPU.
//!
//! Heavy work is admitted first come first served by what the machine can finish, not only
//! by memory: at most [`Lanes::heavy_runs`] decode at once (half the cores, at least one; each
//! decode is parallel in the heavy pool), and a request that finds neither room in the budget
//! nor a free run within [`HEAVY_QUEUE_WAIT`] is refused at once with 503 `busy` and a
//! `Retry-After` from the measured length of heavy decodes. Before, every heavy request started
//! and they shared the cores: 8 regions of 2048^2 that each fit the budget all ran past the
//! 30 s request timeout and none was served. A streamed body holds its memory until its
//! reader has it, but not its run: its decode is done.
//!
//! The permits travel with the work, not with the request: a request that timed out releases
//! its budget only when its work has stopped, which it does at the next band (the work asks
//! [`Cancel::is_set`], which turns true when the request's future is dropped).
//!
//! A light slot stands for a core. Work that waits on another device (a GPU decode) lends its
//! slot for the wait ([`Cancel::off_core`]) and queues for one again to go on (to encode its
//! PNG): a slot held through a GPU round trip left the cores idle while every slot waited on
//! the device (on an H100, 16 slots each held 1.4 ms of GPU wait and 1.3 ms of PNG capped GPU
//! tiles at about 16 / 2.75 ms, 5,800 a second; measured 5,150-5,300). Work coming back from
//! its wait takes the next free slot before new requests do (`work/slots.rs`), so under overload it
//! does not queue twice.

mod slots;

use fractile_proto::ErrorCode;
use std::io::Write;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::response::Response;
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, oneshot};

use slots::{SlotPermit, Slots};

use crate::error::AppError;

/// Work estimated under this many bytes runs in the light lane.
pub(crate) const LIGHT_BYTES: u64 = 24 << 20;

/// How long heavy work may queue for room (memory and a run) before it is refused with 503
/// and `Retry-After`: a client learns at once that it must come back, instead of holding a
/// connection until the request timeout.
pub(crate) const HEAVY_QUEUE_WAIT: Duration = Duration::from_millis(1500);

/// How long a streamed body may wait for its reader to take a chunk before it is abandoned
/// (a reader that stalls must not hold a heavy budget for ever).
pub(crate) const STALLED_READER: Duration = Duration::from_secs(30);

/// Chunks of a streamed body in flight between the writer and the connection.
const STREAM_CHUNKS: usize = 4;
/// Size of a streamed body's chunks.
const CHUNK_BYTES: usize = 256 << 10;

/// The decoding lanes of a server.
pub struct Lanes {
    /// Light slots: one per core.
    light: Arc<Slots>,
    /// Heavy budget, in MiB.
    heavy: Arc<Semaphore>,
    heavy_mib: u32,
    /// Heavy decodes running at once (first come, first served).
    heavy_runs: Arc<Slots>,
    heavy_run_count: usize,
    /// A moving average of heavy decodes' wall time, in milliseconds (what `Retry-After` says).
    heavy_millis: Arc<std::sync::atomic::AtomicU64>,
    /// Threads of heavy work.
    pool: Arc<rayon::ThreadPool>,
}

impl Lanes {
    /// Lanes with `cores` light slots and a heavy budget of `heavy_mib` MiB.
    #[expect(
        clippy::expect_used,
        reason = "a thread pool that cannot start at launch leaves nothing to serve with"
    )]
    pub fn new(cores: usize, heavy_mib: u32) -> Lanes {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(cores.max(1))
            .thread_name(|i| format!("fractile-heavy-{i}"))
            .start_handler(|_| lower_priority())
            .build()
            .expect("a rayon pool for heavy decodes");
        let heavy_mib = heavy_mib.clamp(1, Semaphore::MAX_PERMITS as u32);
        let heavy_run_count = (cores / 2).max(1);
        Lanes {
            light: Slots::new(cores.max(1)),
            heavy: Arc::new(Semaphore::new(heavy_mib as usize)),
            heavy_mib,
            heavy_runs: Slots::new(heavy_run_count),
            heavy_run_count,
            heavy_millis: Arc::new(std::sync::atomic::AtomicU64::new(5_000)),
            pool: Arc::new(pool),
        }
    }

    /// Heavy decodes that may run at once.
    pub fn heavy_runs(&self) -> usize {
        self.heavy_run_count
    }

    /// The refusal of heavy work that found no room within [`HEAVY_QUEUE_WAIT`]: 503 `busy`,
    /// retry after about one heavy decode's time.
    fn busy(&self, mib: u64) -> AppError {
        let secs = self
            .heavy_millis
            .load(Ordering::Relaxed)
            .div_ceil(1000)
            .clamp(1, 120);
        metrics::counter!("fractile_heavy_refused_total").increment(1);
        AppError {
            status: axum::http::StatusCode::SERVICE_UNAVAILABLE,
            code: ErrorCode::Busy,
            detail: format!(
                "the server is busy with large requests (this one needs about {mib} MiB); \
                 retry in {secs} s or ask for fewer pixels"
            ),
            retry_after: Some(secs as u32),
        }
    }

    /// The heavy budget in MiB.
    pub fn heavy_mib(&self) -> u32 {
        self.heavy_mib
    }

    /// Whether a light slot is free now (readiness).
    pub fn light_free(&self) -> bool {
        self.light.free() > 0
    }

    /// Takes the lane that work of `bytes` belongs to (waiting for room), or refuses work
    /// larger than the whole heavy budget.
    async fn admit(&self, bytes: u64) -> Result<Admitted, AppError> {
        if bytes <= LIGHT_BYTES {
            let slot = self.light.arrive().await;
            return Ok(Admitted {
                _budget: None,
                slot: Some(slot),
                light: Some(self.light.clone()),
                run: None,
                pool: None,
            });
        }
        let mib = bytes.div_ceil(1 << 20);
        if mib > u64::from(self.heavy_mib) {
            return Err(AppError {
                status: axum::http::StatusCode::PAYLOAD_TOO_LARGE,
                code: ErrorCode::TooExpensive,
                detail: format!(
                    "this request needs about {mib} MiB to decode, over the server's max_decode_mib of {}: ask for fewer pixels",
                    self.heavy_mib
                ),
                retry_after: None,
            });
        }
        let queued = std::time::Instant::now();
        metrics::gauge!("fractile_heavy_queued").increment(1.0);
        let room = tokio::time::timeout(HEAVY_QUEUE_WAIT, async {
            let budget = self.heavy.clone().acquire_many_owned(mib as u32).await;
            let run = self.heavy_runs.arrive().await;
            (budget, run)
        })
        .await;
        metrics::gauge!("fractile_heavy_queued").decrement(1.0);
        metrics::histogram!("fractile_heavy_wait_seconds").record(queued.elapsed().as_secs_f64());
        let Ok((budget, run)) = room else {
            return Err(self.busy(mib));
        };
        Ok(Admitted {
            _budget: Some(budget.map_err(closed)?),
            slot: None,
            light: None,
            run: Some(run),
            pool: Some(self.pool.clone()),
        })
    }

    /// Runs `f` in the lane of `bytes`, on the blocking pool, with a `Cancel` that turns
    /// true when this future is dropped (the request timed out or its client left).
    pub async fn run<T: Send + 'static>(
        &self,
        bytes: u64,
        f: impl FnOnce(&Cancel) -> T + Send + 'static,
    ) -> Result<T, AppError> {
        let admitted = self.admit(bytes).await?;
        let heavy = admitted.run.is_some();
        let guard = CancelOnDrop::default();
        let cancel = guard.0.clone();
        let start = std::time::Instant::now();
        let (budget, mib) = (self.heavy.clone(), self.heavy_mib);
        let out = tokio::task::spawn_blocking(move || {
            let mut admitted = admitted;
            let out = admitted.install(&cancel, f);
            drop(admitted);
            if heavy {
                crate::memory::give_back_when_idle(&budget, mib);
            }
            out
        })
        .await
        .map_err(|e| AppError::internal(format!("decoding failed: {e}")));
        metrics::histogram!("fractile_decode_seconds").record(start.elapsed().as_secs_f64());
        if heavy {
            heavy_took(&self.heavy_millis, start.elapsed());
        }
        drop(guard);
        out
    }

    /// Runs `f` in the lane of `bytes` and streams what it writes as the response body: `f`
    /// returns the response's head (content type, error bound) and a writer of the body, which
    /// runs while the client reads, with the budget held until the last byte is taken, the
    /// client leaves, or it stalls for `STALLED_READER`. Large bodies are never held whole.
    pub async fn stream<F>(&self, bytes: u64, f: F) -> Result<Response, AppError>
    where
        F: FnOnce(&Cancel) -> Result<(Head, BodyWriter), AppError> + Send + 'static,
    {
        let admitted = self.admit(bytes).await?;
        let guard = CancelOnDrop::default();
        let cancel = guard.0.clone();
        let (head_tx, head_rx) = oneshot::channel();
        let (tx, rx) = mpsc::channel::<Result<Bytes, std::io::Error>>(STREAM_CHUNKS);
        let runtime = tokio::runtime::Handle::current();
        let millis = self.heavy_millis.clone();
        let (budget, mib) = (self.heavy.clone(), self.heavy_mib);
        tokio::task::spawn_blocking(move || {
            let mut admitted = admitted;
            let start = std::time::Instant::now();
            let made = admitted.install(&cancel, f);
            // The decode is done: its run goes to the next heavy request, while its memory
            // stays held until the body is read.
            if admitted.run.take().is_some() {
                heavy_took(&millis, start.elapsed());
            }
            let writer = match made {
                Ok((head, writer)) => {
                    if head_tx.send(Ok(head)).is_err() {
                        return;
                    }
                    writer
                }
                Err(e) => {
                    let _ = head_tx.send(Err(e));
                    return;
                }
            };
            let mut out = ChannelWriter {
                tx,
                runtime,
                buf: Vec::with_capacity(CHUNK_BYTES),
            };
            if writer(&mut out).and_then(|()| out.flush()).is_err() {
                tracing::debug!("a streamed body ended early (its reader left or stalled)");
            }
            let heavy = admitted._budget.is_some();
            drop(admitted);
            if heavy {
                crate::memory::give_back_when_idle(&budget, mib);
            }
        });
        let head = head_rx
            .await
            .map_err(|_| AppError::internal("decoding failed"))??;
        // The guard lives with the body: a client that leaves mid-body cancels the writer.
        let stream = futures_util::stream::unfold((rx, guard), |(mut rx, guard)| async move {
            rx.recv().await.map(|chunk| (chunk, (rx, guard)))
        });
        let mut response = Response::new(Body::from_stream(stream));
        let h = response.headers_mut();
        h.insert(
            axum::http::header::CONTENT_TYPE,
            axum::http::HeaderValue::from_static(head.content_type),
        );
        head.bounds.write(h);
        Ok(response)
    }
}

/// The head of a streamed response.
pub struct Head {
    /// Its content type.
    pub content_type: &'static str,
    /// Its bounds (`X-Convergence-Bound`, `X-Error-Bound`).
    pub bounds: Bounds,
}

/// The bounds an answer carries in its headers.
#[derive(Clone, Copy, Debug)]
pub struct Bounds {
    /// Against the fractal's attractor (the iterations' convergence, plus a mesh's own error
    /// where there is one): `X-Convergence-Bound`, what progressive refinement stops on.
    pub attractor: f32,
    /// The asset's measured error against its source over the answer (`None` for assets
    /// without a source-error map): `X-Error-Bound` is `attractor` plus this.
    pub source: Option<f32>,
}

impl Bounds {
    /// Both bounds plus `extra` (a mesh's error against the decoded heights).
    pub fn plus(self, extra: f32) -> Bounds {
        Bounds {
            attractor: self.attractor + extra,
            ..self
        }
    }

    /// The bound against the source, where the asset has a map.
    pub fn error_bound(&self) -> Option<f32> {
        self.source.map(|s| s + self.attractor)
    }

    /// Writes `X-Convergence-Bound` and, where known, `X-Error-Bound`.
    pub fn write(&self, h: &mut axum::http::HeaderMap) {
        let number = |v: f32| axum::http::HeaderValue::from_str(&v.to_string()).ok();
        if let Some(v) = number(self.attractor) {
            h.insert("x-convergence-bound", v);
        }
        if let Some(v) = self.error_bound().and_then(number) {
            h.insert("x-error-bound", v);
        }
    }
}

/// Records a heavy decode's wall time in the moving average `millis` (weight 1/4).
fn heavy_took(millis: &std::sync::atomic::AtomicU64, took: Duration) {
    let ms = took.as_millis().min(u128::from(u32::MAX)) as u64;
    let old = millis.load(Ordering::Relaxed);
    millis.store((3 * old + ms) / 4, Ordering::Relaxed);
}

/// Writes a streamed body.
pub(crate) type BodyWriter = Box<dyn FnOnce(&mut dyn Write) -> std::io::Result<()> + Send>;

fn closed(_: tokio::sync::AcquireError) -> AppError {
    AppError::internal("the decoding lanes are closed")
}

/// A lane taken: its permit, and the pool heavy work runs in.
struct Admitted {
    /// Heavy work's MiB, held until the work is done (only its drop matters).
    _budget: Option<OwnedSemaphorePermit>,
    /// Light work's slot (`None` while lent to the work's [`Cancel`]).
    slot: Option<SlotPermit>,
    /// The light lane, for a light slot: what [`Cancel::off_core`] gives back and takes again.
    light: Option<Arc<Slots>>,
    /// Heavy work's run, held while it decodes.
    run: Option<SlotPermit>,
    pool: Option<Arc<rayon::ThreadPool>>,
}

impl Admitted {
    /// Runs `f` in the lane: a heavy pool, or with the light slot lent to `cancel` (where
    /// [`Cancel::off_core`] may give it back for a wait), taken back when `f` returns.
    fn install<T: Send>(&mut self, cancel: &Cancel, f: impl FnOnce(&Cancel) -> T + Send) -> T {
        if let Some(lane) = &self.light {
            *cancel.slot() = Some(Slot {
                lane: lane.clone(),
                permit: self.slot.take(),
            });
        }
        let out = match &self.pool {
            Some(pool) => pool.install(|| f(cancel)),
            None => f(cancel),
        };
        if let Some(slot) = cancel.slot().take() {
            self.slot = slot.permit;
        }
        out
    }
}

/// Whether the request that wanted some work has given up; and the light slot the work holds.
#[derive(Clone, Default)]
pub struct Cancel(Arc<Work>);

#[derive(Default)]
struct Work {
    given_up: AtomicBool,
    slot: std::sync::Mutex<Option<Slot>>,
}

/// A light slot held by running work, and its lane.
struct Slot {
    lane: Arc<Slots>,
    permit: Option<SlotPermit>,
}

impl Cancel {
    /// True once the request's future was dropped.
    pub fn is_set(&self) -> bool {
        self.0.given_up.load(Ordering::Relaxed)
    }

    /// The flag [`Cancel::is_set`] reads, for the codec to look at between bands of work
    /// (`fractile_codec::extract::Resources::given_up`).
    pub fn flag(&self) -> &AtomicBool {
        &self.0.given_up
    }

    /// Runs `wait`, which waits on another device (a GPU decode), with the work's light slot
    /// given back to its lane, then takes one again ahead of new requests: the cores serve
    /// other requests meanwhile. Blocks the calling thread (a blocking-pool thread). Heavy work
    /// keeps its budget (the memory stays in use); outside a lane (tests) it only runs `wait`.
    pub fn off_core<T>(&self, wait: impl FnOnce() -> T) -> T {
        // On a rayon worker the work keeps its slot: taking one back would block the worker
        // behind slot holders that may be waiting on the same pool. (Hooks run on the
        // request's own thread today; this keeps a parallel caller from deadlocking.)
        if rayon::current_thread_index().is_some() {
            return wait();
        }
        let lane = {
            let mut slot = self.slot();
            // Dropping the permit is the giving back.
            slot.as_mut()
                .and_then(|s| s.permit.take().map(|_given_back| s.lane.clone()))
        };
        let out = wait();
        if let Some(lane) = lane {
            let permit = lane.resume();
            if let Some(s) = self.slot().as_mut() {
                s.permit = Some(permit);
            }
        }
        out
    }

    fn slot(&self) -> std::sync::MutexGuard<'_, Option<Slot>> {
        // A panic elsewhere cannot leave an `Option` half-written: the lock's poison is moot.
        self.0.slot.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Sets its [`Cancel`] when dropped.
#[derive(Default)]
struct CancelOnDrop(Cancel);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        (self.0).0.given_up.store(true, Ordering::Relaxed);
    }
}

/// A `Write` that hands chunks to a response body through a bounded channel.
struct ChannelWriter {
    tx: mpsc::Sender<Result<Bytes, std::io::Error>>,
    runtime: tokio::runtime::Handle,
    buf: Vec<u8>,
}

impl ChannelWriter {
    fn send(&mut self) -> std::io::Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let chunk = Bytes::from(std::mem::replace(
            &mut self.buf,
            Vec::with_capacity(CHUNK_BYTES),
        ));
        let tx = self.tx.clone();
        self.runtime
            .block_on(async move { tx.send_timeout(Ok(chunk), STALLED_READER).await })
            .map_err(|_| std::io::Error::new(std::io::ErrorKind::BrokenPipe, "reader gone"))
    }
}

impl Write for ChannelWriter {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        self.buf.extend_from_slice(data);
        if self.buf.len() >= CHUNK_BYTES {
            self.send()?;
        }
        Ok(data.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.send()
    }
}

/// Lowers the calling thread's scheduling priority (nice 10) where the platform allows it.
fn lower_priority() {
    #[cfg(target_os = "linux")]
    // SAFETY: setpriority on the calling thread's id (Linux treats a tid as a process of one
    // thread here); it reads nothing from us but integers.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, 10);
    }
}

#[cfg(test)]
mod tests;
