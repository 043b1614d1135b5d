//! Where tile pixels fall on an asset: Web Mercator (EPSG:3857, XYZ scheme, y down from the
//! north) tile geometry, and the mapping from longitude/latitude to an asset's unit square
//! through its georeference. Assets without a georeference are tiled over the unit square.

use std::f64::consts::PI;

use fractile_proto::Georef;

/// Largest Web Mercator latitude (the square world).
pub const MAX_LATITUDE: f64 = 85.051_128_779_806_59;

/// Longitude and latitude (degrees) of a point of tile (z, x, y) given as fractions (fx, fy) of
/// the tile (0..1 from the north-west corner).
pub fn tile_lonlat(z: u8, x: u32, y: u32, fx: f64, fy: f64) -> (f64, f64) {
    let n = (1u64 << z) as f64;
    let lon = (x as f64 + fx) / n * 360.0 - 180.0;
    let lat = (PI * (1.0 - 2.0 * (y as f64 + fy) / n))
        .sinh()
        .atan()
        .to_degrees();
    (lon, lat)
}

/// Bounds `[west, south, east, north]` (degrees) of a tile.
pub fn tile_bounds(z: u8, x: u32, y: u32) -> [f64; 4] {
    let (w, n) = tile_lonlat(z, x, y, 0.0, 0.0);
    let (e, s) = tile_lonlat(z, x, y, 1.0, 1.0);
    [w, s, e, n]
}

/// The tile (x, y) at zoom z that holds (lon, lat).
pub fn lonlat_tile(z: u8, lon: f64, lat: f64) -> (u32, u32) {
    let n = (1u64 << z) as f64;
    let lat = lat.clamp(-MAX_LATITUDE, MAX_LATITUDE).to_radians();
    let x = ((lon + 180.0) / 360.0 * n).floor().clamp(0.0, n - 1.0);
    let y = ((1.0 - (lat.tan() + 1.0 / lat.cos()).ln() / PI) / 2.0 * n)
        .floor()
        .clamp(0.0, n - 1.0);
    (x as u32, y as u32)
}

/// How an asset's unit square sits on the Earth (for geographic georeferences, EPSG:4326 or
/// none given with degree-like numbers).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    west: f64,
    north: f64,
    width_deg: f64,
    height_deg: f64,
    /// Whether the asset spans all longitudes (then u wraps around at +-180).
    global: bool,
}

impl Placement {
    /// The placement of a `width x height` grid with this georeference; `None` for projected
    /// CRSs (tiles of those need a reprojection library: not supported yet).
    pub fn of(g: &Georef, width: u32, height: u32) -> Option<Placement> {
        if g.epsg.is_some_and(|c| c != 4326) {
            return None;
        }
        let width_deg = g.pixel_size[0] * width as f64;
        let height_deg = -g.pixel_size[1] * height as f64;
        (width_deg > 0.0 && height_deg > 0.0).then_some(Placement {
            west: g.origin[0],
            north: g.origin[1],
            width_deg,
            height_deg,
            global: (width_deg - 360.0).abs() < 1e-6 * 360.0,
        })
    }

    /// `[west, south, east, north]` in degrees.
    pub fn bounds(&self) -> [f64; 4] {
        [
            self.west,
            self.north - self.height_deg,
            self.west + self.width_deg,
            self.north,
        ]
    }

    /// Unit coordinates of (lon, lat); `None` outside the asset.
    pub fn unit(&self, lon: f64, lat: f64) -> Option<[f32; 2]> {
        Some([self.unit_x(lon)?, self.unit_y(lat)?])
    }

    /// Unit x of a longitude (u depends on it alone; wrapped for global assets); `None` outside.
    pub fn unit_x(&self, lon: f64) -> Option<f32> {
        let mut u = (lon - self.west) / self.width_deg;
        if self.global {
            u = u.rem_euclid(1.0);
        }
        (0.0..=1.0).contains(&u).then_some(u as f32)
    }

    /// Unit y of a latitude (v depends on it alone); `None` outside.
    pub fn unit_y(&self, lat: f64) -> Option<f32> {
        let v = (self.north - lat) / self.height_deg;
        (0.0..=1.0).contains(&v).then_some(v as f32)
    }

    /// Degrees of longitude per unit of u, and of latitude per unit of v.
    pub fn degrees_per_unit(&self) -> [f64; 2] {
        [self.width_deg, self.height_deg]
    }
}

/// Metres per degree of longitude and of latitude at latitude `lat` (spherical Earth of the
/// WGS84 equatorial radius; good to about 0.5% for local meshes).
pub fn metres_per_degree(lat: f64) -> [f64; 2] {
    let m = 6_378_137.0 * PI / 180.0;
    [m * lat.to_radians().cos(), m]
}

/// The unit point and footprint (size of one pixel in unit coordinates) of each pixel centre of a
/// tile; `None` for pixels outside the asset. Non-georeferenced assets tile the unit square.
pub fn tile_points(
    placement: Option<&Placement>,
    z: u8,
    x: u32,
    y: u32,
    size: usize,
) -> (Vec<Option<[f32; 2]>>, [f32; 2]) {
    let g = tile_grid(placement, z, x, y, size, 0);
    (g.points(), g.footprint)
}

/// The pixel centres of a tile as a separable grid: pixel (i, j) is `(xs[i], ys[j])`, because
/// the asset's u depends on longitude alone, which depends on the column alone, and v on the
/// row alone. Decoders use the structure ([`crate::decode::grid`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TileGrid {
    /// Unit x of each column; `None` outside the asset.
    pub xs: Vec<Option<f32>>,
    /// Unit y of each row; `None` outside the asset.
    pub ys: Vec<Option<f32>>,
    /// Size of one pixel in unit coordinates (at the tile's centre: Mercator stretches
    /// latitude away from it).
    pub footprint: [f32; 2],
}

impl TileGrid {
    /// The grid's points, row-major; `None` where its column or its row is outside the asset.
    pub fn points(&self) -> Vec<Option<[f32; 2]>> {
        self.ys
            .iter()
            .flat_map(|&v| self.xs.iter().map(move |&u| Some([u?, v?])))
            .collect()
    }
}

/// The pixel centres of tile z/x/y (see [`tile_points`]) as a [`TileGrid`], on a
/// `(size + 2 margin)` square grid that extends `margin` pixels beyond the tile on every side
/// (for filters that need neighbours, such as hillshading).
pub fn tile_grid(
    placement: Option<&Placement>,
    z: u8,
    x: u32,
    y: u32,
    size: usize,
    margin: usize,
) -> TileGrid {
    // Longitude depends on the column only, latitude on the row only: 2 x size evaluations.
    let side = size + 2 * margin;
    let frac = |k: usize| (k as f64 - margin as f64 + 0.5) / size as f64;
    let (xs, ys) = match placement {
        Some(p) => (
            (0..side)
                .map(|i| p.unit_x(tile_lonlat(z, x, y, frac(i), 0.5).0))
                .collect(),
            (0..side)
                .map(|j| p.unit_y(tile_lonlat(z, x, y, 0.5, frac(j)).1))
                .collect(),
        ),
        None => {
            let n = (1u64 << z) as f64;
            let axis = |t: u32| -> Vec<Option<f32>> {
                (0..side)
                    .map(|k| Some(((t as f64 + frac(k)) / n) as f32))
                    .collect()
            };
            (axis(x), axis(y))
        }
    };
    let footprint = match placement {
        Some(p) => {
            let [w, s, e, n] = tile_bounds(z, x, y);
            let d = p.degrees_per_unit();
            [
                ((e - w) / size as f64 / d[0]) as f32,
                ((n - s) / size as f64 / d[1]) as f32,
            ]
        }
        None => {
            let f = (1.0 / ((1u64 << z) as f64 * size as f64)) as f32;
            [f, f]
        }
    };
    TileGrid { xs, ys, footprint }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_geometry_matches_the_web_mercator_definition() {
        // Zoom 0 covers the whole world; its centre is (0, 0).
        let (lon, lat) = tile_lonlat(0, 0, 0, 0.5, 0.5);
        assert!(lon.abs() < 1e-9 && lat.abs() < 1e-9);
        let [w, s, e, n] = tile_bounds(0, 0, 0);
        assert!((w + 180.0).abs() < 1e-9 && (e - 180.0).abs() < 1e-9);
        assert!((n - MAX_LATITUDE).abs() < 1e-9 && (s + MAX_LATITUDE).abs() < 1e-9);
        // Round trip through the tile index at zoom 12 (Jacksboro, Tennessee).
        let (x, y) = lonlat_tile(12, -84.2, 36.4);
        let [w, s, e, n] = tile_bounds(12, x, y);
        assert!(w <= -84.2 && -84.2 < e && s < 36.4 && 36.4 <= n);
    }

    #[test]
    fn global_assets_wrap_at_the_antimeridian() {
        let g = Georef {
            epsg: Some(4326),
            origin: [-180.0, 90.0],
            pixel_size: [1.0 / 3.0, -1.0 / 3.0],
        };
        let p = Placement::of(&g, 1080, 540).unwrap();
        let a = p.unit(179.999, 0.0).unwrap();
        let b = p.unit(-179.999, 0.0).unwrap();
        assert!(a[0] > 0.999 && b[0] < 0.001);
        assert!(p.unit(0.0, 91.0).is_none());
        assert!(
            Placement::of(
                &Georef {
                    epsg: Some(32633),
                    ..g
                },
                10,
                10
            )
            .is_none()
        );
    }
}
