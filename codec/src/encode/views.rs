//! The views of a chunked file: overview levels that are not coded but read from the source
//! chunks' coarse bands (lifted projected planes), their cells and their source-error maps.

use crate::Error;
use crate::encode::encoded::Encoded;
use crate::io::asset::Asset;
use crate::io::chunked::{ChunkEntry, ChunkTable};
use crate::io::raster::Raster;
use crate::io::rows::Header;

/// Codes one chunk of a level (0: the source's cells, l: an overview of 2^l cells a side).
pub type EncodeLevel<'a> = dyn Fn(usize, &Raster) -> Result<Encoded, Error> + Sync + 'a;

/// The entries of view level `l`: level 0's, with the cells of their views.
pub(super) fn level_zero_views(zero: &[ChunkEntry], l: usize) -> Vec<ChunkEntry> {
    zero.iter()
        .map(|e| ChunkEntry {
            cells: ChunkTable::view_cells(e.cells, l),
            ..e.clone()
        })
        .collect()
}

/// Whether the first overview levels of a raster of `header` are views of its source chunks
/// (`io::chunked`; [`ChunkTable::view_levels`] of them): for a height field of one channel
/// whose chunks `encode` codes as projected planes (the codec is the caller's: a small surface
/// coded by it says which); otherwise its overviews are coded. Both multiresolutions give
/// views: a lifted plane's coarse band (rate mode) is a local mean, the low-pass it stands
/// for; the pyramid's coarse samples (max-error mode, the bounded default) are source cells
/// decoded within the plane's bound, closed loop, so a view of them is the source decimated
/// to the level's lattice, within the same bound. A decimation aliases where a box mean would
/// not (docs/asset-format.md, "Views"), but coded beside the source the bounded default's
/// overviews cost its files 38-51% of their bytes (etopo20 x 4 at max errors 1 to 150,
/// measured), where as views they cost nothing.
pub(super) fn viewed(header: &Header, encode: &EncodeLevel<'_>) -> bool {
    if header.kind != fractile_proto::AssetKind::HeightField || header.channels != 1 {
        return false;
    }
    let side = 32;
    let surface = (0..side * side)
        .map(|i| ((i % side) * 3 + (i / side) * 5) as f32)
        .collect();
    let probe = Raster {
        width: side,
        height: side,
        channels: vec![surface],
        valid: None,
        kind: header.kind,
        sample: header.sample,
        units: None,
        nodata: None,
        georef: None,
    };
    let projected = |e: &Encoded| {
        e.asset
            .planes()
            .iter()
            .all(|p| matches!(p.coding, crate::io::asset::Coding::Projected { .. }))
    };
    encode(0, &probe).is_ok_and(|e| projected(&e))
}

/// The source-error maps of the views at levels 1 to `views` of a source chunk coded as
/// `enc` from `part`: each view decoded as a reader decodes it (from the file's bytes), against
/// what it stands for, with its share of the chunk's map budget (a view of level l has 4^-l
/// of the cells). A lifted plane's view stands for the same analysis of the source itself (the
/// chunk's lifting to that depth, its coarse band divided by the kernel's gain); a pyramid's
/// for the source cells on the level's lattice, which its samples are.
///
/// Why the analysis and not the box means format 6's overviews were measured against: a coarse
/// level stands for the source low-passed to its cell size, and the view's low-pass is the
/// wavelet's (as JPEG 2000's resolution levels are), longer than a box. Against the box means
/// the difference of the two filters, not the coding, set the map: on etopo20 at 0.8 bits a
/// cell, in chunks of 256, the level-1 view was 161 m RMS and 2,128 m at worst from the box
/// means, its map 3,022 m, where its source level's RMSE was 76 m (measured).
pub(super) fn view_maps(enc: &Encoded, part: &Raster, views: usize) -> Result<Vec<Vec<u8>>, Error> {
    use crate::codecs::projected::lifting;
    let bytes = enc.asset.to_bytes();
    let Some(crate::io::asset::Coding::Projected { header, .. }) =
        enc.asset.planes().first().map(|p| &p.coding)
    else {
        return Ok(Vec::new());
    };
    let (w, h) = (part.width, part.height);
    let mut filled = part.channels[0].clone();
    if let Some(valid) = &part.valid {
        crate::codecs::source::fill_invalid(&mut filled, valid, w, h);
    }
    let grid: Vec<f64> = filled.iter().map(|&v| f64::from(v)).collect();
    // A pyramid's view is the source decimated: valid where its lattice cell is.
    let decimated = header.order.lifting().is_none();
    // What a view of depth `read` stands for at every source cell (read on the lattice).
    let stands_for = |read: u32| -> Vec<f64> {
        let Some(kernel) = header.order.lifting() else {
            return grid.clone();
        };
        let plane = lifting::Plane {
            size: [w, h],
            levels: u32::from(header.levels),
            step: header.step,
            kernel,
            ends: crate::codecs::projected::kernel::Ends::Mirror,
            code: header.order.code(),
        };
        let gain = crate::codecs::projected::kernel::dc_gain(kernel).powi(2 * read as i32);
        let mut band = lifting::analysis(&plane, &grid, read);
        band.iter_mut().for_each(|v| *v /= gain);
        band
    };
    let limits = crate::io::asset::AssetLimits::default();
    (1..=views)
        .map(|l| {
            let view =
                Asset::coarse_view(&bytes, &limits, l as u32, crate::codecs::plane::Build::Lazy)?;
            let band = stands_for((l as u32).min(u32::from(header.levels)));
            let s = 1usize << l;
            let (cw, ch) = (w.div_ceil(s), h.div_ceil(s));
            let mut values = Vec::with_capacity(cw * ch);
            for y in (0..h).step_by(s) {
                values.extend((0..w).step_by(s).map(|x| band[y * w + x] as f32));
            }
            let valid = part
                .valid
                .as_ref()
                .map(|v| crate::io::mask::coarse_valid(v, [w, h], s, decimated));
            let reference = Raster {
                width: cw,
                height: ch,
                channels: vec![values],
                valid,
                kind: part.kind,
                sample: fractile_proto::SampleFormat::F32,
                units: part.units.clone(),
                nodata: part.nodata,
                georef: None,
            };
            let budget = crate::core::fidelity::reserve(bytes.len() >> (2 * l));
            Ok(super::fidelity::measure(&view, &reference, budget).encode())
        })
        .collect()
}
