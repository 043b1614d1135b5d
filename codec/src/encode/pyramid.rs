//! The overview pyramid of a chunked encode, built as the source's rows stream in: level 0
//! is the source, each further level the one before box-averaged by 2 (nodata cells left out
//! of the mean), until a level fits in one chunk.

use crate::Error;
use crate::io::chunked::ChunkTable;
use crate::io::raster::Raster;
use crate::io::rows::Header;

/// The levels of the overview pyramid as the source's rows stream in. Each level holds the
/// rows from its chunk row in progress (less the overlap) on: a chunk row is coded once every
/// row it covers is held, pairs of rows are box-averaged into the next level as soon as both
/// are held, and rows that neither still needs are dropped. A level of width `w` thus holds
/// about `chunk` rows plus the band last read, and the pyramid about twice the source level's.
pub(crate) struct Pyramid {
    levels: Vec<Level>,
    table: ChunkTable,
}

/// One level's rows `top..` (every channel, and whether each cell holds data).
pub(super) struct Level {
    header: Header,
    top: usize,
    channels: Vec<Vec<f32>>,
    valid: Vec<bool>,
    /// Rows before this one were averaged into the next level.
    halved: usize,
    /// The next chunk row to code.
    next_row: u32,
}

impl Level {
    /// A level of `header`'s cells holding no rows yet, the first to come being `top`.
    pub(super) fn new(header: Header, top: usize) -> Level {
        Level {
            channels: vec![Vec::new(); header.channels],
            header,
            top,
            valid: Vec::new(),
            halved: 0,
            next_row: 0,
        }
    }

    /// The row after the last held.
    pub(super) fn bottom(&self) -> usize {
        self.top + self.valid.len() / self.header.width
    }

    /// Rows that follow those held.
    pub(super) fn append(&mut self, band: &Raster) {
        for (c, b) in self.channels.iter_mut().zip(&band.channels) {
            c.extend_from_slice(b);
        }
        match &band.valid {
            Some(v) => self.valid.extend_from_slice(v),
            None => self
                .valid
                .resize(self.valid.len() + band.width * band.height, true),
        }
    }

    /// Cells `[x0, y0, x1, y1)` as a raster of their own (`valid` only where some cell lacks
    /// data, as a raster read whole has it).
    pub(super) fn crop(&self, [x0, y0, x1, y1]: [u32; 4]) -> Raster {
        let (x0, x1) = (x0 as usize, x1 as usize);
        let w = self.header.width;
        let span = (y0 as usize - self.top)..(y1 as usize - self.top);
        let rows = |plane: &[f32]| -> Vec<f32> {
            span.clone()
                .flat_map(|y| plane[y * w + x0..y * w + x1].iter().copied())
                .collect()
        };
        let valid: Vec<bool> = span
            .clone()
            .flat_map(|y| self.valid[y * w + x0..y * w + x1].iter().copied())
            .collect();
        let channels = self.channels.iter().map(|c| rows(c)).collect();
        let valid = valid.contains(&false).then_some(valid);
        self.header
            .band([x0, y0 as usize], x1 - x0, channels, valid)
    }

    /// Drops the rows above `row`.
    pub(super) fn release(&mut self, row: usize) {
        if row > self.top {
            let n = (row - self.top) * self.header.width;
            for c in &mut self.channels {
                c.drain(..n);
            }
            self.valid.drain(..n);
            self.top = row;
        }
    }
}

impl Pyramid {
    /// The levels of `sizes` (level 0 the source's, `header`), cut as `table` cuts them.
    pub(crate) fn new(header: &Header, sizes: &[(u32, u32)], table: &ChunkTable) -> Pyramid {
        let levels = sizes
            .iter()
            .enumerate()
            .map(|(l, &(w, h))| {
                let scale = f64::from(1u32 << l);
                let header = Header {
                    width: w as usize,
                    height: h as usize,
                    georef: header.georef.as_ref().map(|g| fractile_proto::Georef {
                        pixel_size: [g.pixel_size[0] * scale, g.pixel_size[1] * scale],
                        ..g.clone()
                    }),
                    ..header.clone()
                };
                Level::new(header, 0)
            })
            .collect();
        Pyramid {
            levels,
            table: table.clone(),
        }
    }

    /// Rows that follow those level `l` holds: hands `code` each chunk (level, index,
    /// cells) of the chunk rows they complete, averages their pairs into the next level, and
    /// drops what is no longer needed.
    pub(crate) fn push(
        &mut self,
        l: usize,
        band: &Raster,
        code: &mut dyn FnMut(usize, u32, Raster) -> Result<(), Error>,
    ) -> Result<(), Error> {
        let last = l + 1 == self.levels.len();
        let t = &self.table;
        let lev = &mut self.levels[l];
        lev.append(band);
        let (w, h) = (lev.header.width as u32, lev.header.height as u32);
        let (nx, ny) = t.grid(w, h);
        while lev.next_row < ny {
            let row = lev.next_row;
            if lev.bottom() < t.coded_cells(w, h, 0, row)[3] as usize {
                break;
            }
            for cx in 0..nx {
                let part = lev.crop(t.coded_cells(w, h, cx, row));
                code(l, row * nx + cx, part)?;
            }
            lev.next_row += 1;
        }
        let need = if lev.next_row < ny {
            t.coded_cells(w, h, 0, lev.next_row)[1] as usize
        } else {
            lev.bottom()
        };
        if last {
            lev.release(need);
            return Ok(());
        }
        // Whole pairs of rows only (the grid's last row alone at its end), so that each
        // coarse cell averages the 2 x 2 block a whole-raster halving would.
        let bottom = lev.bottom();
        let upto = if bottom == lev.header.height {
            bottom
        } else {
            bottom & !1
        };
        let half =
            (upto > lev.halved).then(|| halve(&lev.crop([0, lev.halved as u32, w, upto as u32])));
        if half.is_some() {
            lev.halved = upto;
        }
        lev.release(need.min(lev.halved));
        match half {
            Some(half) => self.push(l + 1, &half, code),
            None => Ok(()),
        }
    }
}

/// The raster box-averaged by 2 (sizes rounded up): each cell the mean of the valid cells of
/// its 2 x 2 block (rounded for integer samples), nodata where none is.
pub(crate) fn halve(raster: &Raster) -> Raster {
    let (w, h) = (raster.width, raster.height);
    let (hw, hh) = (w.div_ceil(2), h.div_ceil(2));
    let valid_at = |i: usize| raster.valid.as_ref().is_none_or(|v| v[i]);
    // Integer samples stay integers (rounded means): an overview of an integer source is of
    // its sample type, and the codecs that keep a bound per sample count on its quantum.
    let whole = raster.sample != fractile_proto::SampleFormat::F32;
    let mut valid = vec![true; hw * hh];
    let mut channels = vec![vec![f32::NAN; hw * hh]; raster.channels.len()];
    for y in 0..hh {
        for x in 0..hw {
            let cells = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .into_iter()
                .map(|(dx, dy)| (2 * x + dx, 2 * y + dy))
                .filter(|&(cx, cy)| cx < w && cy < h)
                .map(|(cx, cy)| cy * w + cx)
                .filter(|&i| valid_at(i));
            let (mut n, mut sums) = (0u32, [0f64; 4]);
            for i in cells {
                n += 1;
                for (s, c) in sums.iter_mut().zip(&raster.channels) {
                    *s += f64::from(c[i]);
                }
            }
            valid[y * hw + x] = n > 0;
            if n > 0 {
                for (c, s) in channels.iter_mut().zip(sums) {
                    let mean = s / f64::from(n);
                    c[y * hw + x] = if whole { mean.round() } else { mean } as f32;
                }
            }
        }
    }
    Raster {
        width: hw,
        height: hh,
        channels,
        valid: raster.valid.as_ref().map(|_| valid),
        kind: raster.kind,
        sample: raster.sample,
        units: raster.units.clone(),
        nodata: raster.nodata,
        georef: raster.georef.as_ref().map(|g| fractile_proto::Georef {
            pixel_size: [g.pixel_size[0] * 2.0, g.pixel_size[1] * 2.0],
            ..g.clone()
        }),
    }
}
