//! The light lane's core slots, given to work in progress before new work.
//!
//! Work that waits on a GPU gives its slot back for the wait and needs one again to finish (to
//! encode its PNG). With one first-come queue (tokio's `Semaphore`, which has no priorities)
//! that work queued behind every request that arrived during its wait: under overload a GPU
//! tile waited in the queue twice, and its decoded heights stayed in memory meanwhile. Here a
//! freed slot goes first to work coming back from a wait, then to new requests in their
//! order of arrival. Hand-written because no well-kept crate offers a semaphore with two
//! classes of waiters; it is a mutex over two queues of one-shot channels.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::sync::oneshot;

/// A count of core slots with two queues of waiters: work resuming, then new work.
pub(super) struct Slots {
    state: Mutex<State>,
}

struct State {
    free: usize,
    /// Work coming back from a wait off the cores (served first).
    resuming: VecDeque<oneshot::Sender<SlotPermit>>,
    /// New requests, in their order of arrival.
    arriving: VecDeque<oneshot::Sender<SlotPermit>>,
}

/// One slot taken; dropping it gives it to the next waiter, or back to the count.
pub(super) struct SlotPermit {
    /// `None` only for a permit a waiter refused, which [`Slots::give`] passes on itself.
    slots: Option<Arc<Slots>>,
}

impl Drop for SlotPermit {
    fn drop(&mut self) {
        if let Some(slots) = self.slots.take() {
            Slots::give(slots);
        }
    }
}

impl Slots {
    /// `n` free slots.
    pub(super) fn new(n: usize) -> Arc<Slots> {
        Arc::new(Slots {
            state: Mutex::new(State {
                free: n,
                resuming: VecDeque::new(),
                arriving: VecDeque::new(),
            }),
        })
    }

    /// Slots free now.
    pub(super) fn free(&self) -> usize {
        self.state().free
    }

    /// A slot for a new request, after every waiter ahead of it. A request dropped while it
    /// waits loses nothing: a slot sent to it is dropped with its channel, which gives it on.
    #[expect(
        clippy::expect_used,
        reason = "a queued waiter's sender is kept in the state until it sends: the channel never closes unsent"
    )]
    pub(super) async fn arrive(self: &Arc<Slots>) -> SlotPermit {
        let rx = {
            let mut s = self.state();
            if s.free > 0 && s.resuming.is_empty() && s.arriving.is_empty() {
                s.free -= 1;
                return SlotPermit {
                    slots: Some(self.clone()),
                };
            }
            let (tx, rx) = oneshot::channel();
            s.arriving.push_back(tx);
            rx
        };
        // The sender is dropped only after sending: the state keeps it until then.
        rx.await
            .expect("a queued waiter's sender is kept until it sends")
    }

    /// A slot for work coming back from a wait, ahead of new requests. Blocks the calling
    /// thread (a blocking-pool thread, which is what it is for).
    #[expect(
        clippy::expect_used,
        reason = "a queued waiter's sender is kept in the state until it sends: the channel never closes unsent"
    )]
    pub(super) fn resume(self: &Arc<Slots>) -> SlotPermit {
        let rx = {
            let mut s = self.state();
            if s.free > 0 && s.resuming.is_empty() {
                s.free -= 1;
                return SlotPermit {
                    slots: Some(self.clone()),
                };
            }
            let (tx, rx) = oneshot::channel();
            s.resuming.push_back(tx);
            rx
        };
        rx.blocking_recv()
            .expect("a queued waiter's sender is kept until it sends")
    }

    /// Gives a freed slot to the first waiter still waiting (work resuming first), or back to
    /// the count.
    fn give(slots: Arc<Slots>) {
        loop {
            let next = {
                let mut s = slots.state();
                match s.resuming.pop_front().or_else(|| s.arriving.pop_front()) {
                    Some(tx) => tx,
                    None => {
                        s.free += 1;
                        return;
                    }
                }
            };
            // Sent outside the lock. A waiter that left (its request dropped) refuses it: the
            // permit comes back, disarmed, and the next waiter is tried.
            let permit = SlotPermit {
                slots: Some(slots.clone()),
            };
            match next.send(permit) {
                Ok(()) => return,
                Err(mut refused) => refused.slots = None,
            }
        }
    }

    /// Waiters queued now: work resuming, new requests.
    #[cfg(test)]
    pub(super) fn queued(&self) -> (usize, usize) {
        let s = self.state();
        (s.resuming.len(), s.arriving.len())
    }

    fn state(&self) -> MutexGuard<'_, State> {
        // The state is counts and queues, each change a single step: a poisoned lock is moot.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}
