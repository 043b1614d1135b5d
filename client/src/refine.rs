//! Progressive refinement ("time-controlled decompression" in the seed papers): ask for the same
//! answer at 1, 2, 3, ... iterations and stop when
//! - the server's a-priori error bound is under a tolerance, or
//! - the mean absolute change between two successive answers is under a fraction (0.002, the
//!   seed's criterion) of the value range, or
//! - the next step would not fit in a time budget, or
//! - the schedule ends.
//!
//! Every step is handed to a callback as it arrives, so a viewer can draw the coarse answer at
//! once and replace it, and all steps come back with their bound, change and time.

use std::future::Future;
use std::time::{Duration, Instant};

use crate::view;
use crate::{
    AssetKind, AssetSummary, Client, ClientError, PointsEncoding, PointsRequest, PointsResponse,
    Region, RegionRequest, Tile, TileEncoding, TileRequest,
};

/// When refinement stops.
#[derive(Clone, Debug, PartialEq)]
pub struct RefineOptions {
    /// Stop once the server's error bound is at most this (value units).
    pub tolerance: Option<f32>,
    /// Stop once the mean absolute change between successive answers is at most this fraction
    /// of the value range. The seed papers use 0.002.
    pub change: f32,
    /// Stop before a step that would end past this much time from the start (the next step is
    /// predicted to take as long as the last).
    pub budget: Option<Duration>,
    /// Iterations to ask for, in order.
    pub schedule: Vec<u32>,
}

impl Default for RefineOptions {
    fn default() -> Self {
        RefineOptions {
            tolerance: None,
            change: 0.002,
            budget: None,
            schedule: (1..=64).collect(),
        }
    }
}

/// Why refinement stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stop {
    /// The error bound reached the tolerance.
    Bound,
    /// Successive answers stopped changing.
    Converged,
    /// The time budget would run out.
    Budget,
    /// The schedule ended.
    Schedule,
}

/// One answer of a refinement.
#[derive(Clone, Debug)]
pub struct Step<T> {
    /// 1-based step number.
    pub step: usize,
    /// Iterations asked for.
    pub iterations: u32,
    /// The server's convergence bound (value units): how far the answer is from the
    /// fractal's attractor, which more iterations shrink (unlike the error against the source).
    pub convergence_bound: f32,
    /// Mean absolute change against the previous step (value units); `None` on the first.
    pub mean_change: Option<f32>,
    /// Time this request took.
    pub elapsed: Duration,
    /// Why this step is the last (`None` on every other step), known before `on_step` sees it
    /// so a caller streaming steps can say so at once.
    pub stop: Option<Stop>,
    /// The answer.
    pub answer: T,
}

/// Every step, and why the last was the last.
#[derive(Clone, Debug)]
pub struct Refined<T> {
    /// The steps in order; the last is the best answer.
    pub steps: Vec<Step<T>>,
    /// Why refinement stopped.
    pub stop: Stop,
}

/// What refinement reads from an answer.
pub trait Answer {
    /// The values to compare between steps (NaN where there is none).
    fn values(&self) -> Vec<f32>;
    /// The server's convergence bound (what more iterations shrink).
    fn convergence_bound(&self) -> f32;
}

impl Answer for Tile {
    fn values(&self) -> Vec<f32> {
        self.values.clone()
    }
    fn convergence_bound(&self) -> f32 {
        self.convergence_bound
    }
}

impl Answer for Region {
    fn values(&self) -> Vec<f32> {
        self.values.iter().flatten().flatten().copied().collect()
    }
    fn convergence_bound(&self) -> f32 {
        self.convergence_bound
    }
}

impl Answer for PointsResponse {
    fn values(&self) -> Vec<f32> {
        self.results
            .iter()
            .flat_map(|r| match &r.values {
                Some(v) => v.iter().map(|x| x.unwrap_or(f32::NAN)).collect(),
                None => vec![f32::NAN],
            })
            .collect()
    }
    fn convergence_bound(&self) -> f32 {
        self.results
            .iter()
            .filter_map(|r| r.convergence_bound)
            .fold(0.0, f32::max)
    }
}

/// Mean of |a - b| over the pairs where both are finite (`None` when no pair is, or the lengths
/// differ).
pub fn mean_change(a: &[f32], b: &[f32]) -> Option<f32> {
    if a.len() != b.len() {
        return None;
    }
    let (sum, n) = a
        .iter()
        .zip(b)
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .fold((0.0f64, 0usize), |(s, n), (x, y)| {
            (s + (x - y).abs() as f64, n + 1)
        });
    (n > 0).then(|| (sum / n as f64) as f32)
}

/// Refines an answer. `range` is the value range the change criterion is a fraction of (255 for
/// visual tiles, `max - min` for heights); `fetch(n)` asks for the answer at `n` iterations;
/// `on_step` sees each step as it arrives.
pub async fn refine<T, F, Fut>(
    options: &RefineOptions,
    range: f32,
    mut fetch: F,
    mut on_step: impl FnMut(&Step<T>),
) -> Result<Refined<T>, ClientError>
where
    T: Answer,
    F: FnMut(u32) -> Fut,
    Fut: Future<Output = Result<T, ClientError>>,
{
    if options.schedule.is_empty() {
        return Err(ClientError::malformed("refinement", "empty schedule"));
    }
    let start = Instant::now();
    let mut steps: Vec<Step<T>> = Vec::new();
    let mut previous: Option<Vec<f32>> = None;
    for (k, &n) in options.schedule.iter().enumerate() {
        let t = Instant::now();
        let answer = fetch(n).await?;
        let elapsed = t.elapsed();
        let values = answer.values();
        let change = previous.as_deref().and_then(|p| mean_change(p, &values));
        let convergence_bound = answer.convergence_bound();
        let stop = if options.tolerance.is_some_and(|t| convergence_bound <= t) {
            Some(Stop::Bound)
        } else if change.is_some_and(|c| c <= options.change * range) {
            Some(Stop::Converged)
        } else if k + 1 == options.schedule.len() {
            Some(Stop::Schedule)
        } else if options
            .budget
            // Another step takes at least as long as this one did (more iterations).
            .is_some_and(|b| start.elapsed() + elapsed >= b)
        {
            Some(Stop::Budget)
        } else {
            None
        };
        let step = Step {
            step: k + 1,
            iterations: n,
            convergence_bound,
            mean_change: change,
            elapsed,
            stop,
            answer,
        };
        on_step(&step);
        steps.push(step);
        if let Some(stop) = stop {
            return Ok(Refined { steps, stop });
        }
        previous = Some(values);
    }
    unreachable!("the last step of a non-empty schedule always stops")
}

/// Value range the change criterion is a fraction of: 255 for pictures, the asset's span for
/// heights.
fn change_range(a: &AssetSummary, heights: bool) -> f32 {
    if heights {
        (a.value_range[1] - a.value_range[0]).max(f64::MIN_POSITIVE) as f32
    } else {
        255.0
    }
}

impl Client {
    /// Refines one tile (see [`refine`]); `req.iterations` is replaced by the schedule's.
    pub async fn refine_tile(
        &self,
        id: &str,
        req: &TileRequest,
        options: &RefineOptions,
        on_step: impl FnMut(&Step<Tile>),
    ) -> Result<Refined<Tile>, ClientError> {
        let a = self.asset(id).await?;
        let range = change_range(&a, req.encoding.is_heights());
        refine(
            options,
            range,
            |n| {
                let req = TileRequest {
                    iterations: Some(n),
                    tolerance: None,
                    // Refinement compares steps and stops on the convergence bound: heights
                    // rounded to the error bound would hide changes under a step and keep the
                    // bound from falling under half of one.
                    precision: Some(fractile_proto::query::Precision::Full),
                    ..*req
                };
                async move { self.tile(id, &req).await }
            },
            on_step,
        )
        .await
    }

    /// Refines a region; a float32 region compares values, other formats compare nothing and
    /// stop on the bound, the budget or the schedule.
    pub async fn refine_region(
        &self,
        id: &str,
        req: &RegionRequest,
        options: &RefineOptions,
        on_step: impl FnMut(&Step<Region>),
    ) -> Result<Refined<Region>, ClientError> {
        let a = self.asset(id).await?;
        let range = change_range(&a, a.kind == AssetKind::HeightField);
        refine(
            options,
            range,
            |n| {
                let req = RegionRequest {
                    iterations: Some(n),
                    tolerance: None,
                    ..req.clone()
                };
                async move { self.region(id, &req).await }
            },
            on_step,
        )
        .await
    }

    /// Refines a set of points.
    pub async fn refine_points(
        &self,
        id: &str,
        points: &[[f64; 2]],
        encoding: PointsEncoding,
        options: &RefineOptions,
        on_step: impl FnMut(&Step<PointsResponse>),
    ) -> Result<Refined<PointsResponse>, ClientError> {
        let a = self.asset(id).await?;
        let range = change_range(&a, a.kind == AssetKind::HeightField);
        refine(
            options,
            range,
            |n| {
                let req = PointsRequest {
                    points: points.to_vec(),
                    iterations: Some(n),
                    tolerance: None,
                };
                async move { self.points(id, &req, encoding).await }
            },
            on_step,
        )
        .await
    }

    /// Fetches the tiles of a view plan ([`view::plan`]) nearest first, `concurrency` at a time,
    /// each at its planned steps and tolerance. `on_tile` sees each answer as it arrives;
    /// all come back in plan order.
    pub async fn fetch_view(
        &self,
        id: &str,
        plan: &[view::PlannedTile],
        encoding: TileEncoding,
        concurrency: usize,
        mut on_tile: impl FnMut(&view::PlannedTile, &Result<Tile, ClientError>),
    ) -> Vec<Result<Tile, ClientError>> {
        let mut set = tokio::task::JoinSet::new();
        let mut out: Vec<Option<Result<Tile, ClientError>>> =
            (0..plan.len()).map(|_| None).collect();
        let mut next = 0;
        loop {
            while next < plan.len() && set.len() < concurrency.max(1) {
                let p = plan[next];
                let (client, id) = (self.clone(), id.to_string());
                set.spawn(async move {
                    let req = TileRequest {
                        iterations: Some(p.iterations),
                        tolerance: Some(p.tolerance),
                        ..TileRequest::new(p.address, encoding)
                    };
                    (next, client.tile(&id, &req).await)
                });
                next += 1;
            }
            let Some(done) = set.join_next().await else {
                break;
            };
            // Tasks are never cancelled, so a join error is a panic: pass it on.
            let (k, r) = done.unwrap_or_else(|e| std::panic::resume_unwind(e.into_panic()));
            on_tile(&plan[k], &r);
            out[k] = Some(r);
        }
        out.into_iter()
            .map(|r| r.expect("every planned tile was fetched"))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A made-up answer whose values approach 100 geometrically, like a contractive operator's
    /// iterates with contrast 1/2.
    struct Fake(f32, f32);
    impl Answer for Fake {
        fn values(&self) -> Vec<f32> {
            vec![self.0, f32::NAN]
        }
        fn convergence_bound(&self) -> f32 {
            self.1
        }
    }
    fn fake(n: u32) -> std::future::Ready<Result<Fake, ClientError>> {
        let e = 64.0 * 0.5f32.powi(n as i32);
        std::future::ready(Ok(Fake(100.0 - e, 2.0 * e)))
    }
    fn run<T>(f: impl Future<Output = T>) -> T {
        tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap()
            .block_on(f)
    }

    #[test]
    fn stops_on_the_bound_the_change_or_the_schedule() {
        let by_bound = RefineOptions {
            tolerance: Some(1.0),
            change: 0.0,
            ..Default::default()
        };
        let r = run(refine(&by_bound, 100.0, fake, |_| {})).unwrap();
        // The bound 128 / 2^n is under 1 first at n = 7.
        assert_eq!((r.stop, r.steps.len()), (Stop::Bound, 7));
        let by_change = RefineOptions::default();
        let r = run(refine(&by_change, 100.0, fake, |_| {})).unwrap();
        // The change 32 / 2^(n-1) ... is under 0.2 first at n = 9 (0.125); NaN is ignored.
        assert_eq!((r.stop, r.steps.len()), (Stop::Converged, 9));
        assert_eq!(r.steps[1].mean_change, Some(16.0));
        let short = RefineOptions {
            schedule: vec![1, 2, 4],
            change: 0.0,
            ..Default::default()
        };
        let mut seen = Vec::new();
        let r = run(refine(&short, 100.0, fake, |s| seen.push(s.iterations))).unwrap();
        assert_eq!((r.stop, seen), (Stop::Schedule, vec![1, 2, 4]));
    }

    #[test]
    fn a_spent_budget_stops_after_the_first_step() {
        let o = RefineOptions {
            budget: Some(Duration::ZERO),
            change: 0.0,
            ..Default::default()
        };
        let r = run(refine(&o, 100.0, fake, |_| {})).unwrap();
        assert_eq!((r.stop, r.steps.len()), (Stop::Budget, 1));
    }

    #[test]
    fn change_ignores_missing_values() {
        assert_eq!(
            mean_change(&[1.0, f32::NAN, 3.0], &[2.0, 5.0, 1.0]),
            Some(1.5)
        );
        assert_eq!(mean_change(&[f32::NAN], &[1.0]), None);
        assert_eq!(mean_change(&[1.0], &[1.0, 2.0]), None);
    }
}
