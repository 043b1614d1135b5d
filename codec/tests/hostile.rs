//! Hostile asset files (issue 35): the crafted bombs are refused before anything large is
//! allocated, and mutated files of every codec, with their checksums made valid again, are
//! refused or decoded without a panic. `cargo bench -p fractile-codec --bench fuzz_assets`
//! runs the same mutations for longer and prints what it saw.

mod support;

use fractile_codec::{Asset, AssetLimits};
use proptest::prelude::*;
use support::hostile::*;

/// The crafted files kept in `testdata/hostile/` (see its README), each with what its refusal
/// must name.
const CRAFTED: [(&str, &str); 5] = [
    ("frame-bomb-65536.fra", "samples"),
    ("frame-bomb-16384.fra", "stream"),
    ("frame-bomb-16384-big-ranges.fra", "domains"),
    ("metadata-bomb-65536.fra", "samples"),
    ("metadata-bomb-16384.fra", "extent"),
];

fn crafted(name: &str) -> Vec<u8> {
    std::fs::read(data(&format!("hostile/{name}"))).expect("crafted file in testdata/hostile")
}

#[test]
fn crafted_bombs_are_refused_by_name() {
    for (name, says) in CRAFTED {
        let bytes = crafted(name);
        assert!(bytes.len() < 64 * 1024, "{name} is a small file");
        let err = Asset::from_bytes(&bytes).expect_err(name).to_string();
        assert!(err.contains(says), "{name}: {err}");
    }
}

/// With limits raised far past what the files claim, what their streams can hold still
/// refuses the frame bombs (the limits are not what stops them).
#[test]
fn frame_bombs_are_refused_by_their_streams_whatever_the_limits() {
    let wide = AssetLimits {
        max_pixels: u64::MAX,
        max_decode_bytes: u64::MAX,
    };
    for side in [16384, 65536] {
        let bytes = frame_bomb(side, 4, 5, Vec::new());
        let err = Asset::from_bytes_limited(&bytes, &wide)
            .unwrap_err()
            .to_string();
        assert!(err.contains("stream"), "{side}: {err}");
    }
    // A stream of real bytes but far too few for the frame: refused before the walk.
    let bytes = frame_bomb(16384, 4, 5, vec![0x5a; 300]);
    let err = Asset::from_bytes_limited(&bytes, &wide)
        .unwrap_err()
        .to_string();
    assert!(err.contains("needs more than"), "{err}");
}

/// A legitimate file of the same claim (a flat 4096^2 frame in four ranges) is read: the
/// checks refuse what a stream cannot hold, not large frames.
#[test]
fn a_flat_large_frame_in_a_few_ranges_is_read() {
    let flat = {
        // Four 2048 ranges, constant maps: split flag 1 then four leaves, coded by the
        // encoder's own stream writer.
        let header = fractile_codec::codecs::quadtree::stream::PlaneHeader {
            frame: [4096, 4096],
            valid: [4096.0, 4096.0],
            min_size: 4,
            levels: 11,
            domain_steps: (0..11).map(|l| (4u32 << l) * 2).collect(),
            quantiser: fractile_codec::Quantiser::default(),
        };
        let constant = fractile_codec::codecs::quadtree::search::Fit {
            sse: 0.0,
            weight: 0.0,
            contrast: 0,
            offset: 9,
            isometry: 0,
            domain: 0,
            slope: [0; 2],
            constant_sse: 0.0,
            constant_offset: 9,
            constant_slope: [0; 2],
        };
        let stream = fractile_codec::codecs::quadtree::stream::encode_plane(&header, &|l, _, _| {
            (l < 10).then_some(constant)
        });
        let payload = fractile_proto::encode(&(vec![(header, stream)], None::<Vec<u8>>));
        container(
            4,
            0,
            1,
            &fractile_proto::encode(&grey_meta(4096, 4096)),
            &payload,
        )
    };
    let asset = Asset::from_bytes(&flat).expect("a flat large frame is a valid asset");
    assert_eq!(asset.planes()[0].operator.transforms(), 4);
    // And the same claim with an empty stream is not.
    assert!(Asset::from_bytes(&frame_bomb(4096, 4, 11, Vec::new())).is_err());
}

#[test]
fn limits_refuse_what_they_name() {
    let real = &sources_once()[0].1;
    let tight = AssetLimits {
        max_pixels: 1000,
        ..AssetLimits::default()
    };
    let err = Asset::from_bytes_limited(real, &tight)
        .unwrap_err()
        .to_string();
    assert!(err.contains("max_asset_pixels"), "{err}");
    let tight = AssetLimits {
        max_decode_bytes: 1 << 10,
        ..AssetLimits::default()
    };
    let err = Asset::from_bytes_limited(real, &tight)
        .unwrap_err()
        .to_string();
    assert!(err.contains("max_decode_mib"), "{err}");
    assert!(Asset::from_bytes_limited(real, &AssetLimits::default()).is_ok());
}

/// Regenerates `testdata/hostile/` (run with `--ignored` after a format change).
#[test]
#[ignore]
fn write_crafted_files() {
    let dir = data("hostile");
    std::fs::create_dir_all(&dir).unwrap();
    let real = std::fs::read(data("hostile/source-camera-crop.fra")).unwrap_or_else(|_| {
        let b = sources().remove(0).1;
        std::fs::write(data("hostile/source-camera-crop.fra"), &b).unwrap();
        b
    });
    let files = [
        ("frame-bomb-65536.fra", frame_bomb(65536, 4, 5, Vec::new())),
        ("frame-bomb-16384.fra", frame_bomb(16384, 4, 5, Vec::new())),
        (
            "frame-bomb-16384-big-ranges.fra",
            frame_bomb(16384, 16, 12, Vec::new()),
        ),
        (
            "metadata-bomb-65536.fra",
            metadata_bomb(&real, 65536, 65536),
        ),
        (
            "metadata-bomb-16384.fra",
            metadata_bomb(&real, 16384, 16384),
        ),
    ];
    for (name, bytes) in files {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
}

fn sources_once() -> &'static [(&'static str, Vec<u8>)] {
    static S: std::sync::OnceLock<Vec<(&'static str, Vec<u8>)>> = std::sync::OnceLock::new();
    S.get_or_init(sources)
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (any::<usize>(), any::<u8>()).prop_map(|(a, v)| Mutation::Byte(a, v)),
        (any::<usize>(), prop::sample::select(WORDS.to_vec()))
            .prop_map(|(a, v)| Mutation::Word(a, v)),
        (any::<usize>(), any::<u32>()).prop_map(|(a, v)| Mutation::Word(a, v)),
        any::<usize>().prop_map(Mutation::Truncate),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(a, v)| Mutation::Insert(a, v)),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    /// Every codec's file, mutated and resealed: refused with an error or decoded, never a
    /// panic (proptest reports one as a failure, with the smallest mutation list).
    #[test]
    fn mutated_files_never_panic(
        which in 0usize..8,
        mutations in prop::collection::vec(mutation(), 1..4),
    ) {
        let (_, source) = &sources_once()[which];
        exercise(&mutate(source, &mutations));
    }
}

/// The sources themselves are accepted and decoded (so the fuzzing starts from valid files).
#[test]
fn every_source_is_valid() {
    let s = sources_once();
    assert_eq!(s.len(), 8);
    for (name, bytes) in s {
        assert!(exercise(bytes), "{name}");
    }
}
