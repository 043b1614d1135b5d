//! Polylines (GeoJSON) into curve assets, with what the encoder measured against the source.

use crate::codecs::curve::{CurveSettings, Metric, SegmentGrid, encode, fit, geojson, hausdorff};

/// An encoded curve asset and what the encoder measured.
pub struct EncodedCurveAsset {
    /// The asset, as a reader of the file sees it.
    pub asset: crate::io::asset::Asset,
    /// The file's bytes.
    pub bytes: Vec<u8>,
    /// The fit's report.
    pub fit: fit::FitReport,
    /// Input vertices (GeoJSON positions, ring closures included).
    pub points: usize,
}

/// Encodes polylines into an asset file (kind Curve, codec 5). The metadata counts input
/// positions in `width` (one row, two float32 channels: the ratio baseline), and holds the
/// Hausdorff distance to the source at the finest level (`max_error`, measured along segments
/// every tolerance/8) and the RMS distance from input vertices to the decoded polylines
/// (`rmse`): a decoded point may slide along the coast, so its distance to its own input
/// vertex says nothing of the error.
pub fn encode_asset(
    lines: &[geojson::Polyline],
    settings: &CurveSettings,
    name: &str,
) -> Result<EncodedCurveAsset, crate::Error> {
    let started = std::time::Instant::now();
    let (curves, report) = encode(lines, settings)?;
    let points: usize = lines
        .iter()
        .map(|l| l.points.len() + usize::from(l.closed))
        .sum();
    let finest = curves.set.at_level(curves.set.finest());
    let (mut max_err, mut sum2) = (0.0f64, 0.0f64);
    for (l, out) in lines.iter().zip(&finest.lines) {
        let mut src = l.points.clone();
        if l.closed {
            src.push(src[0]);
        }
        let spacing = settings.tolerance / 8.0;
        max_err = max_err.max(hausdorff(settings.metric, &src, out, spacing));
        let grid = SegmentGrid::new(out);
        sum2 += l
            .points
            .iter()
            .map(|&p| grid.distance(settings.metric, p).powi(2))
            .sum::<f64>();
    }
    let ys = lines.iter().flat_map(|l| l.points.iter().map(|p| p[1]));
    let (lo, hi) = ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), y| {
        (lo.min(y), hi.max(y))
    });
    let meta = fractile_proto::AssetMeta {
        kind: fractile_proto::AssetKind::Curve,
        width: u32::try_from(points)
            .ok()
            .filter(|&n| n <= 1 << 26)
            .ok_or_else(|| crate::Error::input(format!("{points} vertices is too many")))?,
        height: 1,
        channels: 2,
        colour: fractile_proto::ColourModel::Grey,
        sample: fractile_proto::SampleFormat::F32,
        units: Some(match settings.metric {
            Metric::Sphere => "degrees".into(),
            Metric::Plane => "units".into(),
        }),
        value_min: lo,
        value_max: hi,
        nodata: None,
        georef: None,
        encoder: format!(
            "{name}: curve-pifs, tolerance {}, {} scheme",
            settings.tolerance,
            if report.kept { "fitted" } else { "default" }
        ),
        stats: fractile_proto::EncodeStats {
            transforms: curves.set.rings.iter().map(|r| r.pieces() as u64).sum(),
            rmse: (sum2 / points.max(1) as f64).sqrt(),
            psnr: 0.0,
            max_error: max_err,
            seconds: started.elapsed().as_secs_f64(),
        },
    };
    let asset = crate::io::asset::Asset::from_curve_parts(meta, curves.header, curves.stream)?;
    let bytes = asset.to_bytes();
    Ok(EncodedCurveAsset {
        asset,
        bytes,
        fit: report,
        points,
    })
}
