//! A circuit breaker over an object store's chunk reads.

use std::time::Duration;

/// How long chunk reads fail at once after one found the store unreachable, before the next
/// one tries it again.
pub(super) const BREAK: Duration = Duration::from_secs(1);

/// A circuit breaker over chunk reads. A read that found the store unreachable (after the
/// client's retries: seconds) opens it: for [`BREAK`] every read that the disk cache cannot
/// serve fails at once (503 `chunk_unavailable` with `Retry-After: 1`) instead of holding a
/// decoding slot through the same seconds of retries; then one read goes through as a probe,
/// the others still failing at once, and its answer closes it or opens it again. A store that
/// comes back is then read again within a second (plus one read's time).
#[derive(Default)]
pub(super) struct Breaker {
    /// Until when reads fail at once; `None`: closed.
    open_until: std::sync::Mutex<Option<std::time::Instant>>,
    /// A probe is out.
    probing: std::sync::atomic::AtomicBool,
}

impl Breaker {
    /// Whether a read may go to the store now (when half open, this read is the probe).
    pub(super) fn admit(&self) -> bool {
        use std::sync::atomic::Ordering::Relaxed;
        match *self.state() {
            None => true,
            Some(t) if std::time::Instant::now() >= t => !self.probing.swap(true, Relaxed),
            Some(_) => false,
        }
    }

    /// What a read that went to the store found: the store answering (whatever its answer),
    /// or not.
    pub(super) fn found(&self, reachable: bool) {
        *self.state() = (!reachable).then(|| std::time::Instant::now() + BREAK);
        self.probing
            .store(false, std::sync::atomic::Ordering::Relaxed);
    }

    fn state(&self) -> std::sync::MutexGuard<'_, Option<std::time::Instant>> {
        // One Option written at once: a poisoned lock is moot.
        self.open_until.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::{BREAK, Breaker};
    use std::time::Duration;

    /// The breaker: open after a read found no store, reads refused at once for its wait, then
    /// one probe let through (the others still refused), closed by a probe that found it.
    #[test]
    fn the_breaker_refuses_for_its_wait_then_lets_one_probe_through() {
        let b = Breaker::default();
        assert!(b.admit() && b.admit(), "closed: every read goes");
        b.found(false);
        assert!(!b.admit(), "open: refused at once");
        std::thread::sleep(BREAK + Duration::from_millis(50));
        assert!(b.admit(), "half open: one probe");
        assert!(!b.admit(), "the others wait for it");
        b.found(false);
        assert!(!b.admit(), "the probe found no store: open again");
        std::thread::sleep(BREAK + Duration::from_millis(50));
        assert!(b.admit());
        b.found(true);
        assert!(b.admit() && b.admit(), "the probe found it: closed");
    }
}
