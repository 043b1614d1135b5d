//! The error-bounded compressors a bounded DEM is measured against, for the benches: SZ3
//! (absolute bound), SPERR (point-wise error) and JPEG-LS near-lossless (CharLS), all through
//! python3's imagecodecs (PyPI), each run on the same cells and each output checked against its
//! bound here. The reference implementations through one maintained wrapper rather than
//! crates: none of the three has a Rust port.

use fractile_codec::Raster;

/// One peer's figures at one bound.
pub(crate) struct Peer {
    /// Source bytes (int16 or float32, as the raster's samples) over compressed bytes.
    pub(crate) ratio: f64,
    /// Largest |decoded - source| over the cells, as the peer decoded them.
    pub(crate) max_error: f64,
}

/// What each peer does at bound `e` on `r` (one channel): SZ3, SPERR, JPEG-LS (`None`: not
/// run: JPEG-LS on values that are not whole, or a peer that failed), and the library versions.
pub(crate) fn at_bound(r: &Raster, e: f64) -> Option<([Option<Peer>; 3], String)> {
    let dir = std::env::temp_dir().join(format!("fractile-peers-{}", std::process::id()));
    std::fs::create_dir_all(&dir).ok()?;
    let raw = dir.join("in.f32");
    let bytes: Vec<u8> = r.channels[0].iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(&raw, &bytes).ok()?;
    let source_bytes = r.width * r.height * r.sample.bytes();
    let script = format!(
        r#"
import numpy as np, imagecodecs as ic
a = np.fromfile('{raw}', dtype='<f4').reshape({h}, {w})
src = a.astype(np.float64)
e = {e}
def run(enc, dec):
    try:
        b = enc(); d = dec(b).astype(np.float64)
        print(len(b), float(np.abs(d - src).max()))
    except Exception as x:
        print('-', x)
run(lambda: ic.sz3_encode(a, mode='abs', abs=e), lambda b: ic.sz3_decode(b, a.shape, np.float32))
run(lambda: ic.sperr_encode(src, mode='pwe', level=e), lambda b: ic.sperr_decode(b, shape=a.shape, dtype=np.float64))
if np.all(a == np.round(a)) and e >= 0:
    lo = a.min(); u = (a - lo).astype(np.uint16)
    run(lambda: ic.jpegls_encode(u, level=int(np.floor(e))), lambda b: ic.jpegls_decode(b).astype(np.float64) + lo)
else:
    print('-', 'not whole numbers')
print('imagecodecs', ic.__version__, ic.sz3_version(), ic.sperr_version(), ic.jpegls_version())
"#,
        raw = raw.display(),
        h = r.height,
        w = r.width,
    );
    let out = std::process::Command::new("python3")
        .args(["-c", &script])
        .output()
        .ok()?;
    let _ = std::fs::remove_dir_all(&dir);
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    let lines: Vec<&str> = text.lines().collect();
    if lines.len() < 4 {
        return None;
    }
    let peer = |line: &str| {
        let mut it = line.split_whitespace();
        let n: f64 = it.next()?.parse().ok()?;
        let max_error: f64 = it.next()?.parse().ok()?;
        Some(Peer {
            ratio: source_bytes as f64 / n,
            max_error,
        })
    };
    Some((
        [peer(lines[0]), peer(lines[1]), peer(lines[2])],
        lines[3].to_string(),
    ))
}
