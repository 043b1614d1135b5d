//! The machine's memory as the server sees it: the default decode budget from the container's
//! or the machine's limit, and memory handed back to the system after a burst.

/// Default of `max_decode_mib` where the memory limit is unknown: what the heavy lane may hold
/// at once, and what one asset may cost to decode
/// ([`fractile_codec::AssetLimits::max_decode_bytes`]).
pub(crate) const DEFAULT_DECODE_MIB: u32 = 3 * 1024;

/// Default of `max_decode_mib` on this machine: half of what its memory limit leaves after
/// 1 GiB for the caches' defaults and the process, within 256 MiB..16 GiB. The limit is the
/// container's (cgroup v2 `memory.max`, or v1 `memory.limit_in_bytes`) where one is set, else
/// the machine's (`MemTotal`): a fixed 3 GiB let a pod of 2 GiB be killed by the kernel under
/// one burst of regions the budget admitted, and left most of a large machine unused.
pub(crate) fn default_decode_mib() -> u32 {
    let Some(limit) = memory_limit() else {
        return DEFAULT_DECODE_MIB;
    };
    let mib = (limit >> 20).saturating_sub(1024) / 2;
    mib.clamp(256, 16 * 1024) as u32
}

/// The memory this process may use, in bytes: the smallest of the cgroup's limit and the
/// machine's memory (Linux; `None` elsewhere or when none can be read).
fn memory_limit() -> Option<u64> {
    let read =
        |path: &str| -> Option<u64> { std::fs::read_to_string(path).ok()?.trim().parse().ok() };
    let total = std::fs::read_to_string("/proc/meminfo").ok().and_then(|m| {
        let line = m.lines().find(|l| l.starts_with("MemTotal:"))?;
        let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kib << 10)
    });
    // "max" (no limit) does not parse; v1 writes a huge number for none.
    let cgroup = read("/sys/fs/cgroup/memory.max")
        .or_else(|| read("/sys/fs/cgroup/memory/memory.limit_in_bytes"))
        .filter(|&b| b < 1 << 60);
    match (cgroup, total) {
        (Some(c), Some(t)) => Some(c.min(t)),
        (c, t) => c.or(t),
    }
}

/// Returns the memory freed by heavy work to the system once no heavy work holds any of the
/// budget (`budget` has all its `mib` permits). glibc's malloc keeps freed memory in its
/// arenas (one per thread that allocated), so after a burst the process held what the burst's
/// peak took: measured, 16 readers of 64 MB regions left RSS (idle 45 MiB) at 112 MiB and the
/// issue's burst 1,604 MB. `malloc_trim` hands the arenas' free pages back; it runs on the
/// blocking thread that finished the work, off the executor, and only when the lane is idle,
/// so a steady load pays nothing. (An allocator with decay, jemalloc or mimalloc, would do it
/// too, at the cost of a C dependency for every build; this is one call.)
pub(crate) fn give_back_when_idle(budget: &tokio::sync::Semaphore, mib: u32) {
    if budget.available_permits() == mib as usize {
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        // SAFETY: malloc_trim takes an integer and only touches the allocator's own state,
        // which it locks.
        unsafe {
            libc::malloc_trim(0);
        }
    }
}
