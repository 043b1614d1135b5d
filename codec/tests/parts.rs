//! A chunked encode split in parts (`fractile encode --part I/N`, `fractile assemble`): the
//! parts of every share, assembled, are the bytes of the encode in one process; a missing,
//! repeated, foreign or corrupt part is refused by name and nothing is written.

use std::path::{Path, PathBuf};

use fractile_codec::encode::assembly;
use fractile_codec::encode::chunked::{Share, encode_chunked_file};
use fractile_codec::encode::parts::encode_chunked_part;
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
    encode_chunked_part(
        &mut rows,
        (64, share, settings, None),
        &one,
        &|_, _| {},
        &out,
    )
    .unwrap();
    out
}

fn assemble(
    parts: &[PathBuf],
    out: &Path,
) -> Result<fractile_codec::encode::Written, fractile_codec::Error> {
    assembly::assemble(parts, out, &|_, r| one(r), &|_, _| {})
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
    // A share is a band of the source's 6 rows of chunks: 7 parts are too many.
    let mut rows = GeoTiff::open(&testdata(name)).unwrap();
    let seven = Share { index: 0, count: 7 };
    let err = encode_chunked_part(
        &mut rows,
        (64, seven, "s", None),
        &one,
        &|_, _| {},
        &dir.join("7"),
    )
    .expect_err("7 parts of 6 rows")
    .to_string();
    assert!(err.contains("at most 6 parts"), "{err}");

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
    // A byte flipped in a chunk's file (just after the header, whose length is at bytes
    // 10..14), in the overview rows a part hands on (its end), and a part cut short.
    let good = std::fs::read(&parts[1]).unwrap();
    let n = good.len();
    let body = 18 + u32::from_le_bytes(good[10..14].try_into().unwrap()) as usize;
    let corrupt = dir.join("corrupt");
    let mut set = parts.clone();
    set[1] = corrupt.clone();
    for (at, what, says) in [
        (body + 10, "a corrupt chunk", "chunk"),
        (
            n - 100,
            "corrupt overview rows",
            "overview rows are corrupt",
        ),
    ] {
        let mut bytes = good.clone();
        bytes[at] ^= 0x40;
        std::fs::write(&corrupt, &bytes).unwrap();
        let err = refused(&set, what);
        assert!(err.contains("corrupt") && err.contains(says), "{err}");
    }
    let bytes = good;
    std::fs::write(&corrupt, &bytes[..n - 10]).unwrap();
    let err = refused(&set, "a part cut short");
    assert!(err.contains("cut short"), "{err}");
    std::fs::write(&corrupt, b"not a part").unwrap();
    let err = refused(&set, "not a part");
    assert!(err.contains("not a part file"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An image's overviews are all coded (no views): its parts hand on their first overview's
/// rows, three channels, and `assemble` codes every overview level, the same bytes again.
#[test]
fn an_image_in_parts_is_the_bytes_of_one_encode() {
    let dir = std::env::temp_dir().join(format!("fractile-parts-rgb-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    use fractile_codec::rows::Rows;
    let whole = Raster::open(&testdata("astronaut.png")).unwrap();
    // Its top 192 rows: three rows of chunks, one a part.
    let image = fractile_codec::rows::InMemory::new(&whole)
        .read(0, 192)
        .unwrap();
    assert_eq!(image.channels.len(), 3);
    let single = dir.join("single.fra");
    let mut rows = fractile_codec::rows::InMemory::new(&image);
    encode_chunked_file(&mut rows, 64, &one, &|_, _| {}, &single).unwrap();
    let parts: Vec<PathBuf> = (0..3)
        .map(|index| {
            let out = dir.join(format!("part{index}"));
            let mut rows = fractile_codec::rows::InMemory::new(&image);
            let share = Share { index, count: 3 };
            encode_chunked_part(&mut rows, (64, share, "s", None), &one, &|_, _| {}, &out).unwrap();
            out
        })
        .collect();
    let joined = dir.join("joined.fra");
    assemble(&parts, &joined).unwrap();
    let (a, b) = (
        std::fs::read(&single).unwrap(),
        std::fs::read(&joined).unwrap(),
    );
    assert!(a.len() > 10_000);
    assert!(a == b, "the assembled image differs from the single encode");
    std::fs::remove_dir_all(&dir).unwrap();
}
