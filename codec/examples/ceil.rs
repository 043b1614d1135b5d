use fractile_codec::raster::Raster;
fn main() {
    let r = Raster::open(std::path::Path::new("/work/main/testdata/etopo20.tif")).unwrap();
    let (w, h) = (r.width, r.height);
    let z = &r.channels[0];
    let (lo, hi) = z
        .iter()
        .fold((f32::MAX, f32::MIN), |a, &v| (a.0.min(v), a.1.max(v)));
    let range = (hi - lo) as f64;
    println!("{w}x{h} range {range}");
    for k in [2usize] {
        let nx = (w - 1).div_ceil(k) + 1;
        let ny = (h - 1).div_ceil(k) + 1;
        let at = |i: usize, j: usize| z[j.min(h - 1) * w + i.min(w - 1)] as f64;
        for step in [100.0f64, 140.0, 180.0, 220.0, 260.0, 300.0] {
            let mut q = vec![0i64; nx * ny];
            let mut nodes = vec![0f64; nx * ny];
            for j in 0..ny {
                for i in 0..nx {
                    let v = at(i * k, j * k);
                    if step > 0.0 {
                        q[j * nx + i] = (v / step).round() as i64;
                        nodes[j * nx + i] = q[j * nx + i] as f64 * step;
                    } else {
                        nodes[j * nx + i] = v;
                    }
                }
            }
            // MED residual entropy
            let mut hist = std::collections::HashMap::new();
            for j in 0..ny {
                for i in 0..nx {
                    let p = match (i, j) {
                        (0, 0) => 0,
                        (_, 0) => q[i - 1],
                        (0, _) => q[(j - 1) * nx],
                        _ => {
                            let (a, b, c) = (
                                q[j * nx + i - 1],
                                q[(j - 1) * nx + i],
                                q[(j - 1) * nx + i - 1],
                            );
                            if c >= a.max(b) {
                                a.min(b)
                            } else if c <= a.min(b) {
                                a.max(b)
                            } else {
                                a + b - c
                            }
                        }
                    };
                    *hist.entry(q[j * nx + i] - p).or_insert(0usize) += 1;
                }
            }
            let n = (nx * ny) as f64;
            let ent: f64 = hist
                .values()
                .map(|&c| {
                    let p = c as f64 / n;
                    -p * p.log2()
                })
                .sum();
            let mut se = 0.0;
            for y in 0..h {
                for x in 0..w {
                    let (ci, cj) = (x / k, y / k);
                    let (fx, fy) = ((x % k) as f64 / k as f64, (y % k) as f64 / k as f64);
                    let v = nodes[cj * nx + ci] * (1.0 - fx) * (1.0 - fy)
                        + nodes[cj * nx + ci + 1] * fx * (1.0 - fy)
                        + nodes[(cj + 1) * nx + ci] * (1.0 - fx) * fy
                        + nodes[(cj + 1) * nx + ci + 1] * fx * fy;
                    se += (v - z[y * w + x] as f64).powi(2);
                }
            }
            let psnr = 10.0 * (range * range / (se / (w * h) as f64)).log10();
            let ratio = if step > 0.0 {
                16.0 * (w * h) as f64 / (ent * n)
            } else {
                0.0
            };
            println!(
                "k={k} step={step} nodes {nx}x{ny} psnr {psnr:.2} dB, DPCM {ent:.2} b/node, ratio {ratio:.1}:1"
            );
        }
    }
}
