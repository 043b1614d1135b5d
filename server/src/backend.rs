//! Where continuous decoding runs: the CPU (always there) or a GPU (`fractile-gpu`), chosen per
//! server (`backend` in the config, `--backend`, `FRACTILE_BACKEND`) and per request
//! (`?backend=cpu|gpu|auto`). No math here: the codec decides what to decode, this module only
//! hands the point chains to one device or the other.
//!
//! `auto` sends a request to the GPU when it decodes at least [`AUTO_POINTS`] points on a
//! hardware adapter. A software adapter (Mesa's lavapipe, device type Cpu) is slower than the
//! CPU decoder itself (the GPU bench measures 10x), so `auto` never picks it; `gpu` still can.
//! Operators are uploaded on first use and stay resident in an LRU cache bounded in bytes
//! (`gpu_memory_mib`); an asset replaced by upload has a new hash, hence new entries.
//! Concurrent first requests for one operator wait for one upload rather than each flattening
//! it: a projected DEM was flattened at 336 bytes a sample before it went to the device (for
//! etopo20, 195 MB and about 0.1 s of a core; it now goes as a lattice of 44 bytes a sample,
//! 26 MB, built in 3 ms), so sixteen tiles arriving together on a fresh server made sixteen
//! copies. An
//! operator the device refuses (its tables over the adapter's largest binding, or over the
//! whole cache) is remembered for [`REFUSAL_TTL`], its requests decoded on the CPU meanwhile
//! without trying again: before, every request flattened the tables again to be refused again,
//! 110 ms of a core a tile on lavapipe's 128 MiB binding.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use fractile_codec::extract::{Answer, PlaneRef, Sites};
use fractile_codec::pieces::Flatten;
use fractile_gpu::{Gpu, GpuOperator};

use crate::store::StoredAsset;

/// Smallest continuous decode `auto` sends to a hardware GPU: one 256 x 256 tile.
pub(crate) const AUTO_POINTS: usize = 256 * 256;

/// A backend choice: the API's own vocabulary (`cpu`, `gpu`, `auto`), from `fractile-proto`.
pub(crate) use fractile_proto::query::Backend;

/// How long an operator the device refused is decoded on the CPU before the device is asked
/// again: a refusal is mostly for good (the tables' size), but one for memory the cache held
/// at the time may pass later.
pub(crate) const REFUSAL_TTL: Duration = Duration::from_secs(600);

/// An operator's key: asset id, its hash, the chunk (chunked assets: level and index), the
/// plane (`usize::MAX`: the volume).
type Key = (String, u32, Option<(usize, usize)>, usize);

/// The server's GPU: the device and its resident operators.
pub struct GpuBackend {
    gpu: Gpu,
    software: bool,
    resident: moka::sync::Cache<Key, Arc<GpuOperator>>,
    /// The bytes the resident operators may take.
    memory: u64,
    refused: moka::sync::Cache<Key, ()>,
    /// Held through an upload: one operator is flattened at a time.
    uploading: std::sync::Mutex<()>,
    /// Operators uploaded, and refused.
    uploads: [AtomicU64; 2],
}

impl GpuBackend {
    /// Opens the first adapter; `memory` bounds the resident operators, in bytes.
    pub fn open(memory: u64) -> Result<GpuBackend, fractile_gpu::GpuError> {
        let gpu = Gpu::new()?;
        let software = gpu.is_software();
        Ok(GpuBackend {
            gpu,
            software,
            resident: moka::sync::Cache::builder()
                .weigher(|_k, v: &Arc<GpuOperator>| v.bytes().try_into().unwrap_or(u32::MAX))
                .max_capacity(memory)
                .build(),
            memory,
            refused: moka::sync::Cache::builder()
                .max_capacity(4096)
                .time_to_live(REFUSAL_TTL)
                .build(),
            uploads: Default::default(),
            uploading: std::sync::Mutex::new(()),
        })
    }

    /// Operators uploaded to the device, and operators it refused, since it was opened.
    pub fn uploads(&self) -> (u64, u64) {
        let [done, refused] = &self.uploads;
        (
            done.load(Ordering::Relaxed),
            refused.load(Ordering::Relaxed),
        )
    }

    /// The adapter, in words.
    pub fn adapter(&self) -> String {
        self.gpu.adapter()
    }

    /// Rounds of small grids the device decoded together, and the grids in them.
    pub fn rounds(&self) -> (u64, u64) {
        self.gpu.rounds()
    }

    /// Whether `choice` sends a decode of `points` points of `a` here. `auto` leaves chunked
    /// assets on the CPU: each chunk's operator goes up when a request first touches it, at
    /// 44 bytes a sample for the default DEM codec (about 9 times what the chunk cache holds of
    /// it), flattened in 19 ms for a 1025 x 1080 chunk on a 2-core machine where a CPU tile
    /// takes 2-4 ms. On an H100, etopo20 in 10 chunks, all resident, served 1.56-1.97x the
    /// CPU's uncached tiles; but a DEM whose touched chunks overflow `gpu_memory_mib` would
    /// upload more than it decodes, and that case is unmeasured. Asked for (`gpu`), they decode
    /// there, chunk by chunk. (A one-off window, `fractile decode`, visits each chunk once and
    /// takes the GPU on `auto` as a whole asset does.)
    pub fn takes(&self, choice: Backend, a: &StoredAsset, points: usize) -> bool {
        match choice {
            Backend::Cpu => false,
            Backend::Gpu => true,
            Backend::Auto => auto_takes(self.software, a.asset.chunked().is_some(), points),
        }
    }

    /// The resident operator of an asset's plane (of one of its chunks, for chunked assets;
    /// `usize::MAX`: its volume), uploaded on first use, once for all the requests that want
    /// it meanwhile; `None` when the device refused it (logged once a refusal), within
    /// [`REFUSAL_TTL`] of a refusal.
    fn resident(
        &self,
        a: &StoredAsset,
        (chunk, plane): (Option<(usize, usize)>, usize),
        upload: impl FnOnce() -> Result<GpuOperator, fractile_gpu::GpuError>,
    ) -> Option<Arc<GpuOperator>> {
        let key = (a.id.clone(), a.hash, chunk, plane);
        if self.refused.contains_key(&key) {
            return None;
        }
        let made = self.resident.try_get_with(key.clone(), || {
            let [done, refused] = &self.uploads;
            // Runs once for the requests that wait on this upload: they share its error.
            let refuse = |why: String| {
                self.refused.insert(key.clone(), ());
                refused.fetch_add(1, Ordering::Relaxed);
                let chunk = chunk.map_or(String::new(), |(l, i)| format!(" (chunk {i} of level {l})"));
                tracing::warn!(
                    "GPU upload of {}{chunk} refused, decoding it on the CPU for the next {} s: {why}",
                    a.id,
                    REFUSAL_TTL.as_secs()
                );
                why
            };
            // One upload at a time: flattening builds an operator's tables on every core, 75 MB
            // for a 1024 x 1024 chunk of the default DEM codec held until they are on the
            // device; first touches of many chunks at once each held theirs.
            let op = {
                let _one = self.uploading.lock().unwrap_or_else(|e| e.into_inner());
                upload().map_err(|e| refuse(e.to_string()))?
            };
            // Tables over the whole cache would be evicted as soon as they are in, and
            // uploaded again by the next request.
            if op.bytes() as u64 > self.memory {
                return Err(refuse(format!(
                    "its tables of {} MiB exceed gpu_memory_mib ({} MiB)",
                    op.bytes() >> 20,
                    self.memory >> 20
                )));
            }
            done.fetch_add(1, Ordering::Relaxed);
            Ok(Arc::new(op))
        });
        made.ok()
    }

    /// Continuous decoding of a volume's box (unit coordinates, corners included); `None`
    /// (logged) when the device fails, for the caller to use the CPU.
    pub fn volume_grid(
        &self,
        a: &StoredAsset,
        (lo, hi, dims): ([f32; 3], [f32; 3], [usize; 3]),
        iterations: u32,
        tolerance: f32,
    ) -> Option<(Vec<f32>, f32)> {
        let volume = a.asset.volume()?;
        let op = self.resident(a, (None, usize::MAX), || {
            self.gpu.upload_volume(&volume.operator)
        })?;
        let dims = dims.map(|d| d as u32);
        // A mesh needs the values and one bound: the device reduces the bounds and sends the
        // values alone.
        match self
            .gpu
            .volume_grid_values(&op, lo, hi, dims, iterations, tolerance)
        {
            Ok(g) => Some((g.values, g.error_bound)),
            Err(e) => {
                tracing::warn!("GPU decode of {} failed, decoding on the CPU: {e}", a.id);
                None
            }
        }
    }

    /// The resident operator of the plane of `a` (or of one of its chunks) that the codec hands
    /// its hook, uploaded on first use; `None` when the device refused it. The upload's
    /// flattening is CPU work, which the caller runs on its core slot (a chunked asset's
    /// chunks go up as requests first touch them, each 44 bytes a sample for the default DEM
    /// codec: 19 ms on two cores for a 1025 x 1080 chunk); the decode that follows waits
    /// on the device and runs off it.
    pub fn operator(&self, a: &StoredAsset, plane: PlaneRef<'_>) -> Option<Arc<GpuOperator>> {
        self.resident(a, (plane.chunk, plane.index), || {
            self.gpu.upload_flat(&plane.operator.flat())
        })
    }

    /// Continuous decoding of one plane's points (a list, or a separable grid generated on the
    /// device) on its resident operator `op` (see [`GpuBackend::operator`]); `None` (logged)
    /// when the device fails, for the caller to use the CPU.
    pub fn points(
        &self,
        a: &StoredAsset,
        op: &GpuOperator,
        sites: Sites<'_>,
        iterations: u32,
        tolerance: f32,
    ) -> Option<Answer> {
        // A grid (a tile, a region) answers one bound for all its pixels, the largest: the
        // device reduces the bounds and sends the values alone, a quarter of the bytes, which
        // go on as they are.
        match self.gpu.answer(op, sites, iterations, tolerance) {
            Ok(v) => Some(v),
            Err(e) => {
                tracing::warn!("GPU decode of {} failed, decoding on the CPU: {e}", a.id);
                None
            }
        }
    }
}

/// `auto`'s choice (see [`GpuBackend::takes`]): a hardware adapter, a whole asset, a tile's
/// points or more.
fn auto_takes(software: bool, chunked: bool, points: usize) -> bool {
    !software && !chunked && points >= AUTO_POINTS
}

#[cfg(test)]
mod tests {
    #[test]
    fn auto_takes_whole_assets_of_a_tile_or_more_to_a_hardware_adapter_only() {
        use super::{AUTO_POINTS, auto_takes};
        assert!(auto_takes(false, false, AUTO_POINTS));
        assert!(!auto_takes(false, false, AUTO_POINTS - 1));
        assert!(
            !auto_takes(true, false, 1 << 24),
            "never a software adapter"
        );
        assert!(
            !auto_takes(false, true, 1 << 24),
            "chunked assets stay on the CPU"
        );
    }
}
