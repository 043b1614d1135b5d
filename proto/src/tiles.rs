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
