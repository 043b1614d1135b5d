//! What coarse zooms cost, three ways, on one plane (issue 52's one multiresolution): the
//! lifted plane alone (no overviews: the floor), box-mean overviews coded on their own at twice
//! the step a level (what a chunked file of format 6 does), and a closed-loop Laplacian
//! pyramid (Burt and Adelson: the coarsest overview coded, each finer level coded as its
//! residual against the decoded coarser one upsampled), the way a COG-like layout would code
//! "coarse first, fine given coarse".
//!
//! `cargo bench -p fractile-codec --bench overviews -- [COPIES] [FILE.tif] [ends]` (etopo20
//! mirrored 4 x 4 by default). Prints bits per cell and PSNR (peak: the value range) at three
//! steps. `ends`: instead, the raster coded in chunks of 1024 that share their edge column and
//! row, with lines mirrored or point-symmetric past their ends (`lifting::Ends`): bits, PSNR,
//! and how far two neighbours' coarse samples along their shared column differ at depths 1, 3
//! and 5 (the seams of coarse zooms read from the chunks' own coarse bands).

use fractile_codec::Raster;
use fractile_codec::codecs::projected::kernel::{Ends, Kernel};
use fractile_codec::codecs::projected::levels_for;
use fractile_codec::codecs::projected::lifting::{self, Plane};

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
            ends: Ends::Mirror,
            code: lifting::Code::Plain,
        };
        let (stream, decoded) = lifting::encode(&plane, values, 0.1);
        (stream.len(), decoded)
    }
}

/// A chunk: its first column, its size, its source cells and its decoded ones.
type Chunk = (usize, [usize; 2], Vec<f64>, Vec<f64>);

/// The `ends` table (see the file's doc).
fn ends(source: &Grid) {
    const CHUNK: usize = 1024;
    let (w, h) = (source.width, source.height);
    let (lo, hi) = source
        .cells
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    println!(
        "{w} x {h} in chunks of {CHUNK} sharing an edge\n\n| kernel | ends | step | bits a cell | PSNR dB | seam, depth 1 / 3 / 5 | seam decoded |"
    );
    println!("|---|---|---|---|---|---|---|");
    for kernel in [Kernel::Cdf97, Kernel::Fitted] {
        for ends in [Ends::Mirror, Ends::PointSymmetric] {
            for step in [(hi - lo) / 200.0, (hi - lo) / 800.0] {
                let plane = |size: [usize; 2]| Plane {
                    size,
                    levels: u32::from(levels_for(size[0], size[1])),
                    step,
                    kernel,
                    ends,
                    code: lifting::Code::Plain,
                };
                let mut bytes = 0;
                let mut decoded = vec![0.0; w * h];
                let mut rows: Vec<Vec<Chunk>> = Vec::new();
                for y0 in (0..h).step_by(CHUNK) {
                    let mut row = Vec::new();
                    for x0 in (0..w).step_by(CHUNK) {
                        let (x1, y1) = ((x0 + CHUNK + 1).min(w), (y0 + CHUNK + 1).min(h));
                        let size = [x1 - x0, y1 - y0];
                        let cells: Vec<f64> = (y0..y1)
                            .flat_map(|y| source.cells[y * w + x0..y * w + x1].iter().copied())
                            .collect();
                        let (stream, dec) = lifting::encode(&plane(size), &cells, 0.1);
                        bytes += stream.len();
                        for y in y0..y1 {
                            decoded[y * w + x0..y * w + x1]
                                .copy_from_slice(&dec[(y - y0) * size[0]..(y - y0 + 1) * size[0]]);
                        }
                        row.push((x0, size, cells, dec));
                    }
                    rows.push(row);
                }
                let sq: f64 = source
                    .cells
                    .iter()
                    .zip(&decoded)
                    .map(|(a, b)| (a - b).powi(2))
                    .sum();
                let psnr = 10.0 * ((hi - lo).powi(2) / (sq / (w * h) as f64)).log10();
                let seams = |coded: bool| {
                    let per_depth: Vec<String> = [1u32, 3, 5]
                        .iter()
                        .map(|&depth| {
                            let mut worst = 0.0f64;
                            // Pairs whose planes both reach the depth (a narrow last chunk
                            // has fewer levels).
                            let deep = |c: &Chunk| plane(c.1).levels >= depth;
                            for pair in rows.iter().flat_map(|r| r.windows(2)) {
                                let (a, b) = (&pair[0], &pair[1]);
                                if !(deep(a) && deep(b)) {
                                    continue;
                                }
                                let band = |c: &Chunk| {
                                    let g = if coded { &c.3 } else { &c.2 };
                                    lifting::analysis(&plane(c.1), g, depth)
                                };
                                let (ba, bb) = (band(a), band(b));
                                let edge = b.0 - a.0;
                                for y in (0..a.1[1].min(b.1[1])).step_by(1 << depth) {
                                    let d = ba[y * a.1[0] + edge] - bb[y * b.1[0]];
                                    worst = worst.max(d.abs());
                                }
                            }
                            format!("{worst:.1}")
                        })
                        .collect();
                    per_depth.join(" / ")
                };
                println!(
                    "| {kernel:?} | {ends:?} | {step:.1} | {:.3} | {psnr:.2} | {} | {} |",
                    bytes as f64 * 8.0 / (w * h) as f64,
                    seams(false),
                    seams(true)
                );
            }
        }
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
        fractile_codec::mosaic::mirrored(&src, copies, copies).expect("a mosaic")
    } else {
        src
    };
    let mut levels = vec![Grid {
        cells: r.channels[0].iter().map(|&v| f64::from(v)).collect(),
        width: r.width,
        height: r.height,
    }];
    if args.iter().any(|a| a == "ends") {
        ends(&levels[0]);
        return;
    }
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
