//! What the commands print and write: numbers parsed from flags, steps of a refinement in
//! words or JSON, files per step, points as CSV.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use fractile_client::TileEncoding;
use fractile_client::refine::{Step, Stop};
use serde_json::json;

pub(crate) fn parse_numbers<const N: usize>(s: &str, what: &str) -> Result<[f64; N]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("{what} {s:?}: not numbers"))?;
    v.try_into()
        .map_err(|_| anyhow::anyhow!("{what} {s:?}: expected {N} comma-separated numbers"))
}

pub(crate) fn encoding(name: &str) -> Result<TileEncoding> {
    TileEncoding::parse(name).with_context(|| {
        format!("unknown encoding {name:?} (png, terrarium, terrainrgb, gray16, f32)")
    })
}

/// `out.png` -> `out.step03.png`.
pub(crate) fn step_path(out: &Path, step: usize) -> PathBuf {
    let stem = out.file_stem().and_then(|s| s.to_str()).unwrap_or("out");
    let name = match out.extension().and_then(|e| e.to_str()) {
        Some(ext) => format!("{stem}.step{step:02}.{ext}"),
        None => format!("{stem}.step{step:02}"),
    };
    out.with_file_name(name)
}

pub(crate) fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// Refinement steps of a file answer (tiles, regions): each written beside the output as it
/// arrives (`out.step01.png`, ...) and printed, the last also written to the output itself.
pub(crate) struct StepFiles<'a> {
    pub(crate) output: &'a Path,
    pub(crate) json: bool,
    pub(crate) failed: Option<anyhow::Error>,
}

impl<'a> StepFiles<'a> {
    pub(crate) fn new(output: &'a Path, json: bool) -> StepFiles<'a> {
        print_head(json);
        StepFiles {
            output,
            json,
            failed: None,
        }
    }

    /// Writes and prints a step; the first write error is kept for `finish`.
    pub(crate) fn step<T>(&mut self, s: &Step<T>, body: &[u8]) {
        if let Err(e) = write(&step_path(self.output, s.step), body) {
            self.failed.get_or_insert(e);
        }
        print_step(self.json, s);
    }

    pub(crate) fn finish(self, last: &[u8], stop: Stop) -> Result<()> {
        if let Some(e) = self.failed {
            return Err(e);
        }
        write(self.output, last)?;
        print_stop(self.json, stop);
        Ok(())
    }
}

/// "convergence bound C, error bound E" (or "error bound unknown" for an asset without a
/// source-error map).
pub(crate) fn bound_words(convergence: f32, error: Option<f32>) -> String {
    match error {
        Some(e) => format!("convergence bound {convergence}, error bound {e}"),
        None => format!("convergence bound {convergence}, error bound unknown"),
    }
}

/// Prints one refinement step as it arrives: a table row, or one JSON object per line (the
/// last carries why it is the last in `stop`; the others have `stop: null`).
pub(crate) fn print_step<T>(json: bool, s: &Step<T>) {
    let ms = s.elapsed.as_secs_f64() * 1e3;
    if json {
        println!(
            "{}",
            json!({"step": s.step, "iterations": s.iterations, "convergence_bound": s.convergence_bound,
                   "mean_change": s.mean_change, "ms": ms, "stop": s.stop})
        );
    } else {
        let change = s.mean_change.map_or("-".to_string(), |c| format!("{c:.4}"));
        println!(
            "| {} | {} | {:.4} | {change} | {ms:.1} |",
            s.step, s.iterations, s.convergence_bound
        );
    }
}

pub(crate) fn print_head(json: bool) {
    if !json {
        println!(
            "| step | iterations | convergence bound | mean change | ms |\n|---|---|---|---|---|"
        );
    }
}

pub(crate) fn print_stop(json: bool, stop: Stop) {
    if !json {
        let why = match stop {
            Stop::Bound => "the convergence bound reached the tolerance",
            Stop::Converged => "the answer stopped changing",
            Stop::Budget => "the time budget ran out",
            Stop::Schedule => "the schedule ended",
        };
        println!("stopped: {why}");
    }
}

pub(crate) fn read_points(path: &Path) -> Result<Vec<[f64; 2]>> {
    let mut r = csv::ReaderBuilder::new()
        .has_headers(false)
        .trim(csv::Trim::All)
        .from_path(path)
        .with_context(|| format!("reading {}", path.display()))?;
    let mut out = Vec::new();
    for (k, rec) in r.records().enumerate() {
        let rec = rec.with_context(|| format!("{}: row {}", path.display(), k + 1))?;
        let nums: Option<Vec<f64>> = rec.iter().take(2).map(|f| f.parse().ok()).collect();
        match nums {
            Some(v) if v.len() == 2 => out.push([v[0], v[1]]),
            // A first row that is not numbers is a header.
            _ if k == 0 => {}
            _ => bail!("{}: row {} is not two numbers", path.display(), k + 1),
        }
    }
    Ok(out)
}

pub(crate) fn points_csv(resp: &fractile_client::PointsResponse) -> String {
    let channels = resp
        .results
        .iter()
        .filter_map(|r| r.values.as_ref().map(Vec::len))
        .max()
        .unwrap_or(1);
    let mut s = String::from("x,y");
    for c in 0..channels {
        s += &format!(",value{c}");
    }
    s += ",error_bound,iterations\n";
    for r in &resp.results {
        s += &format!("{},{}", r.coordinates[0], r.coordinates[1]);
        for c in 0..channels {
            let v = r.values.as_ref().and_then(|v| v.get(c).copied().flatten());
            s += &v.map_or(",".into(), |v| format!(",{v}"));
        }
        s += &r.error_bound.map_or(",".into(), |b| format!(",{b}"));
        s += &format!(",{}\n", r.iterations);
    }
    s
}
