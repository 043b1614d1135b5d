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
        fractile_codec::io::chunked::ChunkCache::shared(),
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
