//! Slippy-map tile addresses (Web Mercator, `z/x/y` with y from the north), the vocabulary of
//! every tile URL: the one copy of these formulas, used by the codec (which tiles what), the
//! client (which tiles to ask for) and the tests.

use std::f64::consts::PI;

/// Largest Web Mercator latitude (the square world).
pub const MAX_LATITUDE: f64 = 85.051_128_779_806_59;

/// Longitude and latitude (degrees) of a point of tile (z, x, y) given as fractions (fx, fy) of
/// the tile (0..1 from the north-west corner).
pub fn tile_lonlat(z: u8, x: u32, y: u32, fx: f64, fy: f64) -> (f64, f64) {
    let n = (1u64 << z) as f64;
    let lon = (x as f64 + fx) / n * 360.0 - 180.0;
    (lon, latitude_of_row((y as f64 + fy) / n))
}

/// Latitude (degrees) of a point at `t` (0 north edge, 1 south edge) down the square world.
pub fn latitude_of_row(t: f64) -> f64 {
    (PI * (1.0 - 2.0 * t)).sinh().atan().to_degrees()
}

/// Bounds `[west, south, east, north]` (degrees) of a tile.
pub fn tile_bounds(z: u8, x: u32, y: u32) -> [f64; 4] {
    let (w, n) = tile_lonlat(z, x, y, 0.0, 0.0);
    let (e, s) = tile_lonlat(z, x, y, 1.0, 1.0);
    [w, s, e, n]
}

/// The tile (x, y) at zoom z that holds (lon, lat); latitudes past the square world clamp to it.
pub fn lonlat_tile(z: u8, lon: f64, lat: f64) -> (u32, u32) {
    let n = (1u64 << z) as f64;
    let lat = lat.clamp(-MAX_LATITUDE, MAX_LATITUDE).to_radians();
    let x = ((lon + 180.0) / 360.0 * n).floor().clamp(0.0, n - 1.0);
    let y = ((1.0 - (lat.tan() + 1.0 / lat.cos()).ln() / PI) / 2.0 * n)
        .floor()
        .clamp(0.0, n - 1.0);
    (x as u32, y as u32)
}

/// Cesium's geographic tiling (EPSG:4326, TMS rows from the south, two root tiles): degrees a
/// side of a tile of level `z`.
pub fn geographic_degrees(z: u8) -> f64 {
    180.0 / f64::from(1u32 << z)
}

/// Bounds `[west, south, east, north]` (degrees) of geographic tile (`z`, `x`, `y`).
pub fn geographic_bounds(z: u8, x: u32, y: u32) -> [f64; 4] {
    let d = geographic_degrees(z);
    let (w, s) = (-180.0 + f64::from(x) * d, -90.0 + f64::from(y) * d);
    [w, s, w + d, s + d]
}

/// Geographic tile columns and rows of level `z` that overlap `bounds` (inclusive ranges); an
/// east or north edge on a tile boundary belongs to the tile before it.
pub fn geographic_range(bounds: [f64; 4], z: u8) -> ([u32; 2], [u32; 2]) {
    let d = geographic_degrees(z);
    let [w, s, e, n] = bounds;
    let last_x = (1u32 << (z + 1)) - 1;
    let last_y = (1u32 << z) - 1;
    let col = |lon: f64| (((lon + 180.0) / d).floor().max(0.0) as u32).min(last_x);
    let row = |lat: f64| (((lat + 90.0) / d).floor().max(0.0) as u32).min(last_y);
    let tiny = d * 1e-9;
    ([col(w), col(e - tiny)], [row(s), row(n - tiny)])
}

/// A terrain layer's available tiles over `bounds`, levels 0 to `max`: both root tiles at level
/// 0 (Cesium draws nothing until both are in), then the tiles that overlap `bounds`.
pub fn geographic_available(bounds: [f64; 4], max: u8) -> Vec<Vec<crate::TileRange>> {
    (0..=max)
        .map(|z| {
            let ([start_x, end_x], [start_y, end_y]) = if z == 0 {
                ([0, 1], [0, 0])
            } else {
                geographic_range(bounds, z)
            };
            vec![crate::TileRange {
                start_x,
                start_y,
                end_x,
                end_y,
            }]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against the definition's fixed points: zoom 0 is the world, its centre (0, 0); the
    /// square world's edge is MAX_LATITUDE; a tile holds its own centre.
    #[test]
    fn tiles_hold_their_points() {
        let [w, s, e, n] = tile_bounds(0, 0, 0);
        assert_eq!((w, e), (-180.0, 180.0));
        assert!((n - MAX_LATITUDE).abs() < 1e-9 && (s + MAX_LATITUDE).abs() < 1e-9);
        assert!(latitude_of_row(0.5).abs() < 1e-12);
        for (z, x, y) in [(3u8, 2u32, 5u32), (12, 1089, 1599), (20, 271_000, 396_000)] {
            let (lon, lat) = tile_lonlat(z, x, y, 0.5, 0.5);
            assert_eq!(lonlat_tile(z, lon, lat), (x, y));
        }
        assert_eq!(lonlat_tile(2, 0.0, 89.9), (2, 0));
    }
}
