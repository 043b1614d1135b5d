//! IFS3D bench (issue 5): meshes to distance fields to octree IFS and back, the seed's Table 1
//! measured our way. Prints one table row per (mesh, grid):
//!
//! asset bytes; ratio against the signed-byte volume of the grid (the seed's baseline), against
//! the float32 volume and against the source mesh file; encode seconds (distance field
//! included, in parentheses alone); PSNR of the decoded field (peak = field range); symmetric
//! Chamfer and Hausdorff distances between the decoded mesh (marching over the continuous decode
//! at the grid's resolution) and the source mesh, in % of the source's bounding-box diagonal.
//!
//! `cargo bench -p fractile-codec --bench volume`. Meshes come from `../shared/data/mesh` when it
//! is there (bunny and dragon are not in the repo), else from `testdata/mesh`.
//! `FRACTILE_TOL` (voxels) overrides the collage tolerance of every row, `FRACTILE_MIN` the
//! smallest range (with four levels), `FRACTILE_ONLY=bunny.off:64` runs one row.

use std::path::{Path, PathBuf};

use fractile_codec::codecs::ifs3d::Partition3;
use fractile_codec::codecs::ifs3d::volume::surface_distance;
use fractile_codec::encode::volume::{MeshSettings, encode_mesh};
use fractile_codec::mesh::Mesh;

fn find(name: &str) -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    [
        root.join("../shared/data/mesh").join(name),
        root.join("testdata/mesh").join(name),
    ]
    .into_iter()
    .find(|p| p.exists())
}

fn main() {
    let rows: &[(&str, usize, f64)] = &[
        ("bunny.off", 64, 0.08),
        ("bunny.off", 128, 0.08),
        ("fandisk.off", 128, 0.08),
        ("ChineseDragon-10kv.off", 128, 0.08),
        ("knot2.off", 128, 0.08),
    ];
    let tol_override: Option<f64> = std::env::var("FRACTILE_TOL")
        .ok()
        .and_then(|v| v.parse().ok());
    println!(
        "| mesh | grid | bytes | ratio vs i8 | vs f32 | vs mesh file | encode s (field) | PSNR dB | in band | Chamfer % diag | Hausdorff % diag | maps |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    // FRACTILE_ONLY=name:grid runs one row (tuning).
    let only = std::env::var("FRACTILE_ONLY").ok();
    let min_size: Option<u32> = std::env::var("FRACTILE_MIN")
        .ok()
        .and_then(|v| v.parse().ok());
    for &(name, grid, tol) in rows {
        if only
            .as_ref()
            .is_some_and(|o| *o != format!("{name}:{grid}"))
        {
            continue;
        }
        let Some(path) = find(name) else {
            println!("| {name} | {grid} | (not found) | | | | | | | | | |");
            continue;
        };
        let mesh = Mesh::read(&path).expect("mesh");
        let file_bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
        let mut s = MeshSettings {
            grid,
            ..Default::default()
        };
        let tol = tol_override.unwrap_or(tol);
        if let Some(m) = min_size {
            s.codec.min_size = m;
            s.codec.levels = 4;
        }
        // Tolerance in voxels -> normalised units (the field spans 2 band voxels).
        s.codec.partition = Partition3::Tolerance((tol / (2.0 * s.band)) as f32);
        let enc = encode_mesh(&mesh, &s, name).expect("encode");
        let (decoded, _) = enc.asset.volume_mesh(None, grid, 16, 0.0).expect("mesh");
        let (lo, hi) = mesh.bounds();
        let diag = (0..3)
            .map(|k| ((hi[k] - lo[k]) as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        let d = surface_distance(&decoded, &mesh, 200_000);
        // PSNR over the band alone (|d| < band), same peak: the whole-grid figure counts the
        // clamped voxels, which every codec gets exactly.
        let native = enc.asset.distance_field_native().expect("native");
        let band = enc.field.band as f32;
        let (mut se, mut k) = (0.0f64, 0usize);
        for (a, b) in native.iter().zip(&enc.field.values) {
            if b.abs() < band {
                se += ((a - b) as f64).powi(2);
                k += 1;
            }
        }
        let in_band = 10.0 * ((2.0 * band as f64).powi(2) / (se / k as f64)).log10();
        println!(
            "| {name} | {grid} | {} | {:.2} | {:.2} | {:.2} | {:.2} ({:.2}) | {:.2} | {:.2} | {:.3} | {:.3} | {} |",
            enc.bytes.len(),
            enc.ratio_i8(),
            enc.ratio_f32(),
            file_bytes as f64 / enc.bytes.len() as f64,
            enc.seconds,
            enc.field_seconds,
            enc.psnr(),
            in_band,
            100.0 * d.chamfer / diag,
            100.0 * d.hausdorff / diag,
            enc.asset.meta.stats.transforms,
        );
    }
}
