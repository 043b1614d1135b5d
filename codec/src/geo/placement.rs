//! How a georeferenced asset's unit square sits on the Earth ([`Placement`]): its CRS
//! (proj4rs for projected ones), longitude/latitude to unit points and back, reprojected
//! patches of points by an interpolated lattice.

use std::sync::Arc;

use fractile_proto::Georef;
use fractile_proto::tiles::{MAX_LATITUDE, tile_bounds, tile_lonlat};
use proj4rs::proj::Proj;

use crate::core::decode::Patch;
use crate::geo::pixels::{PatchAt, Pixels, Sites};

/// How an asset's unit square sits on the Earth: its grid's frame in its own CRS, and that CRS.
/// Requests speak longitude/latitude (WGS84 degrees) whatever the asset's CRS.
#[derive(Clone, Debug)]
pub struct Placement {
    /// West edge, in CRS units (degrees or metres).
    pub(super) west: f64,
    /// North edge, in CRS units.
    pub(super) north: f64,
    /// Width of the grid in CRS units.
    pub(super) width: f64,
    /// Height of the grid in CRS units.
    pub(super) height: f64,
    pub(super) crs: Crs,
    /// `[west, south, east, north]` in degrees: the frame itself for geographic assets, the
    /// smallest lon/lat box around the projected frame otherwise.
    pub(super) bounds: [f64; 4],
}

/// The CRS of an asset's grid.
#[derive(Clone, Debug)]
pub(super) enum Crs {
    /// Longitude/latitude degrees (EPSG:4326, or no code with degree-like numbers): u depends
    /// on longitude alone and v on latitude alone. `global`: the asset spans all longitudes
    /// (then u wraps around at +-180).
    Geographic { global: bool },
    /// A projected CRS: a point goes through the projection before it reaches the grid.
    Projected(Arc<Projection>),
}

/// The two ends of a reprojection (proj4rs: pure Rust, the PROJ.4 pipeline through WGS84).
#[derive(Debug)]
pub(super) struct Projection {
    epsg: u32,
    crs: Proj,
    wgs84: Proj,
}

impl Projection {
    /// The CRS coordinates of (lon, lat) degrees; `None` where the projection fails.
    pub(super) fn forward(&self, lon: f64, lat: f64) -> Option<[f64; 2]> {
        let mut p = (lon.to_radians(), lat.to_radians(), 0.0);
        proj4rs::transform::transform(&self.wgs84, &self.crs, &mut p).ok()?;
        (p.0.is_finite() && p.1.is_finite()).then_some([p.0, p.1])
    }

    /// The (lon, lat) degrees of CRS coordinates; `None` where the projection fails.
    pub(super) fn inverse(&self, x: f64, y: f64) -> Option<[f64; 2]> {
        let mut p = (x, y, 0.0);
        proj4rs::transform::transform(&self.crs, &self.wgs84, &mut p).ok()?;
        let (lon, lat) = (p.0.to_degrees(), p.1.to_degrees());
        (lon.is_finite() && lat.is_finite()).then_some([lon, lat])
    }
}

/// Why an asset's georeference can't be placed on the Earth (it is then tiled over the unit
/// square).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlacementError {
    /// Pixel sizes of the wrong sign (only north-up grids are placed).
    #[error("the grid is not north-up (pixel size {0:?})")]
    NotNorthUp([f64; 2]),
    /// An EPSG code the CRS definitions don't hold.
    #[error("EPSG:{0} is not a CRS we know")]
    UnknownCrs(u32),
    /// The projection fails on the asset's own frame.
    #[error("EPSG:{0} does not project the asset's frame")]
    OutsideCrs(u32),
    /// A lon/lat frame past the poles or wider than the globe (by more than a cell): its
    /// georeference or its size is wrong.
    #[error("a lon/lat frame of {0:?} (west, south, east, north) is not on the globe")]
    OffTheGlobe([f64; 4]),
}

/// Whether EPSG `code` is a geographic (lon/lat) CRS, as the CRS definitions say; `None` for a
/// code they do not hold. (EPSG codes 4000-4999 are mostly geographic but not all: 4087, World
/// Equidistant Cylindrical, is projected.)
pub fn epsg_is_geographic(code: u32) -> Option<bool> {
    crs_of(code).map(|p| p.is_latlong())
}

/// The CRS of EPSG `code`: from the registry's definitions (feature `epsg`, the default), else
/// from [`common_crs`].
fn crs_of(code: u32) -> Option<Proj> {
    #[cfg(feature = "epsg")]
    return u16::try_from(code)
        .ok()
        .and_then(|c| Proj::from_epsg_code(c).ok());
    #[cfg(not(feature = "epsg"))]
    return Proj::from_proj_string(&common_crs(code)?).ok();
}

/// The PROJ.4 definition of the CRSs that nearly all DEMs come in, as the EPSG registry's
/// definitions word them: WGS84 and NAD83 lon/lat, ETRS89, Web Mercator, UTM on WGS84 (north
/// and south), on NAD83 and on ETRS89. What a build without the registry (the browser's, where
/// it would be half of the module) places; a test checks each against the registry.
pub fn common_crs(code: u32) -> Option<String> {
    Some(match code {
        4326 => "+proj=longlat +datum=WGS84 +no_defs".into(),
        4269 => "+proj=longlat +datum=NAD83 +no_defs".into(),
        4258 => "+proj=longlat +ellps=GRS80 +towgs84=0,0,0,0,0,0,0 +no_defs".into(),
        3857 => "+proj=merc +a=6378137 +b=6378137 +lat_ts=0.0 +lon_0=0.0 +x_0=0.0 +y_0=0 \
                 +k=1.0 +units=m +nadgrids=@null +wktext +no_defs"
            .into(),
        32601..=32660 => format!(
            "+proj=utm +zone={} +datum=WGS84 +units=m +no_defs",
            code - 32600
        ),
        32701..=32760 => format!(
            "+proj=utm +zone={} +south +datum=WGS84 +units=m +no_defs",
            code - 32700
        ),
        26901..=26923 => format!(
            "+proj=utm +zone={} +datum=NAD83 +units=m +no_defs",
            code - 26900
        ),
        25828..=25838 => format!(
            "+proj=utm +zone={} +ellps=GRS80 +towgs84=0,0,0,0,0,0,0 +units=m +no_defs",
            code - 25800
        ),
        _ => return None,
    })
}

/// Samples along each edge of a projected frame when bounding it in lon/lat (projected edges
/// bend: a UTM zone's edges curve by metres over a degree).
const EDGE_SAMPLES: usize = 64;

impl Placement {
    /// The placement of a `width x height` grid with this georeference: geographic for
    /// EPSG:4326 or no code (degree-like numbers), projected for any other EPSG code that the
    /// CRS definitions (crs-definitions, from the EPSG registry) hold. Geographic CRSs on other
    /// datums (NAD83, ETRS89) are taken as WGS84: they differ by about a metre, under a cell of
    /// any DEM we serve.
    pub fn of(g: &Georef, width: u32, height: u32) -> Result<Placement, PlacementError> {
        let w = g.pixel_size[0] * width as f64;
        let h = -g.pixel_size[1] * height as f64;
        if !(w > 0.0 && h > 0.0) {
            return Err(PlacementError::NotNorthUp(g.pixel_size));
        }
        let [west, north] = g.origin;
        let geographic = |global| {
            let bounds = [west, north - h, west + w, north];
            // A cell of slack: grids whose cells are centred on the poles or the antimeridian.
            let (cx, cy) = (g.pixel_size[0], -g.pixel_size[1]);
            let on_globe = bounds[1] >= -90.0 - cy
                && bounds[3] <= 90.0 + cy
                && w <= 360.0 + cx
                && bounds[0] >= -540.0
                && bounds[2] <= 540.0;
            if !on_globe {
                return Err(PlacementError::OffTheGlobe(bounds));
            }
            Ok(Placement {
                west,
                north,
                width: w,
                height: h,
                crs: Crs::Geographic { global },
                bounds,
            })
        };
        let code = match g.epsg {
            None | Some(4326) => return geographic((w - 360.0).abs() < 1e-6 * 360.0),
            Some(c) => c,
        };
        let crs = crs_of(code).ok_or(PlacementError::UnknownCrs(code))?;
        if crs.is_latlong() {
            return geographic((w - 360.0).abs() < 1e-6 * 360.0);
        }
        let wgs84 = crs_of(4326).expect("EPSG:4326 is in every CRS table");
        let projection = Projection {
            epsg: code,
            crs,
            wgs84,
        };
        // The lon/lat box of the frame: its edges, sampled.
        let mut bounds = [f64::INFINITY, f64::INFINITY, -f64::INFINITY, -f64::INFINITY];
        for k in 0..=EDGE_SAMPLES {
            let t = k as f64 / EDGE_SAMPLES as f64;
            for [fx, fy] in [[t, 0.0], [t, 1.0], [0.0, t], [1.0, t]] {
                let [lon, lat] = projection
                    .inverse(west + fx * w, north - fy * h)
                    .ok_or(PlacementError::OutsideCrs(code))?;
                bounds = [
                    bounds[0].min(lon),
                    bounds[1].min(lat),
                    bounds[2].max(lon),
                    bounds[3].max(lat),
                ];
            }
        }
        Ok(Placement {
            west,
            north,
            width: w,
            height: h,
            crs: Crs::Projected(Arc::new(projection)),
            bounds,
        })
    }

    /// The EPSG code of a projected placement (`None`: geographic).
    pub fn epsg(&self) -> Option<u32> {
        match &self.crs {
            Crs::Geographic { .. } => None,
            Crs::Projected(p) => Some(p.epsg),
        }
    }

    /// `[west, south, east, north]` in degrees (for projected assets, the smallest lon/lat box
    /// around the grid).
    pub fn bounds(&self) -> [f64; 4] {
        self.bounds
    }

    /// Whether the grid is in longitude/latitude degrees.
    pub fn is_geographic(&self) -> bool {
        matches!(self.crs, Crs::Geographic { .. })
    }

    /// Unit coordinates of (lon, lat); `None` outside the asset.
    pub fn unit(&self, lon: f64, lat: f64) -> Option<[f32; 2]> {
        let [u, v] = self.unit_f64(lon, lat)?;
        ((0.0..=1.0).contains(&u) && (0.0..=1.0).contains(&v)).then_some([u as f32, v as f32])
    }

    /// Unit coordinates of (lon, lat), not clipped to the unit square; `None` far outside the
    /// asset (outside its lon/lat box, where a projection may fold distant points onto it) or
    /// where the projection fails.
    pub(crate) fn unit_f64(&self, lon: f64, lat: f64) -> Option<[f64; 2]> {
        match &self.crs {
            Crs::Geographic { global } => {
                let mut u = (lon - self.west) / self.width;
                if *global {
                    u = u.rem_euclid(1.0);
                }
                Some([u, (self.north - lat) / self.height])
            }
            Crs::Projected(p) => {
                let [w, s, e, n] = self.bounds;
                // A margin of a tenth of the box keeps points just outside the grid (pixels
                // that graze it) while turning away the far side of the world.
                let (mx, my) = (0.1 * (e - w), 0.1 * (n - s));
                if lon < w - mx || lon > e + mx || lat < s - my || lat > n + my {
                    return None;
                }
                let [x, y] = p.forward(lon, lat)?;
                Some([(x - self.west) / self.width, (self.north - y) / self.height])
            }
        }
    }

    /// Size in unit coordinates of a pixel `dlon x dlat` degrees centred at (lon, lat): for
    /// projected assets the extent along u and along v of the pixel's image (the projection
    /// rotates it by the meridian convergence), from a finite difference.
    pub fn footprint(&self, lon: f64, lat: f64, dlon: f64, dlat: f64) -> [f32; 2] {
        match &self.crs {
            Crs::Geographic { .. } => [(dlon / self.width) as f32, (dlat / self.height) as f32],
            Crs::Projected(p) => {
                let at = |x: f64, y: f64| p.forward(x, y);
                let (c, e, n) = (
                    at(lon, lat),
                    at(lon + 0.5 * dlon, lat),
                    at(lon, lat + 0.5 * dlat),
                );
                let (Some(c), Some(e), Some(n)) = (c, e, n) else {
                    return [0.0, 0.0];
                };
                let (ex, ey) = (2.0 * (e[0] - c[0]).abs(), 2.0 * (e[1] - c[1]).abs());
                let (nx, ny) = (2.0 * (n[0] - c[0]).abs(), 2.0 * (n[1] - c[1]).abs());
                [
                    ((ex + nx) / self.width) as f32,
                    ((ey + ny) / self.height) as f32,
                ]
            }
        }
    }

    /// The pixels of a raster whose column i lies at longitude `lons[i]` and row j at latitude
    /// `lats[j]` (a tile, or a north-up lon/lat box), each `footprint` wide (unit coordinates).
    /// Geographic assets give a separable grid; projected ones a point per pixel.
    pub fn pixels(&self, lons: &[f64], lats: &[f64], footprint: [f32; 2]) -> Pixels {
        let sites = match &self.crs {
            Crs::Geographic { .. } => Sites::Grid {
                xs: lons.iter().map(|&lon| self.unit_x(lon)).collect(),
                ys: lats.iter().map(|&lat| self.unit_y(lat)).collect(),
            },
            Crs::Projected(_) => {
                let (points, patches) = self.projected_points(lons, lats, footprint);
                Sites::List {
                    width: lons.len(),
                    points,
                    patches,
                }
            }
        };
        Pixels { sites, footprint }
    }

    /// Unit x of a longitude (geographic assets: u depends on it alone); `None` outside.
    fn unit_x(&self, lon: f64) -> Option<f32> {
        let [u, _] = self.unit_f64(lon, self.north)?;
        (0.0..=1.0).contains(&u).then_some(u as f32)
    }

    /// Unit y of a latitude (geographic assets: v depends on it alone); `None` outside.
    fn unit_y(&self, lat: f64) -> Option<f32> {
        let v = (self.north - lat) / self.height;
        (0.0..=1.0).contains(&v).then_some(v as f32)
    }

    /// Unit points of the pixels `(lons[i], lats[j])` of a projected asset. Projecting every
    /// pixel costs about 0.3 us each (22 ms for a 256 x 256 tile, several times its decoding),
    /// so, as GDAL's warper does, only the corners of blocks of pixels are projected and the
    /// pixels between are interpolated bilinearly: a block starts as the whole raster and splits
    /// in four while the interpolation misses its centre or an edge midpoint by more than half
    /// of [`LATTICE_TOLERANCE`] (strong curvature: low zooms, far from the projection's centre),
    /// down to [`LATTICE`] pixels a side, below which a block that still misses, or that has a
    /// corner off the projection, is projected pixel by pixel. Each interpolated block is also
    /// returned as a [`Patch`], the form decoders step together.
    fn projected_points(
        &self,
        lons: &[f64],
        lats: &[f64],
        footprint: [f32; 2],
    ) -> (Vec<Option<[f32; 2]>>, Vec<PatchAt>) {
        let (w, h) = (lons.len(), lats.len());
        let mut out = vec![None; w * h];
        let mut patches = Vec::new();
        if w == 0 || h == 0 {
            return (out, patches);
        }
        let inside = |p: [f64; 2]| {
            ((0.0..=1.0).contains(&p[0]) && (0.0..=1.0).contains(&p[1]))
                .then_some([p[0] as f32, p[1] as f32])
        };
        let exact = |i: usize, j: usize| self.unit_f64(lons[i], lats[j]);
        let tol = [
            0.5 * LATTICE_TOLERANCE * footprint[0].max(f32::MIN_POSITIVE) as f64,
            0.5 * LATTICE_TOLERANCE * footprint[1].max(f32::MIN_POSITIVE) as f64,
        ];
        // Blocks of pixels [i0, i1) x [j0, j1), corners at the first and last pixels.
        let mut todo = vec![([0, w], [0, h])];
        while let Some(([i0, i1], [j0, j1])) = todo.pop() {
            let (il, jl) = (i1 - 1, j1 - 1);
            let patch = match [exact(i0, j0), exact(il, j0), exact(i0, jl), exact(il, jl)] {
                [Some(c0), Some(c1), Some(c2), Some(c3)] => {
                    let (sx, sy) = ((il - i0).max(1) as f64, (jl - j0).max(1) as f64);
                    let patch = Patch {
                        origin: c0,
                        a: [0, 1].map(|k| (c1[k] - c0[k]) / sx),
                        b: [0, 1].map(|k| (c2[k] - c0[k]) / sy),
                        c: [0, 1].map(|k| (c3[k] - c1[k] - c2[k] + c0[k]) / (sx * sy)),
                        width: i1 - i0,
                        height: j1 - j0,
                    };
                    let (mi, mj) = ((i0 + il) / 2, (j0 + jl) / 2);
                    // The centre and the middle of each edge, where a bilinear patch strays
                    // furthest from a smooth map; half the tolerance there leaves room for the
                    // points between.
                    let fits = [(mi, mj), (mi, j0), (mi, jl), (i0, mj), (il, mj)]
                        .into_iter()
                        .all(|(i, j)| {
                            exact(i, j).is_some_and(|e| {
                                let l = patch.at(i - i0, j - j0);
                                (l[0] - e[0]).abs() <= tol[0] && (l[1] - e[1]).abs() <= tol[1]
                            })
                        });
                    fits.then_some(patch)
                }
                _ => None,
            };
            match patch {
                Some(patch) => {
                    for j in j0..j1 {
                        for (i, p) in out[j * w + i0..j * w + i1].iter_mut().enumerate() {
                            *p = inside(patch.at(i, j - j0));
                        }
                    }
                    patches.push(PatchAt {
                        col: i0,
                        row: j0,
                        patch,
                    });
                }
                None if i1 - i0 > LATTICE || j1 - j0 > LATTICE => {
                    let (mi, mj) = ((i0 + i1) / 2, (j0 + j1) / 2);
                    for (ci, cj) in [
                        ([i0, mi], [j0, mj]),
                        ([mi, i1], [j0, mj]),
                        ([i0, mi], [mj, j1]),
                        ([mi, i1], [mj, j1]),
                    ] {
                        if ci[0] < ci[1] && cj[0] < cj[1] {
                            todo.push((ci, cj));
                        }
                    }
                }
                None => {
                    for j in j0..j1 {
                        for i in i0..i1 {
                            out[j * w + i] = exact(i, j).and_then(inside);
                        }
                    }
                }
            }
        }
        (out, patches)
    }
}

/// Smallest block side (pixels) of the interpolated reprojection (see
/// `Placement::projected_points`).
const LATTICE: usize = 16;

/// Largest interpolation error allowed in a lattice cell, in pixels (GDAL's default error
/// threshold for approximate warping is 0.125 pixel).
const LATTICE_TOLERANCE: f64 = 0.125;

/// The unit point and footprint (size of one pixel in unit coordinates) of each pixel centre of a
/// tile, row-major; `None` for pixels outside the asset. Non-georeferenced assets tile the unit
/// square.
pub fn tile_points(
    placement: Option<&Placement>,
    z: u8,
    x: u32,
    y: u32,
    size: usize,
) -> (Vec<Option<[f32; 2]>>, [f32; 2]) {
    let g = tile_pixels(placement, z, x, y, size, 0);
    (g.points(), g.footprint)
}

/// Zoom at which a tile pixel of `tile_size` is about the size of a source cell of an asset
/// `width` cells wide placed by `placement` (the unit square spans the globe without one).
/// Deeper zooms decode detail the source never had: the point of a fractal codec, so a map's
/// `maxzoom` may go a few levels further (the server's TileJSON says 4).
pub fn native_zoom(placement: Option<&Placement>, width: u32, tile_size: usize) -> u8 {
    let degrees = placement.map_or(360.0, |p| p.bounds()[2] - p.bounds()[0]);
    let pixels_world = f64::from(width) * 360.0 / degrees;
    (pixels_world / tile_size as f64)
        .log2()
        .ceil()
        .clamp(0.0, 22.0) as u8
}

/// An asset's lon/lat bounds `[west, south, east, north]` as a map source states them:
/// clamped to Web Mercator's world, the whole world without a placement.
pub fn map_bounds(placement: Option<&Placement>) -> [f64; 4] {
    let [w, s, e, n] = placement.map_or([-180.0, -90.0, 180.0, 90.0], Placement::bounds);
    [
        w.max(-180.0),
        s.max(-MAX_LATITUDE),
        e.min(180.0),
        n.min(MAX_LATITUDE),
    ]
}

/// The pixel centres of tile z/x/y (see [`tile_points`]), on a `(size + 2 margin)` square
/// raster that extends `margin` pixels beyond the tile on every side (for filters that need
/// neighbours, such as hillshading).
pub fn tile_pixels(
    placement: Option<&Placement>,
    z: u8,
    x: u32,
    y: u32,
    size: usize,
    margin: usize,
) -> Pixels {
    // Longitude depends on the column only, latitude on the row only: 2 x size evaluations.
    let side = size + 2 * margin;
    let frac = |k: usize| (k as f64 - margin as f64 + 0.5) / size as f64;
    match placement {
        Some(p) => {
            let lons: Vec<f64> = (0..side)
                .map(|i| tile_lonlat(z, x, y, frac(i), 0.5).0)
                .collect();
            let lats: Vec<f64> = (0..side)
                .map(|j| tile_lonlat(z, x, y, 0.5, frac(j)).1)
                .collect();
            let [w, s, e, n] = tile_bounds(z, x, y);
            let (lon, lat) = tile_lonlat(z, x, y, 0.5, 0.5);
            let footprint = p.footprint(lon, lat, (e - w) / size as f64, (n - s) / size as f64);
            p.pixels(&lons, &lats, footprint)
        }
        None => {
            let n = (1u64 << z) as f64;
            let axis = |t: u32| -> Vec<Option<f32>> {
                (0..side)
                    .map(|k| Some(((t as f64 + frac(k)) / n) as f32))
                    .collect()
            };
            let f = (1.0 / (n * size as f64)) as f32;
            Pixels::grid(axis(x), axis(y), [f, f])
        }
    }
}
