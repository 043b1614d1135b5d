//! Hostile asset files, shared by the codec's tests and its fuzz bench: valid small assets of
//! every codec (from `testdata/`), crafted bombs, and the mutations a fuzzer makes of them.
//! The container is written here from its spec (docs/asset-format.md), not by the code under
//! test, so the crafted files say what the spec allows.

#![allow(dead_code)]

use std::path::PathBuf;

use fractile_codec::codecs::psa::PsaSettings;
use fractile_codec::codecs::quadtree::stream::PlaneHeader;
use fractile_codec::{Asset, QuadtreeSettings, Quantiser, Raster, RateMode, encode};
use fractile_proto::{AssetKind, AssetMeta, ColourModel, EncodeStats, SampleFormat};

/// A file of `testdata/`.
pub(crate) fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// A w x h crop of a real raster at (x, y).
pub(crate) fn crop(r: &Raster, x: usize, y: usize, w: usize, h: usize) -> Raster {
    let mut c = r.clone();
    c.width = w;
    c.height = h;
    let rows = |ch: &[f32]| -> Vec<f32> {
        (0..h)
            .flat_map(|j| ch[(y + j) * r.width + x..(y + j) * r.width + x + w].to_vec())
            .collect()
    };
    c.channels = r.channels.iter().map(|ch| rows(ch)).collect();
    c.valid = r.valid.as_ref().map(|v| {
        (0..h)
            .flat_map(|j| v[(y + j) * r.width + x..(y + j) * r.width + x + w].to_vec())
            .collect()
    });
    c.georef = None;
    c
}

/// The container around a payload, as docs/asset-format.md lays it out, with its CRC.
pub(crate) fn container(version: u16, kind: u8, codec: u8, meta: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(b"FRACTILE");
    out.extend_from_slice(&version.to_le_bytes());
    out.push(kind);
    out.push(codec);
    out.extend_from_slice(&(meta.len() as u32).to_le_bytes());
    out.extend_from_slice(meta);
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(payload);
    reseal_append(&mut out);
    out
}

fn reseal_append(out: &mut Vec<u8>) {
    let crc = crc32fast::hash(out);
    out.extend_from_slice(&crc.to_le_bytes());
}

/// Writes a valid checksum over a mutated file (its last four bytes), as an attacker would. A
/// chunked container (version 6, from the spec) gets its header's checksum written instead,
/// so that mutations of its table reach the reader's checks of the layout.
pub(crate) fn reseal(bytes: &mut Vec<u8>) {
    if bytes.len() < 4 {
        return;
    }
    if bytes.len() >= 20 && &bytes[..8] == b"FRACTILE" && bytes[8..10] == [6, 0] {
        let len = |at: usize| {
            bytes
                .get(at..at + 4)
                .map(|b| u32::from_le_bytes(b.try_into().unwrap()) as usize)
        };
        if let Some(m) = len(12)
            && let Some(t) = len(16 + m)
            && let Some(end) = (20 + m).checked_add(t).filter(|&e| e + 4 <= bytes.len())
        {
            let crc = crc32fast::hash(&bytes[..end]);
            bytes[end..end + 4].copy_from_slice(&crc.to_le_bytes());
        }
        return;
    }
    bytes.truncate(bytes.len() - 4);
    reseal_append(bytes);
}

/// Metadata of a grey image of `w x h`.
pub(crate) fn grey_meta(w: u32, h: u32) -> AssetMeta {
    AssetMeta {
        kind: AssetKind::Image,
        width: w,
        height: h,
        channels: 1,
        colour: ColourModel::Grey,
        sample: SampleFormat::U8,
        units: None,
        value_min: 0.0,
        value_max: 255.0,
        nodata: None,
        georef: None,
        encoder: "crafted".into(),
        stats: EncodeStats::default(),
    }
}

/// A quadtree file claiming a `side x side` frame (and grid) whose transform stream is
/// `stream`: with an empty stream, the frame bomb of issue 35.
pub(crate) fn frame_bomb(side: u32, min_size: u32, levels: u32, stream: Vec<u8>) -> Vec<u8> {
    let header = PlaneHeader {
        frame: [side, side],
        valid: [side as f32, side as f32],
        min_size,
        levels,
        domain_steps: (0..levels).map(|l| (min_size << l) * 2).collect(),
        quantiser: Quantiser::default(),
    };
    let payload = fractile_proto::encode(&(vec![(header, stream)], None::<Vec<u8>>));
    container(
        4,
        0,
        1,
        &fractile_proto::encode(&grey_meta(side, side)),
        &payload,
    )
}

/// A real asset whose metadata claims a `w x h` grid its planes do not code: the metadata
/// bomb of issue 35.
pub(crate) fn metadata_bomb(real: &[u8], w: u32, h: u32) -> Vec<u8> {
    let asset = Asset::from_bytes(real).expect("a valid asset");
    let mut meta = asset.meta.clone();
    meta.width = w;
    meta.height = h;
    let m_len = u32::from_le_bytes(real[12..16].try_into().unwrap()) as usize;
    let payload = &real[20 + m_len..real.len() - 4];
    container(
        4,
        real[10],
        real[11],
        &fractile_proto::encode(&meta),
        payload,
    )
}

/// Small valid assets of every codec, with a name: quadtree grey, colour and height field with
/// nodata, FIS, psa2d, IFS3D, a chunked container and curves.
pub(crate) fn sources() -> Vec<(&'static str, Vec<u8>)> {
    let quick = |r: &Raster, bpp: f64| {
        let settings = QuadtreeSettings {
            rate: RateMode::TargetBpp(bpp),
            ..QuadtreeSettings::default()
        };
        encode(r, &settings, &|_, _| {}).expect("encodes").bytes
    };
    let camera = Raster::open(&data("camera.png")).unwrap();
    let astronaut = Raster::open(&data("astronaut.png")).unwrap();
    let utm = Raster::open(&data("jacksboro-utm.tif")).unwrap();
    let jacksboro = Raster::open(&data("jacksboro.tif")).unwrap();
    let mut out = vec![
        (
            "quadtree-grey",
            quick(&crop(&camera, 200, 100, 64, 64), 1.0),
        ),
        (
            "quadtree-colour",
            quick(&crop(&astronaut, 100, 60, 49, 37), 1.5),
        ),
        // A corner with nodata (the warp's edge).
        ("quadtree-nodata", quick(&crop(&utm, 0, 0, 48, 48), 2.0)),
    ];
    let fis = fractile_codec::codecs::fis::FisSettings {
        spacing: 4,
        ..Default::default()
    };
    out.push((
        "fis",
        fractile_codec::encode(&crop(&jacksboro, 10, 10, 33, 29), &fis, &|_, _| {})
            .unwrap()
            .bytes,
    ));
    let psa = PsaSettings {
        region: 4,
        ..PsaSettings::default()
    };
    out.push((
        "psa2d",
        fractile_codec::encode(&crop(&camera, 60, 60, 40, 40), &psa, &|_, _| {})
            .unwrap()
            .bytes,
    ));
    let mesh = fractile_codec::mesh::Mesh::read(&data("mesh/fandisk.off")).unwrap();
    let settings = fractile_codec::encode::volume::MeshSettings {
        grid: 16,
        ..Default::default()
    };
    out.push((
        "ifs3d",
        fractile_codec::encode::volume::encode_mesh(&mesh, &settings, "fandisk")
            .unwrap()
            .bytes,
    ));
    // Chunked (version 6): 3 x 2 chunks of 64 and an overview.
    let part = crop(&jacksboro, 0, 0, 190, 130);
    let one = |r: &Raster| fractile_codec::encode_default(r, 1.0, &|_, _| {});
    out.push((
        "chunked",
        fractile_codec::encode::chunked::encode_chunked(&part, 64, &one, &|_, _| {})
            .unwrap()
            .bytes,
    ));
    let text = std::fs::read_to_string(data("curve/coast5.geojson")).unwrap();
    let lines = fractile_codec::codecs::curve::geojson::read(&text).unwrap();
    let curve = fractile_codec::codecs::curve::CurveSettings {
        tolerance: 0.05,
        ..Default::default()
    };
    out.push((
        "curve",
        fractile_codec::encode::curve::encode_asset(&lines[..2], &curve, "coast")
            .unwrap()
            .bytes,
    ));
    out
}

/// One change a fuzzer makes to a file.
#[derive(Clone, Debug)]
pub(crate) enum Mutation {
    /// Sets the byte at (position modulo length) to a value.
    Byte(usize, u8),
    /// Writes a little-endian u32 at a position (a length, a size, a count).
    Word(usize, u32),
    /// Cuts the file at a position.
    Truncate(usize),
    /// Inserts bytes at a position.
    Insert(usize, Vec<u8>),
}

/// Words that make sizes and lengths interesting.
pub(crate) const WORDS: [u32; 8] = [
    0,
    1,
    2,
    0xFFFF,
    0x1_0000,
    0x7FFF_FFFF,
    0xFFFF_FFFF,
    0x4000_0000,
];

/// Applies mutations, then writes a valid checksum.
pub(crate) fn mutate(source: &[u8], mutations: &[Mutation]) -> Vec<u8> {
    let mut b = source.to_vec();
    for m in mutations {
        let n = b.len().max(1);
        match m {
            Mutation::Byte(at, v) => {
                if let Some(x) = b.get_mut(at % n) {
                    *x = *v;
                }
            }
            Mutation::Word(at, v) => {
                let at = at % n;
                for (k, byte) in v.to_le_bytes().into_iter().enumerate() {
                    if let Some(x) = b.get_mut(at + k) {
                        *x = byte;
                    }
                }
            }
            Mutation::Truncate(at) => b.truncate((at % n).max(24)),
            Mutation::Insert(at, bytes) => {
                let at = at % n;
                b.splice(at..at, bytes.iter().copied());
            }
        }
    }
    reseal(&mut b);
    b
}

/// Limits a fuzzer reads under: small enough that an accepted mutant stays cheap.
pub(crate) fn fuzz_limits() -> fractile_codec::AssetLimits {
    fractile_codec::AssetLimits {
        max_pixels: 1 << 22,
        max_decode_bytes: 256 << 20,
    }
}

/// Reads a (mutated) file and, if it is accepted, decodes a little of it every way a server
/// would: points, a small raster, a volume's distances, a curve's levels. Returns whether it
/// was accepted. Panics (a test failure) only if the code under test panics.
pub(crate) fn exercise(bytes: &[u8]) -> bool {
    let Ok(asset) = Asset::from_bytes_limited(bytes, &fuzz_limits()) else {
        return false;
    };
    if asset.volume().is_some() {
        let _ = asset.distances(&[[0.0, 0.0, 0.0], [0.3, -0.2, 0.1]], 8, 0.0);
    } else if let Some(c) = &asset.curves() {
        for level in 0..=c.set.finest().min(3) {
            let _ = c.set.at_level(level);
        }
    } else {
        let _ = asset.point(0.5, 0.5, 8);
        let _ = asset.point(0.999, 0.001, 8);
        // A fine grid (continuous chains) and a coarse one (a pixel over many cells: the
        // discrete path).
        for (w, h) in [(9usize, 7usize), (3, 2)] {
            let xs = (0..w).map(|i| Some((i as f32 + 0.5) / w as f32)).collect();
            let ys = (0..h).map(|j| Some((j as f32 + 0.5) / h as f32)).collect();
            let pixels =
                fractile_codec::geo::Pixels::grid(xs, ys, [1.0 / w as f32, 1.0 / h as f32]);
            let _ = asset.sample(&pixels, 6, 0.0);
        }
    }
    true
}
