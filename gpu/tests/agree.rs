//! Every GPU path against the CPU decoder on real assets (CI runs this on Mesa's lavapipe):
//! within 1e-4 of the value range (values are normalised, so 1e-4 absolute).

use std::path::PathBuf;

use fractile_codec::codecs::fis::{FisSettings, Scaling};
use fractile_codec::codecs::psa::{PsaSettings, Tiling};
use fractile_codec::decode;
use fractile_codec::pieces::Flatten;
use fractile_codec::{Asset, QuadtreeSettings, Raster, RateMode, encode};
use fractile_gpu::{Gpu, Grid};

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// CI installs lavapipe: no adapter is a failure there, not a skip.
fn gpu() -> Gpu {
    Gpu::new().unwrap_or_else(|e| panic!("{e} (install mesa-vulkan-drivers)"))
}

fn quadtree(file: &str, bpp: f64) -> Asset {
    let r = Raster::open(&data(file)).unwrap();
    let mut s = QuadtreeSettings {
        rate: RateMode::TargetBpp(bpp),
        ..QuadtreeSettings::default()
    };
    s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
    encode(&r, &s, &|_, _| {}).unwrap().asset
}

fn scatter(n: usize, seed: u32) -> Vec<[f32; 2]> {
    (0..n as u32)
        .map(|i| {
            let h = i
                .wrapping_mul(2_654_435_761)
                .wrapping_add(seed.wrapping_mul(97));
            let k = i.wrapping_mul(40_503).wrapping_add(seed) ^ (h >> 7);
            [h as f32 / u32::MAX as f32, k as f32 / u32::MAX as f32]
        })
        .collect()
}

fn close(what: &str, cpu: &[decode::PointValue], gpu: &[decode::PointValue]) {
    assert_eq!(cpu.len(), gpu.len(), "{what}");
    let mut worst = 0.0f32;
    for (k, (c, g)) in cpu.iter().zip(gpu).enumerate() {
        let d = (c.value - g.value).abs();
        assert!(
            d <= 1e-4,
            "{what} point {k}: cpu {} gpu {}",
            c.value,
            g.value
        );
        assert!(
            (c.error_bound - g.error_bound).abs() <= 1e-4,
            "{what} bound {k}"
        );
        // The same cells, so the same steps (where a tolerance stops chains early too).
        assert_eq!(c.iterations, g.iterations, "{what} steps {k}");
        worst = worst.max(d);
    }
    eprintln!("{what}: {} points, worst difference {worst:e}", cpu.len());
}

#[test]
fn points_agree_on_images_and_dems_for_every_codec() {
    let mut gpu = gpu();
    eprintln!("adapter: {}", gpu.adapter());
    let dem = Raster::open(&data("jacksboro.tif")).unwrap();
    let assets: Vec<(String, Asset, u32)> = vec![
        ("camera quadtree".into(), quadtree("camera.png", 0.48), 12),
        (
            "jacksboro quadtree".into(),
            quadtree("jacksboro.tif", 1.0),
            12,
        ),
        (
            "jacksboro projected".into(),
            fractile_codec::encode_default(&dem, 0.8, &|_, _| {})
                .unwrap()
                .asset,
            12,
        ),
        (
            "jacksboro fis-rect".into(),
            fractile_codec::encode(
                &dem,
                &FisSettings {
                    scaling: Scaling::PerCell,
                    ..FisSettings::default()
                },
                &|_, _| {},
            )
            .unwrap()
            .asset,
            // phi expands by the cell count (50 here) a step: f32 rounding that differs in the last
            // bit moves a chain to another cell after a few steps, so compare short chains.
            3,
        ),
        (
            "jacksboro psa2d-tri".into(),
            fractile_codec::encode(
                &dem,
                &PsaSettings {
                    tiling: Tiling::Triangular,
                    ..PsaSettings::default()
                },
                &|_, _| {},
            )
            .unwrap()
            .asset,
            12,
        ),
    ];
    for (name, asset, n) in &assets {
        let op = &asset.planes()[0].operator;
        // As the server uploads (the projected codec as a lattice that ends on its samples).
        let dev = gpu.upload_flat(&op.flat()).unwrap();
        // Sizes: a few points, an odd count, and more than one chunk.
        for (count, chunk) in [(7usize, 1 << 22), (10_001, 1 << 22), (70_000, 30_000)] {
            gpu.set_chunk(chunk);
            let pts = scatter(count, count as u32);
            for tolerance in [0.0, 1e-3] {
                let cpu = decode::points(op, &pts, *n, tolerance);
                let got = gpu.points(&dev, &pts, *n, tolerance).unwrap();
                close(&format!("{name} n={count} tol={tolerance}"), &cpu, &got);
            }
        }
    }
}

#[test]
fn windows_and_reprojected_tiles_agree_with_the_cpu() {
    let mut gpu = gpu();
    let asset = quadtree("jacksboro.tif", 1.0);
    let op = &asset.planes()[0].operator;
    let dev = gpu.upload(&op.pieces()).unwrap();
    // A window at 300 x 200 (the kernel makes the points), dispatched in chunks of 7,000.
    gpu.set_chunk(7_000);
    let rect = [0.2f32, 0.3, 0.45, 0.5];
    let (w, h) = (300u32, 200u32);
    let got = gpu
        .grid(
            &dev,
            Grid::Window {
                rect,
                width: w,
                height: h,
            },
            10,
            0.0,
        )
        .unwrap();
    // The pixel centres as the CPU's windows make them.
    let (xs, ys) = decode::window_axes(rect, w as usize, h as usize);
    let pts: Vec<[f32; 2]> = ys
        .iter()
        .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
        .collect();
    close("window", &decode::points(op, &pts, 10, 0.0), &got);

    // A zoom-14 tile over the DEM: pixel centres to lon/lat to unit coordinates, on the GPU.
    let g = asset.meta.georef.as_ref().expect("georeferenced");
    let (w0, n0) = (g.origin[0], g.origin[1]);
    let (dx, dy) = (g.pixel_size[0], g.pixel_size[1]);
    let (sw, sh) = (asset.meta.width as f64, asset.meta.height as f64);
    let u_of_lon = [-w0 / (dx * sw), 1.0 / (dx * sw)];
    let v_of_lat = [-n0 / (dy * sh), 1.0 / (dy * sh)];
    let lon_c = w0 + 0.5 * dx * sw;
    let lat_c = n0 + 0.5 * dy * sh;
    let z = 14u8;
    let nz = f64::from(1u32 << z);
    let tx = ((lon_c + 180.0) / 360.0 * nz) as u32;
    let lat_r = lat_c.to_radians();
    let ty =
        ((1.0 - (lat_r.tan() + 1.0 / lat_r.cos()).ln() / std::f64::consts::PI) / 2.0 * nz) as u32;
    let size = 256u32;
    let (xs, ys) = mercator_axes((z, tx, ty), size, u_of_lon, v_of_lat);
    let got = gpu.grid(&dev, Grid::Separable { xs, ys }, 10, 0.0).unwrap();
    // The CPU's own reprojection of the same pixels, in f64.
    let pts: Vec<[f32; 2]> = (0..size * size)
        .map(|k| {
            let (i, j) = ((k % size) as f64 + 0.5, (k / size) as f64 + 0.5);
            let (mx, my) = (
                (tx as f64 * 256.0 + i) / (nz * 256.0),
                (ty as f64 * 256.0 + j) / (nz * 256.0),
            );
            let lon = mx * 360.0 - 180.0;
            let lat = (std::f64::consts::PI * (1.0 - 2.0 * my))
                .sinh()
                .atan()
                .to_degrees();
            [
                (u_of_lon[0] + u_of_lon[1] * lon) as f32,
                (v_of_lat[0] + v_of_lat[1] * lat) as f32,
            ]
        })
        .collect();
    assert!(
        pts.iter()
            .all(|p| (0.0..=1.0).contains(&p[0]) && (0.0..=1.0).contains(&p[1]))
    );
    close("zoom-14 tile", &decode::points(op, &pts, 10, 0.0), &got);
}

/// Values read back alone (issue 32's 4 bytes a point), with the bounds and step counts reduced
/// on the device: the same values as the full readback, bit for bit, and the largest bound and
/// step count of its points, over several dispatches and with points outside the square.
#[test]
fn values_only_readback_is_the_full_readback_reduced() {
    let mut gpu = gpu();
    let asset = quadtree("jacksboro.tif", 1.0);
    let op = &asset.planes()[0].operator;
    let dev = gpu.upload(&op.pieces()).unwrap();
    gpu.set_chunk(5_000);
    for grid in [
        Grid::Window {
            rect: [0.1, 0.2, 0.6, 0.5],
            width: 173,
            height: 111,
        },
        Grid::Separable {
            xs: (0..90).map(|i| -0.1 + i as f32 * 0.013).collect(),
            ys: (0..70).map(|j| 0.05 + j as f32 * 0.011).collect(),
        },
    ] {
        for tolerance in [0.0, 1e-3] {
            let full = gpu.grid(&dev, grid.clone(), 12, tolerance).unwrap();
            let got = gpu.grid_values(&dev, grid.clone(), 12, tolerance).unwrap();
            assert_eq!(got.values.len(), full.len());
            for (k, (v, p)) in got.values.iter().zip(&full).enumerate() {
                assert!(
                    v.to_bits() == p.value.to_bits(),
                    "point {k}: {v} against {}",
                    p.value
                );
            }
            let bound = full.iter().fold(0.0f32, |m, p| m.max(p.error_bound));
            let steps = full.iter().map(|p| p.iterations).max().unwrap();
            assert_eq!(got.error_bound, bound, "{grid:?}");
            assert_eq!(got.iterations, steps, "{grid:?}");
            assert!(bound > 0.0 && steps > 0);
        }
    }
}

/// Issue 32: small grids asked at once from many threads (a server's tiles) are decoded in
/// shared rounds, one submission for several, and each answers exactly what it answers alone:
/// the values of the full read-back, bit for bit, its largest bound and most steps. Two
/// operators, so that rounds mix them.
#[test]
fn concurrent_small_grids_share_rounds_and_answer_as_alone() {
    let gpu = gpu();
    let assets = [quadtree("jacksboro.tif", 1.0), quadtree("camera.png", 0.5)];
    let devs: Vec<_> = assets
        .iter()
        .map(|a| gpu.upload(&a.planes()[0].operator.pieces()).unwrap())
        .collect();
    // Tiles of different sizes and places, each with its operator and tolerance.
    let jobs: Vec<(usize, Grid, f32)> = (0..12)
        .map(|k| {
            let (w, h) = (24 + 7 * k, 40 - 2 * k);
            let (x0, y0) = (0.05 * k as f32, 0.9 - 0.06 * k as f32);
            let grid = Grid::Separable {
                xs: (0..w).map(|i| x0 + i as f32 * 0.004).collect(),
                ys: (0..h).map(|j| y0 - j as f32 * 0.005).collect(),
            };
            (k % 2, grid, if k % 3 == 0 { 1e-3 } else { 0.0 })
        })
        .collect();
    let alone: Vec<_> = jobs
        .iter()
        .map(|(a, grid, t)| gpu.grid(&devs[*a], grid.clone(), 12, *t).unwrap())
        .collect();
    let (rounds_before, grids_before) = gpu.rounds();
    std::thread::scope(|s| {
        for thread in 0..8 {
            let (gpu, devs, jobs, alone) = (&gpu, &devs, &jobs, &alone);
            s.spawn(move || {
                for rep in 0..4 {
                    let k = (thread * 5 + rep * 3) % jobs.len();
                    let (a, grid, t) = &jobs[k];
                    let got = gpu.grid_values(&devs[*a], grid.clone(), 12, *t).unwrap();
                    let full = &alone[k];
                    assert_eq!(got.values.len(), full.len());
                    for (i, (v, p)) in got.values.iter().zip(full).enumerate() {
                        assert_eq!(v.to_bits(), p.value.to_bits(), "grid {k} point {i}");
                    }
                    let bound = full.iter().fold(0.0f32, |m, p| m.max(p.error_bound));
                    assert_eq!(got.error_bound, bound, "grid {k}");
                    let steps = full.iter().map(|p| p.iterations).max().unwrap();
                    assert_eq!(got.iterations, steps, "grid {k}");
                }
            });
        }
    });
    let (rounds, grids) = gpu.rounds();
    let (rounds, grids) = (rounds - rounds_before, grids - grids_before);
    eprintln!("32 grids from 8 threads: {grids} grids in {rounds} rounds");
    assert_eq!(grids, 32);
    assert!(rounds < grids, "no round held two grids: {rounds} rounds");
}

/// Issue 32: dyadic grids (the source's own size, 2x, 4x, windows aligned with the source's
/// cells) and points exactly on cell boundaries put chains on range boundaries at some step,
/// where the last bit of a position's rounding used to send the CPU and the GPU into different
/// ranges (etopo20 at 1.6 bpp, 2x at 12 steps: 1,367 m apart at worst). With fixed-point
/// positions every step is exact on both, so they differ by f32 accumulation only.
#[test]
fn dyadic_grids_and_points_on_cell_boundaries_agree_with_the_cpu() {
    let mut gpu = gpu();
    gpu.set_chunk(1 << 20);
    let dem = Raster::open(&data("jacksboro.tif")).unwrap();
    let etopo20 = Raster::open(&data("etopo20.tif")).unwrap();
    let assets: Vec<(&str, Asset, u32)> = vec![
        ("etopo20 quadtree", quadtree("etopo20.tif", 1.6), 12),
        // The default DEM codec on the bar's DEM and rate: its chains end on the samples'
        // interpolant, on the device as on the CPU (a constant seed's ends were 4 m apart).
        (
            "etopo20 projected",
            fractile_codec::encode_default(&etopo20, 1.6, &|_, _| {})
                .unwrap()
                .asset,
            12,
        ),
        (
            "jacksboro projected",
            fractile_codec::encode_default(&dem, 0.8, &|_, _| {})
                .unwrap()
                .asset,
            12,
        ),
        (
            "jacksboro psa2d-tri",
            fractile_codec::encode(
                &dem,
                &PsaSettings {
                    tiling: Tiling::Triangular,
                    ..PsaSettings::default()
                },
                &|_, _| {},
            )
            .unwrap()
            .asset,
            12,
        ),
        (
            "jacksboro fis-rect",
            fractile_codec::encode(
                &dem,
                &FisSettings {
                    scaling: Scaling::PerCell,
                    ..FisSettings::default()
                },
                &|_, _| {},
            )
            .unwrap()
            .asset,
            // As in the test above: its maps scale by the cell count, so steps round.
            3,
        ),
    ];
    for (name, asset, n) in &assets {
        let op = &asset.planes()[0].operator;
        // As the server uploads: the projected codec as a lattice built directly.
        let dev = gpu.upload_flat(&op.flat()).unwrap();
        let (w, h) = (asset.meta.width as usize, asset.meta.height as usize);
        for (label, rect, (gw, gh)) in [
            ("1x", [0.0f32, 0.0, 1.0, 1.0], (w, h)),
            ("2x", [0.0, 0.0, 1.0, 1.0], (2 * w, 2 * h)),
            ("4x of a quarter", [0.25, 0.5, 0.5, 0.75], (w, h)),
            // A window whose edges are cell edges, at 8x.
            (
                "8x on cells",
                [
                    (w / 8) as f32 / w as f32,
                    (h / 8) as f32 / h as f32,
                    (w / 8 + w / 4) as f32 / w as f32,
                    (h / 8 + h / 4) as f32 / h as f32,
                ],
                (2 * w, 2 * h),
            ),
        ] {
            let got = gpu
                .grid(
                    &dev,
                    Grid::Window {
                        rect,
                        width: gw as u32,
                        height: gh as u32,
                    },
                    *n,
                    0.0,
                )
                .unwrap();
            let (xs, ys) = decode::window_axes(rect, gw, gh);
            let pts: Vec<[f32; 2]> = ys
                .iter()
                .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
                .collect();
            close(
                &format!("{name} {label}"),
                &decode::points(op, &pts, *n, 0.0),
                &got,
            );
        }
        // Points on the cell lattice itself (corners of source cells, and halves).
        let pts: Vec<[f32; 2]> = (0..20_000u32)
            .map(|k| {
                let (i, j) = (k * 7919 % (2 * w as u32), k * 104_729 % (2 * h as u32));
                [i as f32 / (2 * w) as f32, j as f32 / (2 * h) as f32]
            })
            .collect();
        let got = gpu.points(&dev, &pts, *n, 0.0).unwrap();
        close(
            &format!("{name} points on cell corners"),
            &decode::points(op, &pts, *n, 0.0),
            &got,
        );
    }
}

#[test]
fn volume_points_and_boxes_agree_with_the_cpu() {
    use fractile_codec::encode::volume::{MeshSettings, encode_mesh};
    use fractile_codec::mesh::Mesh;
    let mut gpu = gpu();
    // The bunny is not in the repo (2.6 MB); CI has ../shared beside the clone, and there it
    // runs at the seed's 64^3.
    let bunny = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/mesh/bunny.off");
    let mut meshes = vec![(data("mesh/fandisk.off"), 48), (data("mesh/knot2.off"), 40)];
    if bunny.exists() {
        meshes.push((bunny, 64));
    } else {
        eprintln!("{} absent: bunny skipped", bunny.display());
    }
    for (path, grid) in meshes {
        let file = path.file_name().unwrap().to_string_lossy().into_owned();
        let file = file.as_str();
        let mesh = Mesh::read(&path).unwrap();
        let s = MeshSettings {
            grid,
            ..MeshSettings::default()
        };
        let asset = encode_mesh(&mesh, &s, file).unwrap().asset;
        let op = &asset.volume().unwrap().operator;
        let dev = gpu.upload_volume(op).unwrap();
        // Scattered points in the unit cube, one chunk and several.
        for (count, chunk) in [(5usize, 1 << 22), (20_001, 1 << 22), (50_000, 12_345)] {
            gpu.set_chunk(chunk);
            let pts: Vec<[f32; 3]> = scatter(count, 7)
                .iter()
                .zip(scatter(count, 11))
                .map(|(a, b)| [a[0], a[1], b[0]])
                .collect();
            for tolerance in [0.0, 1e-3] {
                let cpu = decode::points(op, &pts, 12, tolerance);
                let got = gpu.volume_points(&dev, &pts, 12, tolerance).unwrap();
                close(&format!("{file} n={count} tol={tolerance}"), &cpu, &got);
            }
        }
        // A box at a resolution above the grid, made on the device, chunked.
        gpu.set_chunk(40_000);
        let (lo, hi, dims) = ([0.1f32, 0.2, 0.15], [0.8f32, 0.7, 0.9], [61usize, 45, 66]);
        let (cpu, bound) = decode::volume_window(op, lo, hi, dims, 12, 0.0);
        let got = gpu
            .volume_grid(&dev, lo, hi, dims.map(|d| d as u32), 12, 0.0)
            .unwrap();
        assert_eq!(got.len(), cpu.len());
        let worst = cpu
            .iter()
            .zip(&got)
            .map(|(c, g)| (c - g.value).abs())
            .fold(0.0f32, f32::max);
        assert!(worst <= 1e-4, "{file} box: worst {worst}");
        assert!(got.iter().all(|g| g.error_bound <= bound + 1e-6));
        // The values alone, the bounds and steps reduced on the device: the full read-back's,
        // bit for bit (five chunks).
        for tolerance in [0.0, 1e-3] {
            let dims = dims.map(|d| d as u32);
            let full = gpu.volume_grid(&dev, lo, hi, dims, 12, tolerance).unwrap();
            let reduced = gpu
                .volume_grid_values(&dev, lo, hi, dims, 12, tolerance)
                .unwrap();
            assert_eq!(reduced.values.len(), full.len());
            assert!(
                reduced
                    .values
                    .iter()
                    .zip(&full)
                    .all(|(v, p)| v.to_bits() == p.value.to_bits()),
                "{file} tol={tolerance}: values-only box"
            );
            let largest = full.iter().fold(0.0f32, |m, p| m.max(p.error_bound));
            let most = full.iter().map(|p| p.iterations).max().unwrap();
            assert_eq!(
                (reduced.error_bound.to_bits(), reduced.iterations),
                (largest.to_bits(), most),
                "{file} tol={tolerance}: the reduced bound and steps"
            );
        }
        volume_lattices_agree(&gpu, file, op, &dev, grid);
    }
}

/// A volume on its own lattice: boxes whose samples lie on cell faces, edges and corners (at
/// 2x the grid, and at 4x over a box whose faces are cell faces) and points on cell corners,
/// where an inexact position would take the next cell over at some step. The octree's maps (a
/// scale by 2, a cube isometry, a lattice translation) are exact on fixed-point positions and
/// the device takes the CPU's axes (`decode::volume_axes`), so both follow the same cells:
/// the same steps, values within f32 accumulation.
fn volume_lattices_agree(
    gpu: &Gpu,
    file: &str,
    op: &fractile_codec::codecs::ifs3d::OctreeOperator,
    dev: &fractile_gpu::GpuOperator,
    grid: usize,
) {
    let g = grid as f32;
    let cells = |a: usize, b: usize| ([a as f32 / g; 3], [b as f32 / g; 3]);
    let (half_lo, half_hi) = cells(grid / 4, grid / 4 + grid / 2);
    let (quarter_lo, quarter_hi) = cells(grid / 8, grid / 8 + grid / 4);
    for (label, lo, hi, dims) in [
        ("2x", half_lo, half_hi, [grid + 1; 3]),
        ("4x on cells", quarter_lo, quarter_hi, [grid + 1; 3]),
    ] {
        let [xs, ys, zs] = decode::volume_axes(lo, hi, dims);
        let pts: Vec<[f32; 3]> = zs
            .iter()
            .flat_map(|&z| {
                let xs = &xs;
                ys.iter()
                    .flat_map(move |&y| xs.iter().map(move |&x| [x, y, z]))
            })
            .collect();
        let cpu = decode::points(op, &pts, 12, 0.0);
        let got = gpu
            .volume_grid(dev, lo, hi, dims.map(|d| d as u32), 12, 0.0)
            .unwrap();
        close(&format!("{file} box {label}"), &cpu, &got);
        let (values, _) = decode::volume_window(op, lo, hi, dims, 12, 0.0);
        assert!(
            values
                .iter()
                .zip(&cpu)
                .all(|(v, c)| v.to_bits() == c.value.to_bits()),
            "{file} box {label}: volume_window decodes the axes' points"
        );
    }
    let n = 2 * grid as u32;
    let corners: Vec<[f32; 3]> = (0..20_000u32)
        .map(|k| {
            [
                k * 7919 % (n + 1),
                k * 104_729 % (n + 1),
                k * 15_485_863 % (n + 1),
            ]
        })
        .map(|c| c.map(|i| i as f32 / n as f32))
        .collect();
    close(
        &format!("{file} points on cell corners"),
        &decode::points(op, &corners, 12, 0.0),
        &gpu.volume_points(dev, &corners, 12, 0.0).unwrap(),
    );
}

/// The unit coordinates of the pixel centres of Web Mercator tile z/x/y (`size` pixels a side)
/// over an asset placed in lon/lat: `u = u_of_lon[0] + u_of_lon[1] * lon`,
/// `v = v_of_lat[0] + v_of_lat[1] * lat` (degrees), computed in f64 and rounded once, exactly as
/// a CPU computing the same pixels does.
fn mercator_axes(
    (z, x, y): (u8, u32, u32),
    size: u32,
    u_of_lon: [f64; 2],
    v_of_lat: [f64; 2],
) -> (Vec<f32>, Vec<f32>) {
    let n = f64::from(1u32 << z.min(30)) * f64::from(size);
    let xs = (0..size)
        .map(|i| {
            let mx = (f64::from(x) * f64::from(size) + f64::from(i) + 0.5) / n;
            (u_of_lon[0] + u_of_lon[1] * (mx * 360.0 - 180.0)) as f32
        })
        .collect();
    let ys = (0..size)
        .map(|j| {
            let my = (f64::from(y) * f64::from(size) + f64::from(j) + 0.5) / n;
            let lat = (std::f64::consts::PI * (1.0 - 2.0 * my))
                .sinh()
                .atan()
                .to_degrees();
            (v_of_lat[0] + v_of_lat[1] * lat) as f32
        })
        .collect();
    (xs, ys)
}
