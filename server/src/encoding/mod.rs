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

/// Height used where there is no data (see [`fractile_proto::heights::fill_height`]).
fn nodata_height(m: &AssetMeta) -> f32 {
    fractile_proto::heights::fill_height(m.value_min, m.value_max)
}

/// How visual PNGs of heights are drawn beyond the grey ramp.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Style {
    /// A colour ramp over the rescaled heights.
    pub colormap: Option<Colormap>,
    /// Hillshade in [0, 1] per pixel.
    pub shade: Option<Vec<f32>>,
}

// Rounding to what a tile's bound and relief allow (`precision=bound`).
mod rounding;
pub use rounding::{RELIEF_LEVELS, ROUNDING_FRACTION, Relief, Rounding, relief};

/// The deflate effort of a PNG.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Deflate {
    /// The `png` crate's fast mode: for regions, which are large, asked once and not cached.
    Fast,
    /// A zlib level, 1 to 9.
    Level(u8),
}

impl Deflate {
    /// Deflate of a tile. Tiles are cached, by the server and by CDNs, so bytes count for more
    /// than encode time, but not for any time: measured on terrain-RGB tiles
    /// (`cargo bench -p fractile --bench tile_png`, docs/benchmarks.md "Serving the projected
    /// default"):
    /// - rounded tiles: zlib level 5. Level 6 saves 5% more (5.4% on jacksboro at 2 bits a
    ///   cell over zooms 10-16, 4.6% on topobathy) for 2.1 times level 5's deflate time on
    ///   detailed tiles (3.7 against 1.8 ms), which was half an uncached tile's time once
    ///   projected tiles decode by subdivision; level 3 costs 12% more bytes than level 5;
    ///   level 9 saves 12% at 27 times the time.
    /// - full-precision tiles vary in every pixel, and level 6 saves only 2% over level 3 at
    ///   2.5 times its time, so they take level 3 (83% of the fast mode's bytes).
    pub fn for_tile(rounding: Rounding) -> Deflate {
        if rounding.shift > 0 {
            Deflate::Level(5)
        } else {
            Deflate::Level(3)
        }
    }
}

/// The file a tile is written as: a PNG at a deflate effort, or a lossless WebP (`.webp`:
/// MapLibre's `raster-dem` sources and the newer public terrain pyramids take it). Lossless
/// only: packed heights are bit fields, which a lossy code would turn into metres of error.
/// image's pure-Rust WebP encoder is fast but plain: on jacksboro's terrain-RGB tiles, zooms
/// 10-16 (`cargo bench -p fractile --bench tile_png`, 2026-12-07), 1.5% fewer bytes than PNG
/// at full precision in 0.37 of zlib 5's time, but 14% more than PNG on the rounded tiles that
/// `precision=bound` serves (30.4 against 26.6 KB), so PNG stays the default; libwebp's
/// lossless modes are what the smaller WebP tiles of the peers come from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Container {
    /// PNG.
    Png(Deflate),
    /// Lossless WebP (image's encoder, pure Rust).
    WebP,
}

impl Container {
    /// Its media type.
    pub fn media_type(self) -> &'static str {
        match self {
            Container::Png(_) => "image/png",
            Container::WebP => "image/webp",
        }
    }
}

/// Encodes a square tile, heights rounded as `rounding` says.
pub fn encode_tile(
    m: &AssetMeta,
    channels: &[Vec<f32>],
    size: usize,
    f: TileFormat,
    style: Option<Style>,
    (rounding, container): (Rounding, Container),
) -> (&'static str, Vec<u8>) {
    encode_with(
        m,
        channels,
        (size, size),
        f,
        style,
        (rounding.shift, container),
    )
}

/// Encodes a `w x h` raster (fast deflate, full precision).
pub fn encode_raster(
    m: &AssetMeta,
    channels: &[Vec<f32>],
    w: usize,
    h: usize,
    f: TileFormat,
    style: Option<Style>,
) -> (&'static str, Vec<u8>) {
    encode_with(
        m,
        channels,
        (w, h),
        f,
        style,
        (0, Container::Png(Deflate::Fast)),
    )
}

/// Encodes a `w x h` raster, heights rounded to multiples of `2^shift` units.
fn encode_with(
    m: &AssetMeta,
    channels: &[Vec<f32>],
    (w, h): (usize, usize),
    f: TileFormat,
    style: Option<Style>,
    (shift, container): (u32, Container),
) -> (&'static str, Vec<u8>) {
    let png = Png {
        w,
        h,
        container,
        rows: image::codecs::png::FilterType::Adaptive,
    };
    match f {
        TileFormat::F32 => (
            "application/octet-stream",
            channels[0].iter().flat_map(|v| v.to_le_bytes()).collect(),
        ),
        TileFormat::Heights(e) => encode_heights(m, &channels[0], png, e, shift),
        TileFormat::Visual(rescale) => encode_visual(m, channels, png, rescale, style),
    }
}

/// Heights packed for a `raster-dem` source (nodata as the asset's fill height), rounded to
/// multiples of `2^shift` units of the encoding.
fn encode_heights(
    m: &AssetMeta,
    heights: &[f32],
    png: Png,
    e: HeightEncoding,
    shift: u32,
) -> (&'static str, Vec<u8>) {
    let fill = nodata_height(m);
    let height = |v: f32| if v.is_finite() { v } else { fill };
    let px = fractile_proto::heights::pack_rgb(heights, e, fill, shift).unwrap_or_default();
    if e == HeightEncoding::Gray16 {
        // 16-bit grey is PNG's alone (WebP has 8-bit samples; `.webp` gray16 is refused where
        // the request is read): a PNG whatever was asked.
        let png = Png {
            container: match png.container {
                Container::WebP => Container::Png(Deflate::Level(3)),
                c => c,
            },
            ..png
        };
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
            png.write(
                image::ExtendedColorType::L16,
                // image's encoders take 16-bit samples in native byte order (PNG stores them
                // big-endian; the encoder swaps).
                &g.iter().flat_map(|v| v.to_ne_bytes()).collect::<Vec<_>>(),
            ),
        );
    }
    // Packed heights take the Up filter on every row rather than the adaptive choice, for
    // 5-14% less encode time at about the same bytes: against adaptive at zlib 6, from 2.9%
    // fewer (full-precision tiles) to 1.5% more (topobathy's smooth deep zooms), over 400
    // terrarium and terrain-RGB tiles of etopo20, jacksboro and topobathy (2026-11-26,
    // docs/benchmarks.md; `cargo bench -p fractile --bench tile_png` compares them).
    let png = Png {
        rows: image::codecs::png::FilterType::Up,
        ..png
    };
    (
        png.container.media_type(),
        png.write(image::ExtendedColorType::Rgb8, &px),
    )
}

/// A picture: grey, RGB, or heights through a colour ramp and hillshading; nodata transparent.
fn encode_visual(
    m: &AssetMeta,
    channels: &[Vec<f32>],
    png: Png,
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
        let px: Vec<u8> = (0..png.w * png.h)
            .flat_map(|i| [q(channels[0][i]), q(channels[1][i]), q(channels[2][i])])
            .collect();
        (
            png.container.media_type(),
            png.write_with_holes(image::ExtendedColorType::Rgb8, &px, holes.as_deref()),
        )
    } else if style.colormap.is_some() || style.shade.is_some() {
        let ramp = style.colormap.unwrap_or(Colormap::Gray);
        // Heights in metres go through the ramp as heights, so that a terrain ramp puts sea
        // level at 0 m (`Colormap::rgb_height`); anything else as a fraction of its range.
        let metres = match rescale {
            Some(r)
                if ramp == Colormap::Terrain
                    && m.kind == AssetKind::HeightField
                    && m.units.as_deref() == Some("m") =>
            {
                Some(r)
            }
            _ => None,
        };
        let colour = |v: f32| match metres {
            Some(r) if v.is_finite() => ramp.rgb_height(v, r),
            _ => ramp.rgb(q(v) as f32 / 255.0),
        };
        let px: Vec<u8> = channels[0]
            .iter()
            .enumerate()
            .flat_map(|(i, &v)| {
                let c = match (style.colormap, &style.shade) {
                    // Hillshade alone: grey shading.
                    (None, Some(s)) => [255.0 * s[i]; 3],
                    // A ramp, darkened by the shading (a quarter of ambient light).
                    (_, Some(s)) => colour(v).map(|c| c * (0.25 + 0.75 * s[i])),
                    (_, None) => colour(v),
                };
                c.map(|v| v.round().clamp(0.0, 255.0) as u8)
            })
            .collect();
        (
            png.container.media_type(),
            png.write_with_holes(image::ExtendedColorType::Rgb8, &px, holes.as_deref()),
        )
    } else {
        let px: Vec<u8> = channels[0].iter().map(|&v| q(v)).collect();
        (
            png.container.media_type(),
            png.write_with_holes(image::ExtendedColorType::L8, &px, holes.as_deref()),
        )
    }
}

/// A picture's writer: its size, its container, and a PNG's row filters.
#[derive(Clone, Copy)]
struct Png {
    w: usize,
    h: usize,
    container: Container,
    rows: image::codecs::png::FilterType,
}

impl Png {
    fn write(self, colour: image::ExtendedColorType, px: &[u8]) -> Vec<u8> {
        self.write_with_holes(colour, px, None)
    }

    /// A PNG, with an alpha channel added (0 where `holes` says so) when there are holes.
    #[expect(
        clippy::expect_used,
        reason = "a PNG of a buffer whose size matches its width, height and colour cannot fail to encode into memory"
    )]
    fn write_with_holes(
        self,
        colour: image::ExtendedColorType,
        px: &[u8],
        holes: Option<&[bool]>,
    ) -> Vec<u8> {
        use image::ExtendedColorType as C;
        if let Some(holes) = holes {
            let (n, with_alpha) = match colour {
                C::L8 => (1, C::La8),
                C::Rgb8 => (3, C::Rgba8),
                _ => return self.write(colour, px),
            };
            let mut out = Vec::with_capacity(px.len() / n * (n + 1));
            for (p, &hole) in px.chunks_exact(n).zip(holes) {
                out.extend_from_slice(p);
                out.push(if hole { 0 } else { 255 });
            }
            return self.write(with_alpha, &out);
        }
        use image::ImageEncoder;
        use image::codecs::png::{CompressionType, PngEncoder};
        let mut out = Vec::new();
        let deflate = match self.container {
            Container::Png(d) => d,
            Container::WebP => {
                // 8-bit grey, grey and alpha, RGB and RGBA, what every tile here is but a
                // 16-bit grey one (refused in WebP where the request is read).
                image::codecs::webp::WebPEncoder::new_lossless(&mut out)
                    .write_image(px, self.w as u32, self.h as u32, colour)
                    .expect("WebP of a well-formed 8-bit buffer");
                return out;
            }
        };
        let compression = match deflate {
            Deflate::Fast => CompressionType::Fast,
            Deflate::Level(l) => CompressionType::Level(l),
        };
        // Pictures: adaptive filters, each row taking the one whose residuals are smallest.
        let enc = PngEncoder::new_with_quality(&mut out, compression, self.rows);
        enc.write_image(px, self.w as u32, self.h as u32, colour)
            .expect("PNG of a well-formed buffer");
        out
    }
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
    fn rounded_heights_are_multiples_of_the_step_within_half_a_step() {
        let m = AssetMeta {
            kind: AssetKind::HeightField,
            width: 64,
            height: 1,
            channels: 1,
            colour: fractile_proto::ColourModel::Grey,
            sample: fractile_proto::SampleFormat::F32,
            units: None,
            value_min: -500.0,
            value_max: 3000.0,
            nodata: None,
            georef: None,
            encoder: String::new(),
            stats: Default::default(),
        };
        let heights: Vec<f32> = (0..64).map(|k| -431.7 + 53.29 * k as f32).collect();
        for (e, dec, step) in [
            (
                HeightEncoding::TerrainRgb,
                decode_terrain_rgb as fn([u8; 3]) -> f32,
                25.6,
            ),
            (HeightEncoding::Terrarium, decode_terrarium, 32.0),
        ] {
            let r = Rounding::for_tile(
                e,
                100.0,
                Relief {
                    span: f32::NAN,
                    gradient: f32::NAN,
                },
                f32::NAN,
            );
            let (_, bytes) = encode_tile(
                &m,
                std::slice::from_ref(&heights),
                8,
                TileFormat::Heights(e),
                None,
                (r, Container::Png(Deflate::for_tile(r))),
            );
            let img = image::load_from_memory(&bytes).unwrap().to_rgb8();
            let origin = if e == HeightEncoding::TerrainRgb {
                -10000.0
            } else {
                -32768.0
            };
            for (k, p) in img.pixels().enumerate() {
                let got = dec(p.0);
                let steps = (got - origin) / step;
                assert!((steps - steps.round()).abs() < 1e-3, "{e:?}: {got}");
                assert!(
                    (got - heights[k]).abs() <= step / 2.0 + 1e-3,
                    "{e:?}: {got}"
                );
            }
        }
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
