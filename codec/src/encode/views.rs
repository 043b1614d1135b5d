//! The views of a chunked file: overview levels that are not coded but read from the source
//! chunks' coarse bands (lifted projected planes), their cells and their source-error maps.

use crate::Error;
use crate::encode::source::Encoded;
use crate::io::asset::Asset;
use crate::io::chunked::{ChunkEntry, ChunkTable};
use crate::io::raster::Raster;
use crate::io::rows::Header;

/// Codes one chunk of a level (0: the source's cells, l: an overview of 2^l cells a side).
pub(super) type EncodeLevel<'a> = dyn Fn(usize, &Raster) -> Result<Encoded, Error> + Sync + 'a;

/// The entries of view level `l`: level 0's, with the cells of their views.
pub(super) fn level_zero_views(zero: &[ChunkEntry], l: usize) -> Vec<ChunkEntry> {
    zero.iter()
        .map(|e| ChunkEntry {
            cells: ChunkTable::view_cells(e.cells, l),
            ..e.clone()
        })
        .collect()
}

/// How many overview levels of a raster of `header` in `sizes` levels are views of its source
/// chunks (`io::chunked`): [`ChunkTable::view_levels`] for a height field of one channel whose
/// chunks `encode` codes as lifted projected planes (rate mode; the codec is the caller's: a
/// small surface coded by it says which), none otherwise: their overviews are coded. A lifted
/// plane's coarse band is a local mean, as a box-mean overview is; the pyramid's coarse
/// samples (max-error mode, the bounded default) are source cells, closed loop, and a view of
/// them aliases: on etopo20 in chunks of 256 the level-1 view was 2,824 m from the box means
/// it stands for, where the coded level 2 was 510 m (measured).
pub(super) fn view_levels(
    header: &Header,
    sizes: &[(u32, u32)],
    encode: &EncodeLevel<'_>,
) -> usize {
    let n = ChunkTable::view_levels(sizes.len());
    if n == 0 || header.kind != fractile_proto::AssetKind::HeightField || header.channels != 1 {
        return 0;
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
    let lifted = |e: &Encoded| {
        e.asset.planes.iter().all(|p| match &p.coding {
            crate::io::asset::Coding::Projected { header, .. } => header.order.lifting().is_some(),
            _ => false,
        })
    };
    match encode(0, &probe) {
        Ok(e) if lifted(&e) => n,
        _ => 0,
    }
}

/// The source-error maps of the views at levels 1 to `views` of a source chunk coded as
/// `enc` from `part`: each view decoded as a reader decodes it (from the file's bytes), against
/// what it stands for, the same analysis of the source itself (the chunk's lifting to that
/// depth, its coarse band divided by the kernel's gain), with its share of the chunk's map
/// budget (a view of level l has 4^-l of the cells).
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
        enc.asset.planes.first().map(|p| &p.coding)
    else {
        return Ok(Vec::new());
    };
    let Some(kernel) = header.order.lifting() else {
        return Ok(Vec::new());
    };
    let (w, h) = (part.width, part.height);
    let mut filled = part.channels[0].clone();
    if let Some(valid) = &part.valid {
        super::source::fill_invalid(&mut filled, valid, w, h);
    }
    let grid: Vec<f64> = filled.iter().map(|&v| f64::from(v)).collect();
    let plane = lifting::Plane {
        size: [w, h],
        levels: u32::from(header.levels),
        step: header.step,
        kernel,
        ends: crate::codecs::projected::kernel::Ends::Mirror,
    };
    let limits = crate::io::asset::AssetLimits::default();
    (1..=views)
        .map(|l| {
            let view =
                Asset::coarse_view(&bytes, &limits, l as u32, crate::codecs::plane::Build::Lazy)?;
            let read = (l as u32).min(plane.levels);
            let band = lifting::analysis(&plane, &grid, read);
            let gain = crate::codecs::projected::kernel::dc_gain(kernel).powi(2 * read as i32);
            let s = 1usize << l;
            let (cw, ch) = (w.div_ceil(s), h.div_ceil(s));
            let mut values = Vec::with_capacity(cw * ch);
            for y in (0..h).step_by(s) {
                values.extend((0..w).step_by(s).map(|x| (band[y * w + x] / gain) as f32));
            }
            let valid = part.valid.as_ref().map(|v| {
                let mut out = vec![false; cw * ch];
                for (i, _) in v.iter().enumerate().filter(|(_, b)| **b) {
                    out[(i / w / s) * cw + (i % w) / s] = true;
                }
                out
            });
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
