//! `fractile encode` of the inputs that are not rasters: meshes (IFS3D on a signed distance
//! volume) and GeoJSON curves (projected IFS with details).

use std::path::Path;

use anyhow::{Context, Result, bail};
use serde_json::json;

use super::args::EncodeArgs;
/// Whether a path names a mesh (by extension).
pub(crate) fn is_mesh(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["off", "obj", "ply", "stl"].contains(&e.to_ascii_lowercase().as_str()))
}

/// `fractile encode mesh.off --grid N [--tolerance T | --transforms N]`: IFS3D. The octree's
/// ranges are 4 to 16 voxels and its quantiser is its own (`fit::VolumeSettings`); the
/// raster flags of range sizes and bits do not apply.
pub(crate) fn encode_volume(a: &EncodeArgs) -> Result<()> {
    use fractile_codec::codecs::ifs3d::Partition3;
    if a.target_bpp.is_some() || a.codec.is_some() {
        bail!("meshes take --grid, --band and --tolerance (voxels), --transforms or --const-range");
    }
    let input = a.input()?;
    let mesh = fractile_codec::mesh::Mesh::read(input)?;
    let mut s = fractile_codec::encode::volume::MeshSettings {
        grid: a.grid,
        band: a.band,
        ..Default::default()
    };
    s.codec.partition = match (a.tolerance, a.transforms, a.const_range) {
        (Some(t), ..) if !(t.is_finite() && t > 0.0) => bail!("--tolerance {t} must be positive"),
        // Voxels -> normalised units: the field spans 2 band voxels.
        (Some(t), ..) => Partition3::Tolerance(t / (2.0 * a.band) as f32),
        (_, Some(n), _) => Partition3::Transforms(n),
        (.., Some(r)) => {
            let sizes: Vec<u32> = (0..s.codec.levels).map(|l| s.codec.min_size << l).collect();
            match sizes.iter().position(|&n| n == r) {
                Some(l) => Partition3::ConstRange(l),
                None => bail!("--const-range {r}: the octree's ranges are {sizes:?} voxels"),
            }
        }
        // 0.08 voxel RMS collage error: the bench's setting, past the seed's quality bars.
        _ => Partition3::Tolerance((0.08 / (2.0 * a.band)) as f32),
    };
    let name = input
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut bar = crate::progress::Progress::start("coding the volume", a.quiet || a.json);
    let enc = fractile_codec::encode::volume::encode_mesh(&mesh, &s, &name)?;
    bar.finish();
    fractile_codec::asset::write_atomic(&a.output, &enc.bytes)?;
    let file_bytes = std::fs::metadata(input).map(|m| m.len()).unwrap_or(0);
    let report = json!({
        "input": input, "output": a.output, "codec": enc.asset.codec_name(),
        "grid": enc.field.size, "band_voxels": a.band, "voxel": enc.field.voxel,
        "bytes": enc.bytes.len(), "ratio_i8": enc.ratio_i8(), "ratio_f32": enc.ratio_f32(),
        "ratio_mesh_file": file_bytes as f64 / enc.bytes.len() as f64,
        "transforms": enc.asset.meta.stats.transforms, "seconds": enc.seconds,
        "field_seconds": enc.field_seconds, "psnr": enc.psnr(), "rmse": enc.asset.meta.stats.rmse,
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} -> {}: ifs3d-octree {}^3, {} bytes, {:.2}:1 against i8 ({:.2}:1 f32, {:.2}:1 the mesh file), {} maps, {:.2} s ({:.2} s distance field), PSNR {:.2} dB",
            input.display(),
            a.output.display(),
            enc.field.size,
            enc.bytes.len(),
            enc.ratio_i8(),
            enc.ratio_f32(),
            file_bytes as f64 / enc.bytes.len() as f64,
            enc.asset.meta.stats.transforms,
            enc.seconds,
            enc.field_seconds,
            enc.psnr()
        );
    }
    Ok(())
}

/// Whether a path names GeoJSON (by extension).
pub(crate) fn is_geojson(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["geojson", "json"].contains(&e.to_ascii_lowercase().as_str()))
}

/// `fractile encode coast.geojson -o coast.fra [--codec curve] [--tolerance T]`.
pub(crate) fn encode_curve(a: &EncodeArgs) -> Result<()> {
    if !matches!(a.codec.as_deref(), None | Some("curve"))
        || a.target_bpp.is_some()
        || a.transforms.is_some()
        || a.const_range.is_some()
    {
        bail!("GeoJSON takes --codec curve and --tolerance (degrees of arc; 0 keeps every detail)");
    }
    let input = a.input()?;
    let tolerance = f64::from(a.tolerance.unwrap_or(0.0));
    if !(tolerance.is_finite() && tolerance >= 0.0) {
        bail!("--tolerance {tolerance} must be a distance >= 0");
    }
    let text =
        std::fs::read_to_string(input).with_context(|| format!("reading {}", input.display()))?;
    let lines = fractile_codec::codecs::curve::geojson::read(&text)?;
    let settings = fractile_codec::codecs::curve::CurveSettings {
        tolerance,
        ..Default::default()
    };
    let name = input
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut bar = crate::progress::Progress::start("coding the curves", a.quiet || a.json);
    let enc = fractile_codec::encode::curve::encode_asset(&lines, &settings, &name)?;
    bar.finish();
    fractile_codec::asset::write_atomic(&a.output, &enc.bytes)?;
    let set = &enc.asset.curves().expect("a curve asset").set;
    let m = &enc.asset.meta;
    let report = json!({
        "input": input, "output": a.output, "codec": enc.asset.codec_name(),
        "polylines": set.rings.len(), "points": enc.points, "bytes": enc.bytes.len(),
        "ratio_f64": (enc.points * 16) as f64 / enc.bytes.len() as f64,
        "ratio_f32": (enc.points * 8) as f64 / enc.bytes.len() as f64,
        "tolerance_degrees": tolerance,
        "tolerance_m": tolerance * fractile_codec::codecs::curve::METRES_PER_DEGREE,
        "hausdorff_m": m.stats.max_error * fractile_codec::codecs::curve::METRES_PER_DEGREE,
        "finest_level": set.finest(), "fit": enc.fit, "seconds": m.stats.seconds,
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} -> {}: {} polylines, {} points, {} bytes ({:.2}:1 vs float32, {:.2}:1 vs float64), Hausdorff distance to the source {:.0} m, {} levels, {:.2} s",
            input.display(),
            a.output.display(),
            set.rings.len(),
            enc.points,
            enc.bytes.len(),
            report["ratio_f32"].as_f64().unwrap_or(0.0),
            report["ratio_f64"].as_f64().unwrap_or(0.0),
            report["hausdorff_m"].as_f64().unwrap_or(0.0),
            set.finest(),
            m.stats.seconds
        );
    }
    Ok(())
}
