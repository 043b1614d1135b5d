//! Asset files written by every earlier format version's own encoder (`testdata/golden/`, made
//! by the `fractile` binary of the commit before each version change; see its README) are read
//! by this build: each decodes to the quality its encoder measured when it wrote it, and the
//! curve assets of versions before 3 are refused by name.

use std::path::PathBuf;

use fractile_codec::metrics;
use fractile_codec::{Asset, Raster};
use fractile_proto::AssetKind;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// The source each golden file was encoded from.
fn source(name: &str) -> &'static str {
    match name {
        n if n.contains("jacksboro-utm") => "jacksboro-utm.tif",
        n if n.contains("jacksboro") => "jacksboro.tif",
        n if n.contains("camera") => "camera.png",
        n if n.contains("astronaut") => "astronaut.png",
        n if n.contains("fandisk") => "mesh/fandisk.off",
        _ => "curve/coast5.geojson",
    }
}

#[test]
fn every_format_version_is_read_as_it_was_written() {
    let mut files: Vec<PathBuf> = std::fs::read_dir(data("golden"))
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "fra"))
        .collect();
    files.sort();
    assert_eq!(
        files.len(),
        48,
        "six codecs a version, versions 1 to 5; version 6 chunked; version 7 chunked, with and \
         without views; version 8 chunked, bounded, rate and max-error, all with views; the \
         projected codec's three multiresolutions in version 5; version 9 the quadtree, the \
         projected pyramid and CDF 9/7, and chunked bounded, rate and max-error; version 10 the \
         projected CDF 9/7 on grey and colour, and chunked rate"
    );
    let mut versions = std::collections::BTreeSet::new();
    for path in files {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let bytes = std::fs::read(&path).unwrap();
        // The file really is of the version its name says (written by that encoder).
        let version = u16::from_le_bytes([bytes[8], bytes[9]]);
        assert!(name.starts_with(&format!("v{version}-")), "{name}");
        versions.insert(version);
        let read = Asset::from_bytes(&bytes);
        if name.contains("curve") && version < 3 {
            let err = read.expect_err(&name).to_string();
            assert!(err.contains("encode the source again"), "{name}: {err}");
            continue;
        }
        let asset = read.unwrap_or_else(|e| panic!("{name}: {e}"));
        // Version 5 added the source-error map, to rasters only; version 6 is the chunked
        // container, whose chunks are version-5 files with their maps; version 7 adds views,
        // version 8 a coded level above them and views of the pyramid (bounded, max-error);
        // version 9 numbers both containers (the pyramid's details in two-rate contexts).
        let raster = matches!(asset.meta.kind, AssetKind::Image | AssetKind::HeightField);
        let chunked = name.contains("chunked");
        assert_eq!(asset.chunked().is_some(), chunked, "{name}");
        // Versions 6 to 8 are chunked only, 1 to 5 never.
        assert!(version >= 9 || chunked == (version >= 6), "{name}");
        if let Some(c) = &asset.chunked() {
            // Version 7 viewed one level, version 8 views two below a coded one.
            let views = match () {
                _ if !name.contains("views") => 0,
                _ if version == 7 => 1,
                _ => 2,
            };
            assert_eq!(c.table.views.len(), views, "{name}");
            // Every level answers: a view decodes from its source chunk's bytes.
            for level in 0..c.table.levels.len() {
                let some = (0..c.table.levels[level].chunks.len())
                    .filter_map(|i| c.chunk(level, i).unwrap())
                    .count();
                assert!(some > 0, "{name}: level {level}");
            }
        }
        assert_eq!(
            asset.source_error.is_some(),
            version >= 5 && raster && !chunked,
            "{name}"
        );
        // A projected file holds the multiresolution its name says.
        if name.contains("projected") {
            use fractile_codec::asset::Coding;
            use fractile_codec::codecs::projected::pyramid::Order;
            let Coding::Projected { header, .. } = &asset.planes()[0].coding else {
                panic!("{name}: not a projected plane");
            };
            // Version 10 codes lifted coefficients in two-rate contexts.
            let want = match () {
                _ if name.contains("lifted") && version >= 10 => vec![Order::LiftedTwoRate],
                _ if name.contains("cdf97") && version >= 10 => vec![Order::Lifted97TwoRate],
                _ if name.contains("lifted") => vec![Order::Lifted],
                _ if name.contains("cdf97") => vec![Order::Lifted97],
                _ if version >= 9 => Order::PYRAMIDS.to_vec(),
                _ => vec![Order::Separable, Order::Quincunx],
            };
            assert!(want.contains(&header.order), "{name}: {:?}", header.order);
        }
        // A chunked file of version 9 on holds chunks of its own version, whose pyramids are
        // coded in two-rate contexts (and from 10 on its lifted planes too); those of 6 to 8,
        // chunks of version 5.
        if let Some(c) = &asset.chunked() {
            use fractile_codec::asset::Coding;
            let chunk = c.chunk(0, 0).unwrap().expect("a chunk with cells");
            let Coding::Projected { header, .. } = &chunk.planes()[0].coding else {
                panic!("{name}: not a projected chunk");
            };
            let two_rate_since = if header.order.lifting().is_none() {
                9
            } else {
                10
            };
            assert_eq!(header.order.two_rate(), version >= two_rate_since, "{name}");
            let files = fractile_codec::chunked::chunk_files(&c.table, &bytes);
            let chunk_version = u16::from_le_bytes([files[0][0][8], files[0][0][9]]);
            assert_eq!(
                chunk_version,
                if version >= 9 { version } else { 5 },
                "{name}"
            );
        }
        match asset.meta.kind {
            AssetKind::Image | AssetKind::HeightField => {
                let src = Raster::open(&data(source(&name))).unwrap();
                let (decoded, _) = asset.decode_native();
                let e = metrics::compare(
                    &src.channels,
                    &decoded.channels,
                    src.valid.as_deref(),
                    asset.meta.psnr_peak(),
                );
                let written = asset.meta.stats.psnr;
                // A chunked file's figures are summed over its chunks' coded cells, the
                // overlaps counted in both neighbours; in rate mode a chunk's edge cells carry
                // more error than its inside, so the written figure is the lower (by 0.17 dB
                // for chunks of 128 with an overlap of 4, measured).
                let over = if asset.chunked().is_some() {
                    0.25
                } else {
                    0.05
                };
                assert!(
                    e.psnr - written > -0.05 && e.psnr - written < over,
                    "{name}: decodes to {:.3} dB, written at {written:.3} dB",
                    e.psnr
                );
            }
            AssetKind::Volume => {
                let (mesh, _) = asset.volume_mesh(None, 16, 12, 0.0).unwrap();
                assert!(
                    mesh.triangles.len() > 200,
                    "{name}: {}",
                    mesh.triangles.len()
                );
            }
            AssetKind::Curve => {
                let text = std::fs::read_to_string(data(source(&name))).unwrap();
                let lines = fractile_codec::codecs::curve::geojson::read(&text).unwrap();
                let set = &asset.curves().unwrap().set;
                // As a user gets it: GeoJSON of the finest level, one line per input ring with
                // its points.
                let doc = fractile_codec::codecs::curve::geojson::write(
                    &set.at_level(set.finest()),
                    set.finest(),
                    "degrees",
                );
                let back = fractile_codec::codecs::curve::geojson::read(
                    std::str::from_utf8(&doc).unwrap(),
                )
                .unwrap();
                assert_eq!(back.len(), lines.len(), "{name}");
                for (got, want) in back.iter().zip(&lines) {
                    assert_eq!(got.points.len(), want.points.len(), "{name}");
                    assert_eq!(got.closed, want.closed, "{name}");
                }
            }
        }
    }
    assert_eq!(
        versions.into_iter().collect::<Vec<_>>(),
        vec![1, 2, 3, 4, 5, 6, 7, 8, 9, 10]
    );
}
