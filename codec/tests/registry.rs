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

/// Every name the registry gives (`--codec`, Python's `codec=`) makes settings of a codec that
/// writes an asset answering to that name, from a rate and from no options (each codec's
/// defaults, or a refusal naming the rate it needs); the names are distinct; an option the codec does not read, and an unknown name, are
/// refused by name.
#[test]
fn every_codec_name_encodes_under_that_name() {
    use fractile_codec::encode::Options;
    let raster = dem();
    let names = CodecSettings::names();
    let mut distinct: Vec<&str> = names.iter().map(|(n, _)| *n).collect();
    distinct.sort_unstable();
    distinct.dedup();
    assert_eq!(distinct.len(), names.len(), "two codecs share a name");
    assert!(names.len() >= 7, "{names:?}");
    for &(name, help) in &names {
        assert!(!help.is_empty(), "{name}: no help");
        let takes = CodecSettings::takes(name).expect("a listed name is taken");
        for options in [
            Options::default(),
            Options {
                target_bpp: Some(2.0),
                ..Options::default()
            },
        ] {
            let settings = match CodecSettings::named(name, &options, raster.kind) {
                Ok(s) => s,
                // A codec may need a rate: it says which.
                Err(e) if options.given().is_empty() => {
                    assert!(e.to_string().contains("--target-bpp"), "{name}: {e}");
                    continue;
                }
                Err(e) => panic!("{name} with {:?}: {e}", options.given()),
            };
            let enc = encode(&raster, &settings, &|_, _| {})
                .unwrap_or_else(|e| panic!("{name} with {:?}: {e}", options.given()));
            assert_eq!(enc.asset.codec_name(), name);
            if options.target_bpp.is_some() {
                assert!(enc.bpp() <= 2.0, "{name}: {} bpp over 2", enc.bpp());
            }
        }
        let untaken = ["max-error", "spacing", "tolerance"]
            .into_iter()
            .find(|o| !takes.contains(o))
            .expect("no codec reads all three");
        let options = match untaken {
            "max-error" => Options {
                max_error: Some(1.0),
                ..Options::default()
            },
            "spacing" => Options {
                spacing: Some(4),
                ..Options::default()
            },
            _ => Options {
                tolerance: Some(1.0),
                ..Options::default()
            },
        };
        let err = CodecSettings::named(name, &options, raster.kind)
            .expect_err("an option the codec does not read")
            .to_string();
        assert!(
            err.contains(&format!("--{untaken}")) && err.contains(name),
            "{err}"
        );
    }
    let err = CodecSettings::named("jpeg", &Options::default(), raster.kind)
        .expect_err("no such codec")
        .to_string();
    assert!(err.contains("jpeg") && err.contains("projected"), "{err}");
}

/// A plane codec says what is wrong with a plane by kind (`FormatError`): a header that does not
/// fit the metadata is a header error, a truncated stream a stream error; each codec alike.
#[test]
fn a_plane_codec_tells_a_bad_header_from_a_bad_stream() {
    use fractile_codec::FormatError;
    use fractile_codec::asset::Coding;
    use fractile_codec::codecs::plane::{Build, PlaneCodec};
    let raster = dem();
    let mut kinds = 0;
    for &codec in Codec::ALL {
        let Some(mut settings) = CodecSettings::default_for(codec) else {
            continue;
        };
        if let CodecSettings::Projected(s) = &mut settings {
            s.target_bpp = Some(2.0);
        }
        let enc = encode(&raster, &settings, &|_, _| {}).expect("encodes");
        let meta = enc.asset.meta.clone();
        let mut wider = meta.clone();
        wider.width += 8;
        let check = |header: Result<(), FormatError>, stream: Result<(), FormatError>| {
            assert!(
                matches!(header, Err(FormatError::Header(_))),
                "{codec:?}: {header:?}"
            );
            assert!(
                matches!(stream, Err(FormatError::Stream(_))),
                "{codec:?}: {stream:?}"
            );
        };
        fn both<H: PlaneCodec>(
            h: &H,
            s: &[u8],
            meta: &fractile_proto::AssetMeta,
            wider: &fractile_proto::AssetMeta,
        ) -> (Result<(), FormatError>, Result<(), FormatError>) {
            // The quadtree's header holds its own extent: a wider asset is refused by `cost`.
            let header = h
                .cost(wider, s)
                .map(|_| ())
                .and_then(|()| h.operator(wider, s, Build::Whole).map(|_| ()));
            let stream = h
                .operator(meta, &s[..s.len() / 3], Build::Whole)
                .map(|_| ());
            (header, stream)
        }
        let (header, stream) = match &enc.asset.planes()[0].coding {
            Coding::Quadtree { header, stream } => both(header, stream, &meta, &wider),
            Coding::Fis { header, stream } => both(header, stream, &meta, &wider),
            Coding::Psa { header, stream } => both(header, stream, &meta, &wider),
            Coding::Projected { header, stream } => both(header, stream, &meta, &wider),
            // A codec added to the registry is checked once its arm is here.
            #[allow(unreachable_patterns)]
            _ => continue,
        };
        check(header, stream);
        kinds += 1;
    }
    assert!(kinds >= 4);
}
