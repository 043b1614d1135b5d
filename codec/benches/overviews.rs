//! What coarse zooms cost, three ways, on one plane (issue 52's one multiresolution): the
//! lifted plane alone (no overviews: the floor), box-mean overviews coded on their own at twice
//! the step a level (what a chunked file of format 6 does), and a closed-loop Laplacian
//! pyramid (Burt and Adelson: the coarsest overview coded, each finer level coded as its
//! residual against the decoded coarser one upsampled), the way a COG-like layout would code
//! "coarse first, fine given coarse".
//!
//! `cargo bench -p fractile-codec --bench overviews -- [COPIES] [FILE.tif]` (etopo20 mirrored
//! 4 x 4 by default). Prints bits per cell and PSNR (peak: the value range) at four steps.

use fractile_codec::Raster;
use fractile_codec::codecs::projected::levels_for;
use fractile_codec::codecs::projected::lifting::{self, Kernel, Plane};

/// Overview levels below the source coded in each design.
const OVERVIEWS: usize = 3;

/// A grid and its size.
struct Grid {
    cells: Vec<f64>,
    width: usize,
    height: usize,
}

impl Grid {
    /// The next overview: 2 x 2 box means (a half block at an odd edge).
    fn halved(&self) -> Grid {
        let (w, h) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut cells = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                let (mut sum, mut n) = (0.0, 0.0);
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (xx, yy) = (2 * x + dx, 2 * y + dy);
                    if xx < self.width && yy < self.height {
                        sum += self.cells[yy * self.width + xx];
                        n += 1.0;
                    }
                }
                cells[y * w + x] = sum / n;
            }
        }
        Grid {
            cells,
            width: w,
            height: h,
        }
    }

    /// Bilinear upsampling of these cell means onto the cells of `width x height` (cell
    /// centres aligned, edges clamped).
    fn upsampled(&self, width: usize, height: usize) -> Vec<f64> {
        let line = |at: &dyn Fn(isize) -> f64, i: usize| {
            let k = (i / 2) as isize;
            let near = if i.is_multiple_of(2) { k - 1 } else { k + 1 };
            0.75 * at(k) + 0.25 * at(near)
        };
        let mut rows = vec![0.0; width * self.height];
        for y in 0..self.height {
            let at = |j: isize| {
                self.cells[y * self.width + j.clamp(0, self.width as isize - 1) as usize]
            };
            for x in 0..width {
                rows[y * width + x] = line(&at, x);
            }
        }
        let mut out = vec![0.0; width * height];
        for x in 0..width {
            let at = |j: isize| rows[j.clamp(0, self.height as isize - 1) as usize * width + x];
            for y in 0..height {
                out[y * width + x] = line(&at, y);
            }
        }
        out
    }

    /// Bytes and decoded cells of `values` (this grid's size) coded by the lifted levels at `step`.
    fn code(&self, values: &[f64], step: f64) -> (usize, Vec<f64>) {
        let plane = Plane {
            size: [self.width, self.height],
            levels: u32::from(levels_for(self.width, self.height)),
            step,
            kernel: Kernel::Fitted,
        };
        let (stream, decoded) = lifting::encode(&plane, values, 0.1);
        (stream.len(), decoded)
    }
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let copies: usize = args.iter().find_map(|a| a.parse().ok()).unwrap_or(4);
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata");
    let path = args
        .iter()
        .find(|a| a.ends_with(".tif"))
        .map_or(root.join("etopo20.tif"), std::path::PathBuf::from);
    let src = Raster::open(&path).expect("a DEM");
    let r = if copies > 1 {
        fractile_codec::io::mosaic::mirrored(&src, copies, copies).expect("a mosaic")
    } else {
        src
    };
    let mut levels = vec![Grid {
        cells: r.channels[0].iter().map(|&v| f64::from(v)).collect(),
        width: r.width,
        height: r.height,
    }];
    for _ in 0..OVERVIEWS {
        let next = levels.last().expect("a level").halved();
        levels.push(next);
    }
    let source = &levels[0];
    let (lo, hi) = source
        .cells
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let cells = source.cells.len() as f64;
    let psnr = |d: &[f64]| {
        let sq: f64 = source
            .cells
            .iter()
            .zip(d)
            .map(|(a, b)| (a - b).powi(2))
            .sum();
        10.0 * ((hi - lo).powi(2) / (sq / cells)).log10()
    };
    let bpp = |bytes: usize| bytes as f64 * 8.0 / cells;
    println!(
        "{} x {}, {OVERVIEWS} overviews\n\n| step | design | bits a cell | PSNR dB | coarse levels' share |",
        r.width, r.height
    );
    println!("|---|---|---|---|---|");
    for step in [(hi - lo) / 400.0, (hi - lo) / 1600.0, (hi - lo) / 6400.0] {
        let (alone, decoded) = source.code(&source.cells, step);
        println!(
            "| {step:.1} | one plane, no overviews | {:.3} | {:.2} | 0 |",
            bpp(alone),
            psnr(&decoded)
        );
        let own: usize = (1..=OVERVIEWS)
            .map(|l| levels[l].code(&levels[l].cells, step * f64::from(1 << l)).0)
            .sum();
        println!(
            "| {step:.1} | overviews on their own, 2x the step a level | {:.3} | {:.2} | {:.1}% |",
            bpp(alone + own),
            psnr(&decoded),
            100.0 * own as f64 / (alone + own) as f64
        );
        let top = &levels[OVERVIEWS];
        let (mut bytes, mut decoded) = top.code(&top.cells, step * f64::from(1 << OVERVIEWS));
        let mut coarse = 0;
        for l in (0..OVERVIEWS).rev() {
            let (level, parent) = (&levels[l], &levels[l + 1]);
            let parent = Grid {
                cells: decoded,
                width: parent.width,
                height: parent.height,
            };
            let predicted = parent.upsampled(level.width, level.height);
            let residual: Vec<f64> = level
                .cells
                .iter()
                .zip(&predicted)
                .map(|(a, p)| a - p)
                .collect();
            coarse = if l == 0 { bytes } else { coarse };
            let (b, r) = level.code(&residual, step * f64::from(1 << l));
            bytes += b;
            decoded = predicted.iter().zip(&r).map(|(p, r)| p + r).collect();
        }
        println!(
            "| {step:.1} | Laplacian pyramid, 2x the step a level | {:.3} | {:.2} | {:.1}% |",
            bpp(bytes),
            psnr(&decoded),
            100.0 * coarse as f64 / bytes as f64
        );
    }
}
