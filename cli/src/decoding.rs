//! `fractile decode`, `mesh` and `curve`: assets back to rasters, meshes and GeoJSON.

use super::*;

#[derive(clap::Args)]
pub(crate) struct CurveArgs {
    /// The curve asset.
    asset: PathBuf,
    /// Output GeoJSON file.
    #[arg(short, long)]
    output: PathBuf,
    /// Level: 0 is the coarsest, the default the input's finest; deeper levels continue the
    /// details self-similarly.
    #[arg(long)]
    level: Option<usize>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
pub(crate) struct MeshArgs {
    /// The volume asset.
    asset: PathBuf,
    /// Output: .obj, .ply or .glb.
    #[arg(short, long)]
    output: PathBuf,
    /// Samples along the box's longest side [default: the encoded grid].
    #[arg(long)]
    resolution: Option<usize>,
    /// Box `x0,y0,z0,x1,y1,z1` in the mesh's units [default: the whole grid]; it may start
    /// with a minus sign (`--bbox -0.5,-0.5,-0.5,0,0,0.2`).
    #[arg(long, value_parser = parse_box3, allow_hyphen_values = true)]
    bbox: Option<([f64; 3], [f64; 3])>,
    /// Inverse steps of continuous decoding.
    #[arg(long, default_value_t = 16)]
    iterations: u32,
    /// Where the box is decoded: cpu, gpu (fails without an adapter), or auto (the GPU for a
    /// million samples or more when a hardware adapter exists, else the CPU).
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    backend: BackendArg,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

pub(crate) fn parse_box3(s: &str) -> Result<([f64; 3], [f64; 3]), String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>().map_err(|e| format!("{x:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x0, y0, z0, x1, y1, z1] if x1 > x0 && y1 > y0 && z1 > z0 => {
            Ok(([x0, y0, z0], [x1, y1, z1]))
        }
        _ => Err("expected x0,y0,z0,x1,y1,z1 with max > min on every axis".into()),
    }
}

#[derive(clap::Args)]
pub(crate) struct DecodeArgs {
    /// The asset file.
    asset: PathBuf,
    /// Output: .png or .tif/.tiff (float32 GeoTIFF, height fields).
    #[arg(short, long)]
    output: PathBuf,
    /// Scale factor against the source size (any positive real).
    #[arg(long, conflicts_with_all = ["width", "height"])]
    scale: Option<f32>,
    /// Output width (height follows the aspect ratio unless given).
    #[arg(long)]
    width: Option<usize>,
    /// Output height.
    #[arg(long)]
    height: Option<usize>,
    /// Iterations (discrete) or inverse steps (continuous); default: until converged.
    #[arg(long)]
    iterations: Option<u32>,
    /// Window `u0,v0,u1,v1` of the unit square (default: all of it).
    #[arg(long, value_parser = parse_window)]
    window: Option<[f32; 4]>,
    /// Decoding method.
    #[arg(long, value_enum, default_value_t = MethodArg::Auto)]
    method: MethodArg,
    /// Where continuous decoding runs: cpu, gpu (fails without an adapter), or auto (the GPU
    /// for windows of a million pixels or more when a hardware adapter exists, else the CPU;
    /// never a software rasteriser such as lavapipe, slower than the CPU).
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    backend: BackendArg,
}

/// The GPU a decode runs on: `gpu` asks for one (an error without it); `auto` takes one for work
/// that pays for the transfer (`big`), and only a hardware adapter: a software one (Mesa's
/// lavapipe, where it is the only adapter) measured 1.85 s against the CPU's 0.8 s for etopo5
/// at its own size, as the server's `auto` already knew.
fn gpu_for(backend: BackendArg, big: bool) -> Result<Option<fractile_gpu::Gpu>> {
    match backend {
        BackendArg::Cpu => Ok(None),
        BackendArg::Gpu => Ok(Some(fractile_gpu::Gpu::new()?)),
        // No hardware to find: no probe (see `Gpu::hardware_may_exist`).
        BackendArg::Auto if !big || !fractile_gpu::Gpu::hardware_may_exist() => Ok(None),
        BackendArg::Auto => match fractile_gpu::Gpu::new() {
            Ok(g) if !g.is_software() => Ok(Some(g)),
            Ok(_) => Ok(None),
            Err(e) => {
                eprintln!("fractile: no GPU ({e}), decoding on the CPU");
                Ok(None)
            }
        },
    }
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum BackendArg {
    Cpu,
    Gpu,
    Auto,
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum MethodArg {
    Auto,
    Discrete,
    Continuous,
}

pub(crate) fn parse_window(s: &str) -> Result<[f32; 4], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|v| v.trim().parse::<f32>().map_err(|e| e.to_string()))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [a, b, c, d]
            if (0.0..=1.0).contains(&a)
                && (0.0..=1.0).contains(&b)
                && c > a
                && d > b
                && c <= 1.0
                && d <= 1.0 =>
        {
            Ok([a, b, c, d])
        }
        _ => Err("expected u0,v0,u1,v1 with 0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1".into()),
    }
}

pub(crate) fn run_mesh(a: MeshArgs) -> Result<()> {
    let asset = Asset::read(&a.asset)?;
    let Some(volume) = asset.volume() else {
        bail!(
            "{} is not a volume asset (terrain meshes: the server's /v1/assets/{{id}}/mesh)",
            a.asset.display()
        );
    };
    let resolution = a.resolution.unwrap_or(volume.size());
    if !(2..=1024).contains(&resolution) {
        bail!("--resolution {resolution} must be 2..=1024");
    }
    let ext = a
        .output
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    if !["obj", "ply", "glb"].contains(&ext.as_str()) {
        bail!(
            "output {} must end in .obj, .ply or .glb",
            a.output.display()
        );
    }
    let started = Instant::now();
    let samples = resolution.pow(3);
    let gpu = gpu_for(a.backend, samples >= 1 << 20)?;
    let device = match &gpu {
        Some(g) => Some((g, g.upload_volume(&volume.operator)?)),
        None => None,
    };
    let on_gpu = |lo, hi, dims: [usize; 3], n, t| {
        let (g, op) = device.as_ref()?;
        let g = g
            .volume_grid_values(op, lo, hi, dims.map(|d| d as u32), n, t)
            .ok()?;
        Some((g.values, g.error_bound))
    };
    let (mesh, bound) =
        asset.volume_mesh_with(a.bbox, resolution, a.iterations, 0.0, Some(&on_gpu))?;
    let body = match ext.as_str() {
        "obj" => mesh.to_obj(),
        "ply" => mesh.to_ply(),
        _ => mesh.to_glb(),
    };
    fractile_codec::asset::write_atomic(&a.output, &body)?;
    let report = json!({
        "output": a.output, "resolution": resolution, "vertices": mesh.positions.len(),
        "triangles": mesh.triangles.len(), "error_bound": bound, "seconds": started.elapsed().as_secs_f64(),
        "backend": if device.is_some() { "gpu" } else { "cpu" },
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{}: {} vertices, {} triangles at resolution {resolution}, distance error bound {bound:.3e}, {:.2} s",
            a.output.display(),
            mesh.positions.len(),
            mesh.triangles.len(),
            started.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

/// `fractile curve coast.fra -o out.geojson [--level N]`.
pub(crate) fn run_curve(a: CurveArgs) -> Result<()> {
    let asset = Asset::read(&a.asset)?;
    let Some(c) = asset.curves() else {
        bail!(
            "{} is not a curve asset (it is {:?})",
            a.asset.display(),
            asset.meta.kind
        );
    };
    let finest = c.set.finest();
    let level = a.level.unwrap_or(finest);
    // Each level doubles the points: refuse what would not fit in memory before decoding.
    if c.set.points_at(level) > 1 << 26 {
        bail!("level {level} would have over 2^26 points (the finest is {finest})");
    }
    let decoded = c.set.at_level(level);
    let units = asset.meta.units.clone().unwrap_or_default();
    let text = fractile_codec::codecs::curve::geojson::write(&decoded, finest, &units);
    fractile_codec::asset::write_atomic(&a.output, &text)?;
    let points: usize = decoded.lines.iter().map(Vec::len).sum();
    let report = json!({"output": a.output, "level": level, "finest_level": finest,
        "polylines": decoded.lines.len(), "points": points, "error_bound": decoded.error_bound,
        "units": units});
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} -> {}: level {level} of {finest}, {} polylines, {points} points, error bound {} {units}",
            a.asset.display(),
            a.output.display(),
            decoded.lines.len(),
            decoded.error_bound
        );
    }
    Ok(())
}

pub(crate) fn run_decode(a: DecodeArgs) -> Result<()> {
    let asset = Asset::read(&a.asset)?;
    if asset.volume().is_some() {
        bail!(
            "{} is a volume: extract its surface with `fractile mesh`",
            a.asset.display()
        );
    }
    if asset.curves().is_some() {
        bail!(
            "{} holds curves: decode them to GeoJSON with `fractile curve {} -o out.geojson`",
            a.asset.display(),
            a.asset.display()
        );
    }
    let (sw, sh) = (asset.meta.width as f32, asset.meta.height as f32);
    let window = a.window.unwrap_or([0.0, 0.0, 1.0, 1.0]);
    let (ww, wh) = ((window[2] - window[0]) * sw, (window[3] - window[1]) * sh);
    let (width, height) = match (a.scale, a.width, a.height) {
        (Some(s), ..) if s > 0.0 && s.is_finite() => {
            ((ww * s).round() as usize, (wh * s).round() as usize)
        }
        (Some(s), ..) => bail!("scale {s} must be a positive number"),
        (None, Some(w), Some(h)) => (w, h),
        (None, Some(w), None) => (w, (w as f32 * wh / ww).round() as usize),
        (None, None, Some(h)) => ((h as f32 * ww / wh).round() as usize, h),
        (None, None, None) => (ww.round() as usize, wh.round() as usize),
    };
    if width == 0 || height == 0 {
        bail!("output size {width}x{height} must be at least 1x1");
    }
    // The codec's rule for any read (Python's too), on the GPU's path as well: the size is
    // checked before anything is made.
    asset.check_read(width, height, &fractile_codec::AssetLimits::default())?;
    let started = Instant::now();
    let method = match a.method {
        MethodArg::Auto => Method::Auto,
        MethodArg::Discrete => Method::Discrete,
        MethodArg::Continuous => Method::Continuous,
    };
    // The GPU runs continuous decoding: asked for, or (auto) a continuous-capable request of a
    // million pixels or more, where the transfer pays for itself. A chunked asset's pixels
    // are always continuous (see `Asset::window`).
    let continuous = method != Method::Discrete || asset.chunked().is_some();
    let gpu = gpu_for(a.backend, continuous && width * height >= 1 << 20)?;
    let (decoded, used, backend) = if let (Some(g), Some(_)) = (&gpu, &asset.chunked()) {
        let d = chunks_on(g, &asset, window, (width, height), (a.iterations, method))?;
        (d, Method::Continuous, g.adapter())
    } else if let Some(g) = &gpu {
        // As many steps as the CPU's continuous window takes by default.
        let n = a.iterations.unwrap_or(12);
        let mut planes = Vec::new();
        for p in asset.planes() {
            let dev = g.upload_flat(&fractile_codec::pieces::Flatten::flat(&p.operator))?;
            let grid = fractile_gpu::Grid::Window {
                rect: window,
                width: width as u32,
                height: height as u32,
            };
            // Values alone: 4 bytes a point cross from the device instead of 16.
            planes.push(g.grid_values(&dev, grid, n, 0.0)?.values);
        }
        let d = asset.window_from_planes(window, width, height, planes);
        (d, Method::Continuous, g.adapter())
    } else {
        // What Python's `Asset.read` makes too.
        let (d, m) = asset.raster(a.window, width, height, a.iterations, method)?;
        (d, m, "CPU".into())
    };
    write_decoded(&asset, &decoded, window, &a.output)?;
    eprintln!(
        "decoded {}x{} ({used:?}, {backend}) in {:.1} ms -> {}",
        width,
        height,
        started.elapsed().as_secs_f64() * 1e3,
        a.output.display()
    );
    Ok(())
}

/// A chunked asset's window with each chunk's chains decoded on `gpu`: a window visits each
/// chunk's planes once, so each operator is uploaded when its chains arrive and dropped after.
/// The first device error fails the decode rather than leave the rest to the CPU unasked.
fn chunks_on(
    gpu: &fractile_gpu::Gpu,
    asset: &Asset,
    window: [f32; 4],
    (width, height): (usize, usize),
    steps: (Option<u32>, Method),
) -> Result<fractile_codec::extract::Decoded> {
    let failed = std::sync::Mutex::new(None);
    let hook = |p: fractile_codec::extract::PlaneRef<'_>,
                sites: fractile_codec::extract::Sites<'_>,
                n,
                t| {
        let answer = gpu
            .upload_flat(&fractile_codec::pieces::Flatten::flat(p.operator))
            .and_then(|op| gpu.answer(&op, sites, n, t));
        match answer {
            Ok(a) => Some(a),
            Err(e) => {
                failed.lock().unwrap().get_or_insert(e);
                None
            }
        }
    };
    let (d, _) = asset.window_with(window, width, height, steps, &hook);
    match failed.into_inner().unwrap() {
        Some(e) => Err(e.into()),
        None => Ok(d),
    }
}

pub(crate) fn write_decoded(
    asset: &Asset,
    d: &fractile_codec::extract::Decoded,
    window: [f32; 4],
    out: &Path,
) -> Result<()> {
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let m = &asset.meta;
    match (ext.as_str(), m.kind) {
        ("tif" | "tiff", AssetKind::HeightField) => {
            let georef = m.georef.as_ref().map(|g| {
                let sx = (window[2] - window[0]) as f64 * m.width as f64 / d.width as f64;
                let sy = (window[3] - window[1]) as f64 * m.height as f64 / d.height as f64;
                fractile_proto::Georef {
                    epsg: g.epsg,
                    origin: [
                        g.origin[0] + window[0] as f64 * m.width as f64 * g.pixel_size[0],
                        g.origin[1] + window[1] as f64 * m.height as f64 * g.pixel_size[1],
                    ],
                    pixel_size: [g.pixel_size[0] * sx, g.pixel_size[1] * sy],
                }
            });
            let nodata = m.nodata.unwrap_or(f64::NAN);
            let values: Vec<f32> = d.channels[0]
                .iter()
                .map(|&v| if v.is_nan() { nodata as f32 } else { v })
                .collect();
            raster::write_geotiff_f32(
                out,
                d.width,
                d.height,
                &values,
                georef.as_ref(),
                // A chunked asset's masks are its chunks': the tag goes with any cell written
                // as nodata, or rasterio would read -32768 as a height.
                (asset.mask().is_some() || d.channels[0].iter().any(|v| v.is_nan()))
                    .then_some(nodata),
            )?;
        }
        ("tif" | "tiff", _) => bail!("GeoTIFF output is for height fields; write a .png"),
        ("png", AssetKind::HeightField) => {
            // U16 sources keep their own values; others map the value range onto 0..=65535.
            let (lo, span) = (m.value_min as f32, (m.value_max - m.value_min) as f32);
            let values: Vec<f32> = d.channels[0]
                .iter()
                .map(|&v| match (v.is_nan(), m.sample) {
                    (true, _) => 0.0,
                    (false, SampleFormat::U16) => v,
                    _ => (v - lo) / span * 65535.0,
                })
                .collect();
            raster::write_png16(out, d.width, d.height, &values)?;
        }
        ("png", _) => raster::write_png8(out, d.width, d.height, &d.channels)?,
        _ => bail!("unknown output type {:?}: use .png or .tif", out.display()),
    }
    Ok(())
}
