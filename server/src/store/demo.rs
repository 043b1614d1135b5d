//! The built-in demo assets: small real files shipped in the binary, encoded into a folder
//! at first start.

use std::path::Path;

/// The demo assets: real data shipped in the binary, with the rate each is encoded at (bits a
/// source cell), by the codec `fractile encode` picks when none is named.
const DEMO: &[(&str, &str, &[u8], f64)] = &[
    (
        "jacksboro",
        "jacksboro.tif",
        include_bytes!("../../../testdata/jacksboro.tif"),
        0.8,
    ),
    (
        // The same terrain on a UTM 16N grid (GDAL's warp): tiles and points go through the
        // reprojection.
        "jacksboro-utm",
        "jacksboro-utm.tif",
        include_bytes!("../../../testdata/jacksboro-utm.tif"),
        0.8,
    ),
    (
        "topobathy",
        "topobathy.tif",
        include_bytes!("../../../testdata/topobathy.tif"),
        1.6,
    ),
    (
        "camera",
        "camera.png",
        include_bytes!("../../../testdata/camera.png"),
        0.48,
    ),
    (
        "astronaut",
        "astronaut.png",
        include_bytes!("../../../testdata/astronaut.png"),
        0.5,
    ),
];

/// The revision of the demo's raster encodes, kept beside them: a folder of another revision
/// is encoded again. Bump it when [`fractile_codec::encode_default`] changes what it writes.
const DEMO_REVISION: &str = "3 (images: projected)";

/// The demo volume: fandisk (a CAD part with sharp features) as a 64^3 distance field.
const DEMO_VOLUME: (&str, &str, &[u8]) = (
    "fandisk",
    "fandisk.off",
    include_bytes!("../../../testdata/mesh/fandisk.off"),
);

/// The demo curves: five Natural Earth 1:50m coastlines, coded to about 1 km (0.009°).
const DEMO_CURVE: (&str, &str, &[u8], f64) = (
    "coast",
    "coast5.geojson",
    include_bytes!("../../../testdata/curve/coast5.geojson"),
    0.009,
);

/// Whether the asset file at `path` is of a format version older than this build writes (its
/// version field, bytes 8-9; unreadable files are left to the store to report).
fn older_format(path: &Path) -> bool {
    let mut head = [0u8; 10];
    std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok_and(|()| {
            u16::from_le_bytes([head[8], head[9]]) < fractile_codec::asset::FORMAT_VERSION
        })
}

/// Encodes the demo assets into `dir` unless they are there already (a progress line each).
pub(crate) fn ensure_demo_assets(dir: &Path) -> Result<(), fractile_codec::Error> {
    std::fs::create_dir_all(dir)
        .map_err(|e| fractile_codec::Error::output(format!("{}: {e}", dir.display())))?;
    let (id, name, bytes) = DEMO_VOLUME;
    let out = dir.join(format!("{id}.fra"));
    if !out.exists() {
        tracing::info!("encoding demo volume {id} from {name} (first start only)");
        let text = std::str::from_utf8(bytes)
            .map_err(|e| fractile_codec::Error::input(format!("{name}: {e}")))?;
        let mesh = fractile_codec::mesh::Mesh::parse_off(text).map_err(|e| e.within(name))?;
        let enc = fractile_codec::encode::volume::encode_mesh(
            &mesh,
            &fractile_codec::encode::volume::MeshSettings::default(),
            name,
        )?;
        fractile_codec::asset::write_atomic(&out, &enc.bytes)?;
        tracing::info!(
            "demo volume {id}: {} bytes, {:.2}:1 against i8, PSNR {:.2} dB",
            enc.bytes.len(),
            enc.ratio_i8(),
            enc.psnr()
        );
    }
    let (id, name, bytes, tolerance) = DEMO_CURVE;
    let out = dir.join(format!("{id}.fra"));
    if !out.exists() {
        let text = std::str::from_utf8(bytes)
            .map_err(|e| fractile_codec::Error::input(format!("{name}: {e}")))?;
        let lines =
            fractile_codec::codecs::curve::geojson::read(text).map_err(|e| e.within(name))?;
        let settings = fractile_codec::codecs::curve::CurveSettings {
            tolerance,
            ..Default::default()
        };
        let enc = fractile_codec::encode::curve::encode_asset(&lines, &settings, name)?;
        fractile_codec::asset::write_atomic(&out, &enc.bytes)?;
        tracing::info!(
            "demo curves {id}: {} polylines, {} bytes",
            lines.len(),
            enc.bytes.len()
        );
    }
    // Demo rasters written by an older build (before the source-error maps of format version
    // 5, or before the default encode changed) are encoded again, so the demo is what
    // `fractile encode` writes today.
    let revision = dir.join(".demo-revision");
    let current = std::fs::read_to_string(&revision).is_ok_and(|r| r.trim() == DEMO_REVISION);
    for (id, name, bytes, rate) in DEMO {
        let out = dir.join(format!("{id}.fra"));
        if out.exists() && current && !older_format(&out) {
            continue;
        }
        tracing::info!("encoding demo asset {id} from {name} (first start, or an older format)");
        let src = dir.join(format!(".{name}"));
        fractile_codec::asset::write_atomic(&src, bytes)?;
        let raster = fractile_codec::Raster::open(&src)?;
        // As `fractile encode` codes them by default.
        let enc = fractile_codec::encode_default(&raster, *rate, &|_, _| {})?;
        fractile_codec::asset::write_atomic(&out, &enc.bytes)?;
        let _ = std::fs::remove_file(&src);
        tracing::info!(
            "demo asset {id}: {} bytes, {:.2}:1, PSNR {:.2} dB",
            enc.bytes.len(),
            enc.ratio(),
            enc.errors.psnr
        );
    }
    if !current {
        fractile_codec::asset::write_atomic(&revision, DEMO_REVISION.as_bytes())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn demo_assets_of_an_older_format_are_told_apart() {
        let golden = Path::new(env!("CARGO_MANIFEST_DIR")).join("../testdata/golden");
        assert!(older_format(&golden.join("v4-quadtree-jacksboro-utm.fra")));
        assert!(older_format(&golden.join("v1-quadtree-camera.fra")));
        // Version 9 numbers files that are not chunked too: 5 is older now.
        assert!(older_format(&golden.join("v5-quadtree-jacksboro-utm.fra")));
        assert!(older_format(&golden.join("v8-chunked-views-jacksboro.fra")));
        // Version 10 codes lifted planes anew: 9 is older now, and re-encoded.
        assert!(older_format(&golden.join("v9-quadtree-camera.fra")));
        assert!(!older_format(
            &golden.join("v10-projected-cdf97-camera.fra")
        ));
        assert!(!older_format(
            &golden.join("v10-chunked-views-rate-jacksboro.fra")
        ));
        // Unreadable or too short: left to the store, which names the problem.
        assert!(!older_format(&golden.join("missing.fra")));
    }
}
