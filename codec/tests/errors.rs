//! The codec's errors by kind (issue 57): each names its kind, the file it concerns and the error
//! beneath, so that callers branch on them (the server: a corrupt chunk is 500, a store that is
//! down 503) rather than on their text, and the text people read stays what it was.

use fractile_codec::{Asset, Error, Raster};

#[test]
fn a_missing_input_is_an_input_error_naming_the_file_and_the_io_error() {
    let missing = std::path::Path::new("/nonexistent/fractile/dem.tif");
    let e = Raster::open(missing).unwrap_err();
    assert!(matches!(e, Error::Input { .. }), "{e:?}");
    assert_eq!(e.path(), Some(missing));
    let beneath = std::error::Error::source(&e).expect("the I/O error beneath");
    let io = std::fs::File::open(missing).unwrap_err();
    assert_eq!(beneath.to_string(), io.to_string());
    // What people read: the kind, the file, the cause.
    assert_eq!(e.to_string(), format!("input: {}: {io}", missing.display()));
}

#[test]
fn a_corrupt_asset_is_an_asset_error_naming_the_file() {
    let dir = std::env::temp_dir().join(format!("fractile-errors-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("junk.fra");
    std::fs::write(&path, b"FRACTILE\x05\x00 not an asset at all").unwrap();
    let e = Asset::open(
        &path,
        &fractile_codec::AssetLimits::default(),
        fractile_codec::chunked::ChunkCache::shared(),
    )
    .unwrap_err();
    assert!(matches!(e, Error::Asset { .. }), "{e:?}");
    assert_eq!(e.path(), Some(path.as_path()));
    assert!(
        e.message().starts_with(&path.display().to_string()),
        "{}",
        e.message()
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn context_keeps_the_kind_the_file_and_the_cause() {
    let io = std::io::Error::other("disk on fire");
    let e = Error::output("writing a chunk")
        .at("/tmp/x.fra")
        .caused_by(io)
        .within("chunk 3");
    assert!(matches!(e, Error::Output { .. }));
    assert_eq!(e.message(), "chunk 3: writing a chunk");
    assert_eq!(e.path(), Some(std::path::Path::new("/tmp/x.fra")));
    assert_eq!(
        std::error::Error::source(&e).map(|s| s.to_string()),
        Some("disk on fire".into())
    );
    assert_eq!(e.to_string(), "output: chunk 3: writing a chunk");
}

/// What a writer checks (`check_opens`, from headers) is what a reader opens: on every golden
/// file, at limits from far too small to the default, the two agree. A writer that checked
/// less wrote files its own reader refused (Python's 8640 x 8640 in one piece).
#[test]
fn what_a_writer_checks_is_what_a_reader_opens() {
    let golden = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata/golden");
    let mut files = 0;
    for e in std::fs::read_dir(golden).unwrap() {
        let path = e.unwrap().path();
        let bytes = std::fs::read(&path).unwrap();
        for mib in [0u64, 1, 4, 16, 64, 3 << 10] {
            let limits = fractile_codec::AssetLimits {
                max_decode_bytes: mib << 20,
                ..Default::default()
            };
            let checked = fractile_codec::asset::check_opens(&bytes, &limits);
            let opened = Asset::from_bytes_limited(&bytes, &limits);
            assert_eq!(
                checked.is_ok(),
                opened.is_ok(),
                "{} at {mib} MiB: check {:?}, open {:?}",
                path.display(),
                checked.err(),
                opened.err()
            );
        }
        files += 1;
    }
    assert!(files > 20);
}

/// Values beyond what the codecs hold in float32 are refused with a message that names the
/// usual cause (an undeclared nodata marker), not decoded to infinity under a max error of 0.
#[test]
fn extreme_values_are_refused_naming_nodata() {
    let mut v = vec![100.0f32; 64 * 64];
    v[5] = -3.4028235e38;
    let e =
        Raster::from_values(64, 64, v.clone(), fractile_proto::AssetKind::HeightField).unwrap_err();
    assert!(matches!(e, Error::Input { .. }), "{e:?}");
    assert!(e.to_string().contains("nodata"), "{e}");
    // Declared as nodata, the same cells encode.
    let r = Raster::from_channels(
        64,
        64,
        vec![v],
        fractile_proto::AssetKind::HeightField,
        fractile_proto::SampleFormat::F32,
        Some(-3.4028235e38),
    )
    .unwrap();
    assert!(!r.is_valid(5));
}
