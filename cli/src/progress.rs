//! Progress of long work on stderr: an indicatif bar on a terminal, a plain line every
//! [`LINE_EVERY`] elsewhere (a log, CI, a pipe), nothing with `--quiet` or `--json`.
//!
//! Why a thread of its own and not only the work's own counts: the work reports what it has
//! finished (chunks, blocks), and one chunk of a bounded DEM encode takes tens of seconds on
//! two cores. A user who sees nothing for that long thinks the program hung (a 12-minute
//! default encode of a 9.3 Mpx DEM printed nothing at all). So the bar appears after
//! [`SHOW_AFTER`] whatever the work has reported, and redraws its elapsed time and spinner
//! every [`TICK`] between counts.

use std::io::IsTerminal;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle};

/// Work shorter than this shows nothing.
pub(crate) const SHOW_AFTER: Duration = Duration::from_secs(1);
/// How often a terminal's bar redraws between counts.
pub(crate) const TICK: Duration = Duration::from_millis(500);
/// How often a line is printed where stderr is not a terminal.
pub(crate) const LINE_EVERY: Duration = Duration::from_secs(10);

/// Where progress goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Mode {
    Quiet,
    Terminal,
    Lines,
}

/// What the ticking thread and the work share.
struct Shared {
    done: Mutex<bool>,
    wake: Condvar,
}

/// Progress of one piece of work (see the module). Dropping it ends it.
pub(crate) struct Progress {
    bar: ProgressBar,
    shared: Arc<Shared>,
    ticker: Option<std::thread::JoinHandle<()>>,
}

impl Progress {
    /// Progress of `what` (e.g. "coding chunks"), quiet when `quiet`.
    pub(crate) fn start(what: &str, quiet: bool) -> Progress {
        let mode = if quiet {
            Mode::Quiet
        } else if std::io::stderr().is_terminal() {
            Mode::Terminal
        } else {
            Mode::Lines
        };
        let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::hidden());
        bar.set_style(style(what));
        let shared = Arc::new(Shared {
            done: Mutex::new(false),
            wake: Condvar::new(),
        });
        let ticker = (mode != Mode::Quiet).then(|| {
            let (bar, shared, what) = (bar.clone(), shared.clone(), what.to_string());
            std::thread::spawn(move || tick(mode, &bar, &shared, &what))
        });
        Progress {
            bar,
            shared,
            ticker,
        }
    }

    /// `done` of `total` units finished.
    pub(crate) fn update(&self, done: u64, total: u64) {
        self.bar.set_length(total);
        self.bar.set_position(done);
    }

    /// Ends the progress and clears the bar.
    pub(crate) fn finish(&mut self) {
        *self.shared.done.lock().unwrap_or_else(|e| e.into_inner()) = true;
        self.shared.wake.notify_all();
        if let Some(t) = self.ticker.take() {
            let _ = t.join();
        }
        self.bar.finish_and_clear();
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.finish();
    }
}

/// The bar: what, how far, elapsed and an estimate of what is left (from the rate so far;
/// "estimating" before the first unit is done).
fn style(what: &str) -> ProgressStyle {
    ProgressStyle::with_template(&format!(
        "{{spinner}} {what} {{bar:30}} {{pos}}/{{len}}, {{elapsed}} so far, {{left}}"
    ))
    .expect("a valid template")
    .with_key("left", |s: &ProgressState, w: &mut dyn std::fmt::Write| {
        let _ = write!(w, "{}", left(s.pos(), s.len(), s.eta()));
    })
}

/// The estimate of time left, in words, from `pos` of `len` done and indicatif's estimate.
fn left(pos: u64, len: Option<u64>, eta: Duration) -> String {
    if pos == 0 || len.is_none() {
        "estimating the time left".into()
    } else {
        format!("about {} left", indicatif::HumanDuration(eta))
    }
}

/// The ticking thread: after [`SHOW_AFTER`], the bar on a terminal (redrawn every [`TICK`]) or
/// a line every [`LINE_EVERY`] elsewhere, until the work is done.
fn tick(mode: Mode, bar: &ProgressBar, shared: &Shared, what: &str) {
    let started = Instant::now();
    let wait = |d: Duration| {
        let done = shared.done.lock().unwrap_or_else(|e| e.into_inner());
        let (done, _) = shared
            .wake
            .wait_timeout_while(done, d, |done| !*done)
            .unwrap_or_else(|e| e.into_inner());
        *done
    };
    if wait(SHOW_AFTER) {
        return;
    }
    match mode {
        Mode::Terminal => {
            bar.set_draw_target(ProgressDrawTarget::stderr());
            bar.enable_steady_tick(TICK);
        }
        Mode::Lines => {
            while !wait(LINE_EVERY) {
                let (pos, len) = (bar.position(), bar.length());
                let count = len.map_or(String::new(), |l| format!(" {pos}/{l},"));
                eprintln!(
                    "{what}:{count} {} so far, {}",
                    indicatif::HumanDuration(started.elapsed()),
                    left(pos, len, bar.eta())
                );
            }
        }
        Mode::Quiet => {}
    }
}
