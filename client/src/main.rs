//! `fractile-client`: the command line of the thin client. Every command takes `--server URL`
//! (or `FRACTILE_SERVER`) and `--json` for machine-readable output.

mod args;
mod output;

use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::Parser;
use fractile_client::view::{Camera, PlanLimits};
use fractile_client::{
    Client, MeshRequest, PointsEncoding, PointsRequest, RegionRequest, TileAddress, TileEncoding,
    TileRequest, bench,
};
use serde_json::json;

use args::*;
use output::*;

fn main() -> std::process::ExitCode {
    // Rust ignores SIGPIPE, so `fractile-client ... | head` would panic on the closed pipe; a
    // command-line tool should just stop, as every Unix tool does (rust-lang/rust#62569).
    #[cfg(unix)]
    // SAFETY: restores the default disposition before any thread or I/O exists (the runtime
    // is built below).
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    let verbose = cli.verbose;
    let result = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(anyhow::Error::from)
        .and_then(|rt| rt.block_on(run(cli)));
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // One line by default: anyhow's Debug form adds a backtrace whenever
            // RUST_BACKTRACE is set, as it is in many Rust users' shells.
            if verbose {
                eprintln!("fractile-client: {e:?}");
            } else {
                eprintln!("fractile-client: {e:#}");
            }
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run(cli: Cli) -> Result<()> {
    let client = Client::new(&cli.server)?
        .with_token(cli.token.clone())
        .with_backend(cli.backend);
    let json = cli.json;
    match cli.command {
        Command::Assets => {
            let assets = client.assets().await?;
            if json {
                println!("{}", serde_json::to_string_pretty(&assets)?);
            } else {
                println!(
                    "| id | kind | size | bytes | ratio | PSNR dB |\n|---|---|---|---|---|---|"
                );
                for a in assets {
                    println!(
                        "| {} | {:?} | {}x{} | {} | {:.1} | {:.2} |",
                        a.id, a.kind, a.width, a.height, a.bytes, a.ratio, a.encode_psnr
                    );
                }
            }
        }
        Command::Info { id } => {
            let a = client.asset(&id).await?;
            println!("{}", serde_json::to_string_pretty(&a)?);
        }
        Command::Upload { file, id } => {
            let bytes =
                std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
            let up = client.upload(&id, bytes).await?;
            if json {
                println!("{}", json!({"created": up.created, "asset": up.summary}));
            } else {
                let verb = if up.created { "created" } else { "replaced" };
                println!(
                    "{verb} {} ({} bytes, {:.1}:1)",
                    up.summary.id, up.summary.bytes, up.summary.ratio
                );
            }
        }
        Command::Delete { id } => {
            client.delete(&id).await?;
            if json {
                println!("{}", json!({"deleted": id}));
            } else {
                println!("deleted {id}");
            }
        }
        Command::Tile(a) => tile(&client, json, a).await?,
        Command::Point(a) => point(&client, json, a).await?,
        Command::Points(a) => points(&client, json, a).await?,
        Command::Region(a) => region(&client, json, a).await?,
        Command::Mesh(a) => mesh(&client, json, a).await?,
        Command::View(a) => view(&client, json, a).await?,
        Command::Tileset { id, output } => {
            let f = client.fetch_tileset(&id, &output).await?;
            if json {
                println!(
                    "{}",
                    json!({"subtrees": f.subtrees, "contents": f.contents, "bytes": f.bytes,
                           "output": output})
                );
            } else {
                println!(
                    "{}: tileset.json, {} subtrees, {} tiles, {} bytes",
                    output.display(),
                    f.subtrees,
                    f.contents,
                    f.bytes
                );
            }
        }
        Command::Bench(a) => run_bench(&client, json, a).await?,
    }
    Ok(())
}

/// `tile`: fetches a tile (refined step by step with --refine).
async fn tile(client: &Client, json: bool, a: TileArgs) -> Result<()> {
    let TileArgs {
        id,
        z,
        x,
        y,
        output,
        encoding: enc,
        tile_size,
        precision,
        refine,
    } = a;
    let precision = precision
        .map(|p| p.parse::<fractile_client::Precision>())
        .transpose()
        .map_err(|e| anyhow::anyhow!(e))?;
    let req = TileRequest {
        iterations: refine.iterations,
        tile_size,
        precision,
        ..TileRequest::new(TileAddress { z, x, y }, {
            let by_name = output.extension().is_some_and(|e| e == "f32");
            let name = enc.unwrap_or_else(|| if by_name { "f32" } else { "png" }.into());
            encoding(&name)?
        })
    };
    if refine.refine {
        let mut steps = StepFiles::new(&output, json);
        let r = client
            .refine_tile(&id, &req, &refine.options(), |s| {
                steps.step(s, &s.answer.body)
            })
            .await?;
        let last = &r.steps.last().expect("at least one step").answer.body;
        steps.finish(last, r.stop)?;
    } else {
        let t = client.tile(&id, &req).await?;
        write(&output, &t.body)?;
        if json {
            println!(
                "{}",
                json!({"tile": t.address.to_string(), "bytes": t.body.len(), "convergence_bound": t.convergence_bound, "error_bound": t.error_bound, "ms": t.elapsed.as_secs_f64() * 1e3})
            );
        } else {
            println!(
                "{} -> {} ({} bytes, {})",
                t.address,
                output.display(),
                t.body.len(),
                bound_words(t.convergence_bound, t.error_bound)
            );
        }
    }
    Ok(())
}

/// `point`: prints the value at one point.
async fn point(client: &Client, json: bool, a: PointArgs) -> Result<()> {
    let PointArgs {
        id,
        lon,
        lat,
        unit,
        iterations,
    } = a;
    let p = if unit {
        client.point_unit(&id, lon, lat, iterations).await?
    } else {
        client.point_lonlat(&id, lon, lat, iterations).await?
    };
    if json {
        println!("{}", serde_json::to_string(&p)?);
    } else {
        let values: Vec<String> = p
            .values
            .iter()
            .flatten()
            .map(|v| v.map_or("nodata".into(), |v| v.to_string()))
            .collect();
        println!(
            "{} at {},{} ({}, {} steps)",
            values.join(" "),
            lon,
            lat,
            bound_words(p.convergence_bound.unwrap_or(f32::NAN), p.error_bound),
            p.iterations
        );
    }
    Ok(())
}

/// `points`: values at the points of a CSV file.
async fn points(client: &Client, json: bool, a: PointsArgs) -> Result<()> {
    let PointsArgs {
        id,
        file,
        output,
        binary,
        refine,
    } = a;
    let points = read_points(&file)?;
    let enc = if binary {
        PointsEncoding::Binary
    } else {
        PointsEncoding::Json
    };
    let resp = if refine.refine {
        print_head(json);
        let r = client
            .refine_points(&id, &points, enc, &refine.options(), |s| {
                print_step(json, s);
            })
            .await?;
        print_stop(json, r.stop);
        r.steps
            .into_iter()
            .last()
            .expect("at least one step")
            .answer
    } else {
        let req = PointsRequest {
            points,
            iterations: refine.iterations,
            tolerance: None,
        };
        client.points(&id, &req, enc).await?
    };
    let csv = points_csv(&resp);
    match output {
        Some(path) => write(&path, csv.as_bytes())?,
        None if json && !refine.refine => println!("{}", serde_json::to_string(&resp)?),
        None => print!("{csv}"),
    }
    Ok(())
}

/// `region`: fetches a region.
async fn region(client: &Client, json: bool, a: RegionArgs) -> Result<()> {
    let RegionArgs {
        id,
        bbox,
        width,
        height,
        format,
        output,
        refine,
    } = a;
    let req = RegionRequest {
        bbox: parse_numbers(&bbox, "bbox")?,
        width,
        height,
        iterations: refine.iterations,
        tolerance: None,
        format,
    };
    if refine.refine {
        let mut steps = StepFiles::new(&output, json);
        let r = client
            .refine_region(&id, &req, &refine.options(), |s| {
                steps.step(s, &s.answer.body)
            })
            .await?;
        let last = &r.steps.last().expect("at least one step").answer.body;
        steps.finish(last, r.stop)?;
    } else {
        let r = client.region(&id, &req).await?;
        write(&output, &r.body)?;
        if json {
            println!(
                "{}",
                json!({"bytes": r.body.len(), "convergence_bound": r.convergence_bound, "error_bound": r.error_bound})
            );
        } else {
            println!(
                "{}x{} -> {} ({})",
                width,
                height,
                output.display(),
                bound_words(r.convergence_bound, r.error_bound)
            );
        }
    }
    Ok(())
}

/// `mesh`: fetches a terrain mesh.
async fn mesh(client: &Client, json: bool, a: MeshArgs) -> Result<()> {
    let MeshArgs {
        id,
        bbox,
        resolution,
        format,
        iterations,
        max_error,
        output,
    } = a;
    let req = MeshRequest {
        bbox: bbox.map(|b| parse_numbers(&b, "bbox")).transpose()?,
        resolution,
        iterations,
        tolerance: None,
        max_error,
        format,
    };
    let m = client.mesh(&id, &req).await?;
    write(&output, &m.body)?;
    if json {
        println!(
            "{}",
            json!({"bytes": m.body.len(), "content_type": m.content_type, "convergence_bound": m.convergence_bound, "error_bound": m.error_bound})
        );
    } else {
        println!(
            "{} -> {} ({} bytes, {})",
            m.content_type,
            output.display(),
            m.body.len(),
            bound_words(m.convergence_bound, m.error_bound)
        );
    }
    Ok(())
}

/// `view`: plans and fetches the tiles a camera sees.
async fn view(client: &Client, json: bool, a: ViewArgs) -> Result<()> {
    let ViewArgs {
        id,
        camera,
        bbox,
        pixel_error,
        max_tiles,
        concurrency,
        encoding: enc,
        plan_only,
        output,
    } = a;
    let [lon, lat, h] = parse_numbers(&camera, "camera")?;
    let asset = client.asset(&id).await?;
    let tj = client.tilejson(&id).await?;
    let region = match bbox {
        Some(b) => parse_numbers(&b, "bbox")?,
        None => tj.bounds,
    };
    let cam = Camera {
        pixel_error,
        ..Camera::new(lon, lat, h)
    };
    let limits = PlanLimits {
        min_zoom: tj.minzoom,
        max_zoom: tj.maxzoom,
        max_tiles,
        ..Default::default()
    };
    let plan = fractile_client::view::plan(&cam, region, &asset, limits)?;
    let enc = encoding(&enc)?;
    if !json {
        println!(
            "| tile | distance m | tolerance | iterations | convergence bound | ms |\n|---|---|---|---|---|---|"
        );
    }
    let row = |p: &fractile_client::view::PlannedTile, bound: Option<f32>, ms: Option<f64>| {
        if json {
            println!(
                "{}",
                json!({"tile": p.address.to_string(), "distance": p.distance, "tolerance": p.tolerance, "iterations": p.iterations, "convergence_bound": bound, "ms": ms})
            );
        } else {
            let b = bound.map_or("-".into(), |b| format!("{b:.3}"));
            let ms = ms.map_or("-".into(), |m| format!("{m:.1}"));
            println!(
                "| {} | {:.0} | {:.3} | {} | {b} | {ms} |",
                p.address, p.distance, p.tolerance, p.iterations
            );
        }
    };
    if plan_only {
        plan.iter().for_each(|p| row(p, None, None));
        return Ok(());
    }
    let ext = if enc == TileEncoding::F32 {
        "f32"
    } else {
        "png"
    };
    let mut failures = 0;
    let results = client
        .fetch_view(&id, &plan, enc, concurrency, |p, r| match r {
            Ok(t) => row(
                p,
                Some(t.convergence_bound),
                Some(t.elapsed.as_secs_f64() * 1e3),
            ),
            Err(e) => {
                failures += 1;
                eprintln!("{}: {e}", p.address);
            }
        })
        .await;
    if let Some(dir) = output {
        for t in results.iter().flatten() {
            let a = t.address;
            let folder = dir.join(a.z.to_string()).join(a.x.to_string());
            std::fs::create_dir_all(&folder)
                .with_context(|| format!("creating {}", folder.display()))?;
            write(&folder.join(format!("{}.{ext}", a.y)), &t.body)?;
        }
    }
    if failures > 0 {
        bail!("{failures} of {} tiles failed", plan.len());
    }
    Ok(())
}

/// `bench`: runs the load generator.
async fn run_bench(client: &Client, json: bool, a: BenchArgs) -> Result<()> {
    let BenchArgs {
        asset,
        concurrency,
        duration,
        kinds,
        batch,
        encoding: heights,
    } = a;
    let kinds = kinds
        .iter()
        .map(|k| bench::Kind::parse(k).with_context(|| format!("unknown kind {k:?}")))
        .collect::<Result<Vec<_>>>()?;
    if !(duration > 0.0 && duration <= 3600.0) {
        bail!("duration must be in (0, 3600] seconds");
    }
    let options = bench::BenchOptions {
        asset,
        concurrency,
        duration: Duration::from_secs_f64(duration),
        kinds,
        batch,
        heights: encoding(&heights)?,
        ..Default::default()
    };
    let reports = bench::run(client, &options).await?;
    if json {
        println!("{}", serde_json::to_string_pretty(&reports)?);
    } else {
        print!("{}", bench::table(&reports, concurrency));
        for r in reports.iter().filter(|r| r.errors > 0) {
            eprintln!(
                "{:?}: first error: {}",
                r.kind,
                r.first_error.as_deref().unwrap_or("?")
            );
        }
    }
    Ok(())
}
