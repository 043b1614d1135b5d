//! View-dependent refinement (the seeds' "guided decompression"): for a camera over a region,
//! choose per tile the zoom and the iteration count from its distance, and fetch the nearest
//! tiles first.
//!
//! One rule decides both. At distance `d` one screen pixel spans `d * 2 tan(fov / 2) / pixels`
//! metres (times the allowed screen-space error in pixels): a tile is fine enough once its own
//! pixels are no larger, and a height is good enough once its error bound is no larger, since a
//! vertical error smaller than a pixel's footprint is invisible from there. The steps follow
//! from the asset's a-priori bound `seed_bound * max_contrast^n`; the server is also sent the
//! tolerance, so each point stops as soon as its own (usually much smaller) bound meets it.

use std::collections::BinaryHeap;

use crate::tile::TileAddress;
use crate::{AssetSummary, ClientError};

/// Equatorial circumference of the Web Mercator sphere, metres.
const EARTH_CIRCUMFERENCE: f64 = 40_075_016.686;
/// Metres per degree of latitude (mean).
const METRES_PER_DEGREE: f64 = 111_320.0;

/// Where the viewer is and what it resolves.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Longitude, degrees.
    pub lon: f64,
    /// Latitude, degrees.
    pub lat: f64,
    /// Height above sea level, metres.
    pub height: f64,
    /// Vertical field of view, degrees.
    pub fov: f64,
    /// Viewport height, pixels.
    pub viewport: f64,
    /// Allowed screen-space error, pixels.
    pub pixel_error: f64,
}

impl Camera {
    /// A camera with a 60 degree field of view over 1080 pixels, 1 pixel of error.
    pub fn new(lon: f64, lat: f64, height: f64) -> Camera {
        Camera {
            lon,
            lat,
            height,
            fov: 60.0,
            viewport: 1080.0,
            pixel_error: 1.0,
        }
    }

    /// Metres one allowed screen error spans at distance `d`.
    pub fn resolvable(&self, d: f64) -> f64 {
        d * 2.0 * (self.fov.to_radians() / 2.0).tan() / self.viewport * self.pixel_error
    }

    /// Distance in metres to the nearest point of a box `[w, s, e, n]` whose ground lies at
    /// `ground` metres (the tangent-plane approximation, good over the few tens of kilometres
    /// where the choice matters).
    pub fn distance_to(&self, [w, s, e, n]: [f64; 4], ground: f64) -> f64 {
        let lon = self.lon.clamp(w, e);
        let lat = self.lat.clamp(s, n);
        let dx = (lon - self.lon) * METRES_PER_DEGREE * self.lat.to_radians().cos();
        let dy = (lat - self.lat) * METRES_PER_DEGREE;
        let dz = (self.height - ground).max(1.0);
        (dx * dx + dy * dy + dz * dz).sqrt()
    }
}

/// One tile of a plan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlannedTile {
    /// Which tile.
    pub address: TileAddress,
    /// Distance from the camera to its nearest point, metres.
    pub distance: f64,
    /// Height error that is invisible from there (value units).
    pub tolerance: f32,
    /// Steps after which the a-priori bound is under the tolerance everywhere (capped).
    pub iterations: u32,
}

/// Limits of a plan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanLimits {
    /// Shallowest zoom.
    pub min_zoom: u8,
    /// Deepest zoom (the TileJSON's `maxzoom`).
    pub max_zoom: u8,
    /// Most steps a request may ask for (the server's limit).
    pub max_iterations: u32,
    /// Most tiles in a plan; the farthest are coarsened first when over.
    pub max_tiles: usize,
}

impl Default for PlanLimits {
    fn default() -> Self {
        PlanLimits {
            min_zoom: 0,
            max_zoom: 18,
            max_iterations: 64,
            max_tiles: 1024,
        }
    }
}

/// A tile waiting in the descent, ordered by how much it needs splitting.
struct Open {
    need: f64,
    t: TileAddress,
    d: f64,
}

impl PartialEq for Open {
    fn eq(&self, other: &Self) -> bool {
        self.need.total_cmp(&other.need).is_eq()
    }
}
impl Eq for Open {}
impl PartialOrd for Open {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Open {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.need.total_cmp(&other.need)
    }
}

fn intersects(a: [f64; 4], b: [f64; 4]) -> bool {
    a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3]
}

/// The tiles that cover `region` (`[w, s, e, n]`, degrees) for `camera`, nearest first: a
/// quadtree descent that splits a tile while its pixels are coarser than what the camera
/// resolves at its nearest point.
pub fn plan(
    camera: &Camera,
    region: [f64; 4],
    asset: &AssetSummary,
    limits: PlanLimits,
) -> Result<Vec<PlannedTile>, ClientError> {
    if !asset.georeferenced {
        return Err(ClientError::malformed(
            "view",
            format!(
                "asset {} is not georeferenced: tiles have no place",
                asset.id
            ),
        ));
    }
    let [w, s, e, n] = region;
    if !(w < e && s < n) || [w, s, e, n].iter().any(|v| !v.is_finite()) {
        return Err(ClientError::malformed(
            "region",
            "must be west,south,east,north with east > west and north > south",
        ));
    }
    // The highest ground is the nearest the camera can be to the terrain.
    let ground = asset.value_range[1];
    let pixel_metres = |t: TileAddress| {
        let [_, s, _, n] = t.bounds();
        let lat = if s <= 0.0 && n >= 0.0 {
            0.0
        } else {
            s.abs().min(n.abs())
        };
        EARTH_CIRCUMFERENCE * lat.to_radians().cos() / (256.0 * (1u64 << t.z) as f64)
    };
    // How much coarser a tile's pixels are than what the camera resolves there (> 1: split).
    let need = |t: TileAddress| {
        let d = camera.distance_to(t.bounds(), ground);
        (pixel_metres(t) / camera.resolvable(d), d)
    };
    // Start from the tiles of min_zoom that meet the region, then always split the tile that
    // needs it most, so a tile budget runs out on the far tiles, never on the one under the
    // camera (a depth-first descent would spend it on whichever corner it visits first).
    let z0 = limits.min_zoom;
    let (a, b) = (
        TileAddress::containing(z0, w, n),
        TileAddress::containing(z0, e, s),
    );
    let mut open: BinaryHeap<Open> = (a.y..=b.y)
        .flat_map(|y| (a.x..=b.x).map(move |x| TileAddress { z: z0, x, y }))
        .map(|t| {
            let (need, d) = need(t);
            Open { need, t, d }
        })
        .collect();
    let mut leaves = Vec::new();
    while let Some(o) = open.pop() {
        let children: Vec<TileAddress> =
            o.t.children()
                .into_iter()
                .filter(|c| intersects(c.bounds(), region))
                .collect();
        let over = leaves.len() + open.len() + children.len() > limits.max_tiles;
        if o.need <= 1.0 || o.t.z >= limits.max_zoom || over {
            leaves.push((o.t, o.d));
            if over {
                // Every tile left needs splitting less than this one did: all are leaves.
                leaves.extend(open.drain().map(|o| (o.t, o.d)));
            }
        } else {
            open.extend(children.into_iter().map(|t| {
                let (need, d) = need(t);
                Open { need, t, d }
            }));
        }
    }
    let mut out: Vec<PlannedTile> = leaves
        .into_iter()
        .map(|(t, d)| {
            let tolerance = camera.resolvable(d) as f32;
            let iterations = asset
                .iterations_for(tolerance)
                .unwrap_or(limits.max_iterations)
                .clamp(1, limits.max_iterations);
            PlannedTile {
                address: t,
                distance: d,
                tolerance,
                iterations,
            }
        })
        .collect();
    out.sort_by(|a, b| a.distance.total_cmp(&b.distance));
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use fractile_proto::{AssetKind, ColourModel};

    fn dem() -> AssetSummary {
        AssetSummary {
            id: "dem".into(),
            kind: AssetKind::HeightField,
            width: 1200,
            height: 1200,
            channels: 1,
            colour: ColourModel::Grey,
            bounds: Some([-98.0, 33.0, -97.0, 34.0]),
            georeferenced: true,
            epsg: None,
            value_range: [200.0, 400.0],
            units: Some("m".into()),
            nodata: None,
            codec: "quadtree-pifs".into(),
            bytes: 1,
            ratio: 1.0,
            transforms: 1,
            encode_psnr: 40.0,
            encode_rmse: 1.0,
            max_contrast: 0.5,
            seed_bound: 100.0,
            tilejson: None,
        }
    }

    #[test]
    fn near_tiles_are_deeper_finer_and_first() {
        let cam = Camera::new(-97.9, 33.1, 1400.0);
        let region = [-98.0, 33.0, -97.0, 34.0];
        let p = plan(&cam, region, &dem(), PlanLimits::default()).unwrap();
        assert!(p.len() > 4 && p.len() <= 1024);
        // Nearest first; zoom never grows and tolerance never shrinks with distance.
        for w in p.windows(2) {
            assert!(w[0].distance <= w[1].distance);
        }
        let (near, far) = (p.first().unwrap(), p.last().unwrap());
        assert!(near.address.z > far.address.z, "{near:?} {far:?}");
        assert!(near.tolerance < far.tolerance && near.iterations > far.iterations);
        // The steps meet the tolerance by the a-priori bound 100 * 0.5^n.
        for t in &p {
            assert!(100.0 * 0.5f32.powi(t.iterations as i32) <= t.tolerance || t.iterations == 1);
        }
        // The tiles cover the region: their area over the region is at least the region's.
        let area: f64 = p
            .iter()
            .map(|t| {
                let [w, s, e, n] = t.address.bounds();
                (e.min(region[2]) - w.max(region[0])).max(0.0)
                    * (n.min(region[3]) - s.max(region[1])).max(0.0)
            })
            .sum();
        assert!(
            (area - 1.0).abs() < 1e-6,
            "covered {area} square degrees of 1"
        );
    }

    #[test]
    fn a_tight_budget_coarsens_the_far_tiles_first() {
        let cam = Camera::new(-97.9, 33.1, 1400.0);
        let region = [-98.0, 33.0, -97.0, 34.0];
        let limits = PlanLimits {
            max_tiles: 16,
            ..Default::default()
        };
        let p = plan(&cam, region, &dem(), limits).unwrap();
        assert!(p.len() <= 16);
        let near = p.first().unwrap();
        assert!(p.iter().all(|t| t.address.z <= near.address.z), "{p:?}");
        assert!(near.address.z > p.last().unwrap().address.z);
        // The budget is spent: one more split of the nearest tile would overflow it.
        assert!(p.len() + 3 > 16);
    }

    #[test]
    fn images_without_a_place_are_refused() {
        let mut a = dem();
        a.georeferenced = false;
        let cam = Camera::new(0.0, 0.0, 100.0);
        assert!(plan(&cam, [0.0, 0.0, 1.0, 1.0], &a, PlanLimits::default()).is_err());
        assert!(plan(&cam, [1.0, 0.0, 0.0, 1.0], &dem(), PlanLimits::default()).is_err());
    }
}
