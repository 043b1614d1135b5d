//! The registry of plane codecs (`codecs/mod.rs`, one line a codec): every codec it lists is
//! reachable through the one encoder entry, writes its own codec byte and name, and reads back
//! as itself, so that a codec added by its line alone works end to end.

use fractile_codec::Codec;
use fractile_codec::{Asset, CodecSettings, Raster, encode};

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// A 64 x 64 window of a real DEM: small enough for every codec's defaults in a second.
fn dem() -> Raster {
    let r = Raster::open(&testdata("jacksboro.tif")).expect("jacksboro");
    let (x, y, w, h) = (40, 40, 64, 64);
    let mut c = r.clone();
    (c.width, c.height) = (w, h);
    c.channels = r
        .channels
        .iter()
        .map(|ch| {
            (0..h)
                .flat_map(|j| ch[(y + j) * r.width + x..][..w].to_vec())
                .collect()
        })
        .collect();
    c.valid = None;
    c.georef = None;
    c
}

#[test]
fn every_codec_byte_names_one_codec() {
    for &c in Codec::ALL {
        assert_eq!(Codec::from_byte(c.byte()), Some(c), "{c:?}");
    }
    let mut bytes: Vec<u8> = Codec::ALL.iter().map(|c| c.byte()).collect();
    bytes.sort_unstable();
    bytes.dedup();
    assert_eq!(bytes.len(), Codec::ALL.len(), "two codecs share a byte");
    assert_eq!(Codec::from_byte(0), None);
    assert_eq!(Codec::from_byte(200), None);
}

#[test]
fn every_registered_plane_codec_encodes_and_reads_back_as_itself() {
    let raster = dem();
    let mut planes = 0;
    for &codec in Codec::ALL {
        let Some(mut settings) = CodecSettings::default_for(codec) else {
            assert!(matches!(codec, Codec::Octree | Codec::Curve), "{codec:?}");
            continue;
        };
        planes += 1;
        // The projected codec has no default rate: a bound or a size is the user's to give.
        if let CodecSettings::Projected(s) = &mut settings {
            s.target_bpp = Some(2.0);
        }
        assert_eq!(settings.codec(), codec);
        let enc = encode(&raster, &settings, &|_, _| {})
            .unwrap_or_else(|e| panic!("{codec:?} with its defaults: {e}"));
        assert_eq!(enc.asset.codec(), codec);
        let bytes = enc.asset.to_bytes();
        assert_eq!(
            bytes[11],
            codec.byte(),
            "{codec:?}: the container's codec byte"
        );
        let back = Asset::from_bytes(&bytes).expect("reads back");
        assert_eq!(back.codec(), codec);
        assert_eq!(back.codec_name(), enc.asset.codec_name());
        assert_eq!(
            back.to_bytes(),
            bytes,
            "{codec:?}: written again, the same bytes"
        );
        if let Some(name) = codec.name() {
            assert_eq!(enc.asset.codec_name(), name);
        }
        // The operator decodes through the registry's dispatch: the decoded grid is near the
        // source (each codec's defaults keep within a tenth of the relief).
        let (decoded, _) = back.decode_native();
        let relief = (raster.channels[0].iter().copied().fold(f32::MIN, f32::max)
            - raster.channels[0].iter().copied().fold(f32::MAX, f32::min))
            as f64;
        let rmse = (decoded.channels[0]
            .iter()
            .zip(&raster.channels[0])
            .map(|(&d, &s)| (f64::from(d) - f64::from(s)).powi(2))
            .sum::<f64>()
            / raster.channels[0].len() as f64)
            .sqrt();
        assert!(
            rmse < 0.1 * relief,
            "{codec:?}: RMSE {rmse} over relief {relief}"
        );
    }
    assert!(
        planes >= 4,
        "the registry lists the four plane codecs at least"
    );
}
