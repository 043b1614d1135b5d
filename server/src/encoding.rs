//! Output encodings of decoded samples: PNG (grey, RGB, terrain-RGB, Terrarium, 16-bit grey) and
//! little-endian float32. These are file formats, not math: the formulas are MapLibre's.

use fractile_codec::render::Colormap;
use fractile_proto::{AssetKind, AssetMeta};

/// How a height tile is packed into a PNG: the API's `encoding`, from `fractile-proto`.
pub use fractile_proto::query::HeightEncoding;

/// What a tile or region answer is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TileFormat {
    /// Heights packed for a `raster-dem` source.
    Heights(HeightEncoding),
    /// A picture: images as they are; heights mapped from `(min, max)` to grey.
    Visual(Option<(f32, f32)>),
    /// Raw float32 heights, little-endian, row-major (NaN for nodata).
    F32,
}

/// Height used where there is no data: 0 clamped into the asset's range, so that a map never
/// sees a -10000 m hole or a spike (the camera would jump).
fn nodata_height(m: &AssetMeta) -> f32 {
    0.0f32.clamp(m.value_min as f32, m.value_max as f32)
}

/// `x.round() as u32` for `x >= 0` without the libm call that `round` is on baseline x86-64
/// (3% of an uncached tile's time): truncating `x + 0.5` is the same below 2^23 (where adding
/// 0.5 is exact from x = 1 up; under 1 only x = 0.5 - 2^-25 differs, a height of -9999.95 m in
/// terrain-RGB), and from 2^23 up x is already an integer.
fn round_non_negative(x: f32) -> u32 {
    if x < 8_388_608.0 {
        (x + 0.5) as u32
    } else {
        x as u32
    }
}

/// How visual PNGs of heights are drawn beyond the grey ramp.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Style {
    /// A colour ramp over the rescaled heights.
    pub colormap: Option<Colormap>,
    /// Hillshade in [0, 1] per pixel.
    pub shade: Option<Vec<f32>>,
}

/// Encodes a square tile.
pub fn encode_tile(
    m: &AssetMeta,
    channels: &[Vec<f32>],
    size: usize,
    f: TileFormat,
    style: Option<Style>,
) -> (&'static str, Vec<u8>) {
    encode_raster(m, channels, size, size, f, style)
}

/// Encodes a `w x h` raster.
pub fn encode_raster(
    m: &AssetMeta,
    channels: &[Vec<f32>],
    w: usize,
    h: usize,
    f: TileFormat,
    style: Option<Style>,
) -> (&'static str, Vec<u8>) {
    match f {
        TileFormat::F32 => (
            "application/octet-stream",
            channels[0].iter().flat_map(|v| v.to_le_bytes()).collect(),
        ),
        TileFormat::Heights(e) => encode_heights(m, &channels[0], w, h, e),
        TileFormat::Visual(rescale) => encode_visual(m, channels, w, h, rescale, style),
    }
}

/// Heights packed for a `raster-dem` source (nodata as the asset's fill height).
fn encode_heights(
    m: &AssetMeta,
    heights: &[f32],
    w: usize,
    h: usize,
    e: HeightEncoding,
) -> (&'static str, Vec<u8>) {
    let fill = nodata_height(m);
    let height = |v: f32| if v.is_finite() { v } else { fill };
    // One loop per encoding into a sized buffer (a `flat_map(..).collect()` with the
    // match inside measured 7-15% of an uncached tile's time).
    let mut px = vec![0u8; heights.len() * 3];
    let cells = px.chunks_exact_mut(3).zip(heights);
    match e {
        HeightEncoding::TerrainRgb => {
            for (p, &v) in cells {
                let x = ((height(v) + 10000.0) * 10.0).max(0.0);
                let c = round_non_negative(x).min(0xFF_FFFF);
                p.copy_from_slice(&[(c >> 16) as u8, (c >> 8) as u8, c as u8]);
            }
        }
        HeightEncoding::Terrarium => {
            for (p, &v) in cells {
                let c = (height(v) + 32768.0).clamp(0.0, 65535.996);
                // Truncation is floor for c >= 0 (and not a libm call).
                let i = c as u32;
                p.copy_from_slice(&[
                    (i >> 8) as u8,
                    (i & 0xFF) as u8,
                    ((c - i as f32) * 256.0) as u8,
                ]);
            }
        }
        HeightEncoding::Gray16 => {}
    }
    if e == HeightEncoding::Gray16 {
        let (lo, span) = (
            m.value_min as f32,
            (m.value_max - m.value_min).max(f64::MIN_POSITIVE) as f32,
        );
        let g: Vec<u16> = heights
            .iter()
            .map(|&v| {
                (((height(v) - lo) / span) * 65535.0)
                    .round()
                    .clamp(0.0, 65535.0) as u16
            })
            .collect();
        return (
            "image/png",
            png(
                w,
                h,
                image::ExtendedColorType::L16,
                // image's encoders take 16-bit samples in native byte order (PNG stores them
                // big-endian; the encoder swaps).
                &g.iter().flat_map(|v| v.to_ne_bytes()).collect::<Vec<_>>(),
            ),
        );
    }
    ("image/png", png(w, h, image::ExtendedColorType::Rgb8, &px))
}

/// A picture: grey, RGB, or heights through a colour ramp and hillshading; nodata transparent.
fn encode_visual(
    m: &AssetMeta,
    channels: &[Vec<f32>],
    w: usize,
    h: usize,
    rescale: Option<(f32, f32)>,
    style: Option<Style>,
) -> (&'static str, Vec<u8>) {
    let style = style.unwrap_or_default();
    // Nodata (and pixels outside the asset) are transparent, so a map shows what lies
    // beneath instead of black.
    let holes: Option<Vec<bool>> = channels[0]
        .iter()
        .any(|v| v.is_nan())
        .then(|| channels[0].iter().map(|v| v.is_nan()).collect());
    let q = |v: f32| -> u8 {
        let v = match rescale {
            Some((lo, hi)) if m.kind == AssetKind::HeightField => (v - lo) / (hi - lo) * 255.0,
            _ => v,
        };
        if v.is_finite() {
            v.round().clamp(0.0, 255.0) as u8
        } else {
            0
        }
    };
    if channels.len() == 3 {
        let px: Vec<u8> = (0..w * h)
            .flat_map(|i| [q(channels[0][i]), q(channels[1][i]), q(channels[2][i])])
            .collect();
        (
            "image/png",
            png_with_holes(w, h, image::ExtendedColorType::Rgb8, &px, holes.as_deref()),
        )
    } else if style.colormap.is_some() || style.shade.is_some() {
        let ramp = style.colormap.unwrap_or(Colormap::Gray);
        let px: Vec<u8> = channels[0]
            .iter()
            .enumerate()
            .flat_map(|(i, &v)| {
                let t = q(v) as f32 / 255.0;
                let c = match (style.colormap, &style.shade) {
                    // Hillshade alone: grey shading.
                    (None, Some(s)) => [255.0 * s[i]; 3],
                    // A ramp, darkened by the shading (a quarter of ambient light).
                    (_, Some(s)) => ramp.rgb(t).map(|c| c * (0.25 + 0.75 * s[i])),
                    (_, None) => ramp.rgb(t),
                };
                c.map(|v| v.round().clamp(0.0, 255.0) as u8)
            })
            .collect();
        (
            "image/png",
            png_with_holes(w, h, image::ExtendedColorType::Rgb8, &px, holes.as_deref()),
        )
    } else {
        let px: Vec<u8> = channels[0].iter().map(|&v| q(v)).collect();
        (
            "image/png",
            png_with_holes(w, h, image::ExtendedColorType::L8, &px, holes.as_deref()),
        )
    }
}

fn png(w: usize, h: usize, colour: image::ExtendedColorType, px: &[u8]) -> Vec<u8> {
    png_with_holes(w, h, colour, px, None)
}

/// A PNG, with an alpha channel added (0 where `holes` says so) when there are holes.
fn png_with_holes(
    w: usize,
    h: usize,
    colour: image::ExtendedColorType,
    px: &[u8],
    holes: Option<&[bool]>,
) -> Vec<u8> {
    use image::ExtendedColorType as C;
    if let Some(holes) = holes {
        let (n, with_alpha) = match colour {
            C::L8 => (1, C::La8),
            C::Rgb8 => (3, C::Rgba8),
            _ => return png_with_holes(w, h, colour, px, None),
        };
        let mut out = Vec::with_capacity(px.len() / n * (n + 1));
        for (p, &hole) in px.chunks_exact(n).zip(holes) {
            out.extend_from_slice(p);
            out.push(if hole { 0 } else { 255 });
        }
        return png_with_holes(w, h, with_alpha, &out, None);
    }
    use image::ImageEncoder;
    let mut out = Vec::new();
    // Fast compression: tiles are small and latency matters more than a few per cent of bytes.
    let enc = image::codecs::png::PngEncoder::new_with_quality(
        &mut out,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Adaptive,
    );
    enc.write_image(px, w as u32, h as u32, colour)
        .expect("PNG of a well-formed buffer");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode_terrain_rgb(p: [u8; 3]) -> f32 {
        -10000.0 + (p[0] as f32 * 65536.0 + p[1] as f32 * 256.0 + p[2] as f32) * 0.1
    }

    fn decode_terrarium(p: [u8; 3]) -> f32 {
        p[0] as f32 * 256.0 + p[1] as f32 + p[2] as f32 / 256.0 - 32768.0
    }

    #[test]
    fn height_encodings_invert_with_maplibre_formulas() {
        let m = AssetMeta {
            kind: AssetKind::HeightField,
            width: 2,
            height: 1,
            channels: 1,
            colour: fractile_proto::ColourModel::Grey,
            sample: fractile_proto::SampleFormat::I16,
            units: None,
            value_min: -500.0,
            value_max: 2000.0,
            nodata: None,
            georef: None,
            encoder: String::new(),
            stats: Default::default(),
        };
        for v in [-432.1f32, 0.0, 1234.56] {
            for (e, dec, tol) in [
                (
                    HeightEncoding::TerrainRgb,
                    decode_terrain_rgb as fn([u8; 3]) -> f32,
                    0.051,
                ),
                (HeightEncoding::Terrarium, decode_terrarium, 0.004),
            ] {
                let (_, bytes) = encode_raster(&m, &[vec![v]], 1, 1, TileFormat::Heights(e), None);
                let img = image::load_from_memory(&bytes).unwrap().to_rgb8();
                let p = img.get_pixel(0, 0).0;
                assert!(
                    (dec(p) - v).abs() <= tol,
                    "{e:?}: {v} -> {p:?} -> {}",
                    dec(p)
                );
            }
        }
    }
}
