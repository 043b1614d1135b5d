//! The lanes' tests: slots lent for a device's wait, the order of waiters, refusals of heavy
//! work past the queue wait.
use super::*;

/// A GPU-like wait on one lane slot: a second request runs during the wait (it would wait
/// for ever if the slot were held), and the first takes a slot again before going on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn work_waiting_on_a_device_lends_its_core_slot() {
    let lanes = Arc::new(Lanes::new(1, 64));
    let (entered_tx, entered_rx) = oneshot::channel::<()>();
    let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
    let first = {
        let lanes = lanes.clone();
        tokio::spawn(async move {
            let inner = lanes.clone();
            lanes
                .run(0, move |cancel| {
                    let held_before = !inner.light_free();
                    let _ = entered_tx.send(());
                    let waited =
                        cancel.off_core(|| done_rx.recv_timeout(Duration::from_secs(20)).is_ok());
                    (held_before, waited, !inner.light_free())
                })
                .await
        })
    };
    entered_rx.await.expect("the first request runs");
    let second = tokio::time::timeout(
        Duration::from_secs(10),
        lanes.run(0, move |_| done_tx.send(()).is_ok()),
    )
    .await
    .expect("the second request got the lent slot")
    .expect("it ran");
    assert!(second);
    let (held_before, waited, held_after) = first.await.unwrap().unwrap();
    assert!(held_before, "the first request held the only slot");
    assert!(waited, "its wait ended by the second request's work");
    assert!(held_after, "it holds a slot again after the wait");
    assert!(lanes.light_free(), "both slots were given back");
}

/// Waits until the light lane's queues hold `queued` (resuming, arriving).
async fn until_queued(lanes: &Lanes, queued: (usize, usize)) {
    for _ in 0..2000 {
        if lanes.light.queued() == queued {
            return;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    panic!(
        "the lane never queued {queued:?}: {:?}",
        lanes.light.queued()
    );
}

/// Work back from a device wait takes the next free slot before a request that arrived
/// during its wait (with one first-come queue it would run after it).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn work_back_from_a_wait_goes_before_new_requests() {
    let lanes = Arc::new(Lanes::new(1, 64));
    let order = Arc::new(std::sync::Mutex::new(Vec::new()));
    let (lent_tx, lent_rx) = oneshot::channel::<()>();
    let (wait_tx, wait_rx) = std::sync::mpsc::channel::<()>();
    let (hold_tx, hold_rx) = std::sync::mpsc::channel::<()>();
    let (held_tx, held_rx) = oneshot::channel::<()>();
    let spawn = |f: Box<dyn FnOnce(&Cancel) + Send>| {
        let lanes = lanes.clone();
        tokio::spawn(async move { lanes.run(0, f).await.unwrap() })
    };
    let o = order.clone();
    let waiting = spawn(Box::new(move |cancel: &Cancel| {
        cancel.off_core(|| {
            let _ = lent_tx.send(());
            wait_rx.recv_timeout(Duration::from_secs(20)).unwrap();
        });
        o.lock().unwrap().push("back from the wait");
    }));
    lent_rx.await.unwrap();
    // A second request takes the lent slot and holds it.
    let holding = spawn(Box::new(move |_: &Cancel| {
        let _ = held_tx.send(());
        hold_rx.recv_timeout(Duration::from_secs(20)).unwrap();
    }));
    held_rx.await.unwrap();
    // A third arrives and queues; then the first's wait ends and it queues too.
    let o = order.clone();
    let arriving = spawn(Box::new(move |_: &Cancel| {
        o.lock().unwrap().push("arrived")
    }));
    until_queued(&lanes, (0, 1)).await;
    wait_tx.send(()).unwrap();
    until_queued(&lanes, (1, 1)).await;
    hold_tx.send(()).unwrap();
    for task in [waiting, holding, arriving] {
        task.await.unwrap();
    }
    assert_eq!(
        *order.lock().unwrap(),
        ["back from the wait", "arrived"],
        "the slot freed went to the work in progress first"
    );
    assert!(lanes.light_free(), "the slot was given back");
}

/// A request dropped while it queues loses its place, not the lane's slot.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_dropped_in_the_queue_gives_its_slot_on() {
    let lanes = Arc::new(Lanes::new(1, 64));
    let (hold_tx, hold_rx) = std::sync::mpsc::channel::<()>();
    let holding = {
        let lanes = lanes.clone();
        tokio::spawn(async move {
            lanes
                .run(0, move |_| {
                    hold_rx.recv_timeout(Duration::from_secs(20)).is_ok()
                })
                .await
        })
    };
    until_slots_taken(&lanes).await;
    let dropped = tokio::time::timeout(Duration::from_millis(50), lanes.run(0, |_| ())).await;
    assert!(
        dropped.is_err(),
        "the second request queued behind the first"
    );
    hold_tx.send(()).unwrap();
    assert!(holding.await.unwrap().unwrap());
    let third = tokio::time::timeout(Duration::from_secs(10), lanes.run(0, |_| 3)).await;
    assert_eq!(third.expect("the slot was not lost").unwrap(), 3);
    assert!(lanes.light_free());
}

async fn until_slots_taken(lanes: &Lanes) {
    for _ in 0..2000 {
        if !lanes.light_free() {
            return;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    panic!("the lane's slot was never taken");
}

/// On a rayon worker, work keeps its slot through a wait rather than block the worker to
/// take one back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wait_on_a_rayon_worker_keeps_its_slot() {
    let lanes = Arc::new(Lanes::new(1, 64));
    let inner = lanes.clone();
    let held = lanes
        .run(0, move |cancel| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .build()
                .unwrap();
            pool.install(|| cancel.off_core(|| !inner.light_free()))
        })
        .await
        .unwrap();
    assert!(held, "the slot stayed held through the wait");
    assert!(lanes.light_free(), "and was given back after");
}

/// Heavy work runs first come, first served, one run a two cores: while the first decodes,
/// the next ones are refused within the queue wait, with 503 `busy` and `Retry-After`,
/// rather than all sharing the cores until the request timeout; once it is done the next
/// one runs.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn heavy_work_past_the_queue_wait_is_refused_at_once() {
    let lanes = Arc::new(Lanes::new(2, 1024));
    assert_eq!(lanes.heavy_runs(), 1);
    let heavy = LIGHT_BYTES + 1;
    let (started_tx, started_rx) = oneshot::channel::<()>();
    let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
    let first = {
        let lanes = lanes.clone();
        tokio::spawn(async move {
            lanes
                .run(heavy, move |_| {
                    let _ = started_tx.send(());
                    done_rx.recv_timeout(Duration::from_secs(30)).is_ok()
                })
                .await
        })
    };
    started_rx.await.expect("the first heavy request runs");
    let t = std::time::Instant::now();
    let later: Vec<_> = (0..3)
        .map(|_| {
            let lanes = lanes.clone();
            tokio::spawn(async move { lanes.run(heavy, |_| ()).await })
        })
        .collect();
    for task in later {
        let refused = task.await.unwrap().expect_err("no run is free");
        assert_eq!(refused.status, axum::http::StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(refused.code, fractile_proto::ErrorCode::Busy);
        assert!(refused.retry_after.is_some_and(|s| s >= 1));
    }
    let waited = t.elapsed();
    assert!(
        waited >= HEAVY_QUEUE_WAIT && waited < HEAVY_QUEUE_WAIT + Duration::from_secs(2),
        "refused after the queue wait, not the request timeout: {waited:?}"
    );
    // Light work is not held up by the heavy queue.
    let light = tokio::time::timeout(Duration::from_secs(5), lanes.run(0, |_| 1)).await;
    assert_eq!(light.expect("a light slot").unwrap(), 1);
    done_tx.send(()).unwrap();
    assert!(
        first.await.unwrap().unwrap(),
        "the first heavy request was served"
    );
    let next = tokio::time::timeout(Duration::from_secs(5), lanes.run(heavy, |_| 2)).await;
    assert_eq!(next.expect("the run was given back").unwrap(), 2);
}

/// Outside a lane, `off_core` only runs its closure.
#[test]
fn off_core_outside_a_lane_runs_the_wait() {
    assert_eq!(Cancel::default().off_core(|| 7), 7);
}
