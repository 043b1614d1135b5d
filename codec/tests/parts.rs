//! A chunked encode split in parts (`fractile encode --part I/N`, `fractile assemble`): the
//! parts of every share, assembled, are the bytes of the encode in one process; a missing,
//! repeated, foreign or corrupt part is refused by name and nothing is written.

use std::path::{Path, PathBuf};

use fractile_codec::encode::chunked::{Share, encode_chunked_file};
use fractile_codec::encode::parts::{assemble, encode_chunked_part};
use fractile_codec::rows::GeoTiff;
use fractile_codec::{Encoded, Raster, encode_default};

fn testdata(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

fn one(part: &Raster) -> Result<Encoded, fractile_codec::Error> {
    encode_default(part, 0.8, &|_, _| {})
}

fn part(dir: &Path, name: &str, share: Share, settings: &str) -> PathBuf {
    let out = dir.join(format!(
        "{name}-{settings}-{}-of-{}",
        share.index, share.count
    ));
    let mut rows = GeoTiff::open(&testdata(name)).unwrap();
    encode_chunked_part(&mut rows, (64, share, settings), &one, &|_, _| {}, &out).unwrap();
    out
}

#[test]
fn four_parts_assembled_are_the_bytes_of_one_encode() {
    let dir = std::env::temp_dir().join(format!("fractile-parts-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Nodata around a rotated grid: some chunks of some shares have no data.
    let name = "jacksboro-utm.tif";
    let single = dir.join("single.fra");
    let mut rows = GeoTiff::open(&testdata(name)).unwrap();
    let whole = encode_chunked_file(&mut rows, 64, &one, &|_, _| {}, &single).unwrap();
    let shares: Vec<Share> = (0..4).map(|index| Share { index, count: 4 }).collect();
    // Parts in any order.
    let mut parts: Vec<PathBuf> = shares
        .iter()
        .map(|&s| part(&dir, name, s, "bpp 0.8"))
        .collect();
    parts.reverse();
    let joined = dir.join("joined.fra");
    let assembled = assemble(&parts, &joined).unwrap();
    let (a, b) = (
        std::fs::read(&single).unwrap(),
        std::fs::read(&joined).unwrap(),
    );
    assert!(a.len() > 10_000);
    assert!(a == b, "assembled parts differ from the single encode");
    assert_eq!(assembled.length, whole.length);
    assert_eq!(assembled.errors.rmse, whole.errors.rmse);
    assert_eq!(Share::parse("3/4").unwrap(), Share { index: 3, count: 4 });
    for bad in ["4/4", "1", "a/2", "0/0"] {
        assert!(Share::parse(bad).is_err(), "{bad}");
    }

    let refused = |parts: &[PathBuf], what: &str| {
        let out = dir.join("refused.fra");
        let err = assemble(parts, &out).expect_err(what).to_string();
        assert!(!out.exists(), "{what}: an output was written");
        err
    };
    let err = refused(&parts[..3], "a missing part");
    assert!(err.contains("missing"), "{err}");
    let err = refused(
        &[parts.clone(), vec![parts[0].clone()]].concat(),
        "a repeated part",
    );
    assert!(err.contains("both part"), "{err}");
    let other = part(&dir, name, shares[0], "bpp 1.0");
    let err = refused(
        &[vec![other], parts[..3].to_vec()].concat(),
        "other settings",
    );
    assert!(err.contains("settings"), "{err}");
    let foreign = part(&dir, "jacksboro.tif", shares[0], "bpp 0.8");
    let err = refused(
        &[vec![foreign], parts[..3].to_vec()].concat(),
        "another source",
    );
    assert!(err.contains("sources"), "{err}");
    // A byte flipped in a chunk's file, and a part cut short.
    let mut bytes = std::fs::read(&parts[1]).unwrap();
    let n = bytes.len();
    bytes[n - 100] ^= 0x40;
    let corrupt = dir.join("corrupt");
    std::fs::write(&corrupt, &bytes).unwrap();
    let mut set = parts.clone();
    set[1] = corrupt.clone();
    let err = refused(&set, "a corrupt chunk");
    assert!(err.contains("corrupt"), "{err}");
    std::fs::write(&corrupt, &bytes[..n - 10]).unwrap();
    let err = refused(&set, "a part cut short");
    assert!(err.contains("cut short"), "{err}");
    std::fs::write(&corrupt, b"not a part").unwrap();
    let err = refused(&set, "not a part");
    assert!(err.contains("not a part file"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
