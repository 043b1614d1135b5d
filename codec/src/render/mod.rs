//! Rendering decoded heights for people: colour ramps and hillshading (Horn's method, the
//! convention of GDAL's `gdaldem hillshade`).

pub(crate) mod colour;

/// A colour ramp over normalised values in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Colormap {
    /// Black to white.
    Gray,
    /// Greens to browns to white, for land.
    Terrain,
    /// Perceptually uniform blue-green-yellow.
    Viridis,
}

impl Colormap {
    /// By name: `gray`, `terrain`, `viridis`.
    pub fn parse(name: &str) -> Option<Colormap> {
        match name {
            "gray" | "grey" => Some(Colormap::Gray),
            "terrain" => Some(Colormap::Terrain),
            "viridis" => Some(Colormap::Viridis),
            _ => None,
        }
    }

    fn stops(self) -> &'static [(f32, [f32; 3])] {
        match self {
            Colormap::Gray => &[(0.0, [0.0, 0.0, 0.0]), (1.0, [255.0, 255.0, 255.0])],
            Colormap::Terrain => &[
                (0.0, [51.0, 102.0, 153.0]),
                (0.15, [0.0, 153.0, 102.0]),
                (0.35, [153.0, 204.0, 102.0]),
                (0.6, [204.0, 179.0, 102.0]),
                (0.8, [153.0, 102.0, 51.0]),
                (1.0, [255.0, 255.0, 255.0]),
            ],
            Colormap::Viridis => &[
                (0.0, [68.0, 1.0, 84.0]),
                (0.25, [59.0, 82.0, 139.0]),
                (0.5, [33.0, 145.0, 140.0]),
                (0.75, [94.0, 201.0, 98.0]),
                (1.0, [253.0, 231.0, 37.0]),
            ],
        }
    }

    /// Colour of `t` (clamped to [0, 1]; NaN is black).
    pub fn rgb(self, t: f32) -> [f32; 3] {
        along(self.stops(), t)
    }

    /// Colour of a height `v` in metres on a ramp from `lo` to `hi`: [`Self::rgb`], except that
    /// [`Colormap::Terrain`] over a range that crosses sea level puts it at 0 m, with the blues
    /// of bathymetry from `lo` (deep) to 0 and the land ramp from 0 to `hi`. Without a sea
    /// level, a global DEM's oceans (most of its range below the shore) took the ramp's greens.
    pub fn rgb_height(self, v: f32, (lo, hi): (f32, f32)) -> [f32; 3] {
        if self != Colormap::Terrain || !(lo < 0.0 && hi > 0.0) {
            return self.rgb((v - lo) / (hi - lo));
        }
        if v < 0.0 {
            along(SEA, 1.0 - v / lo)
        } else {
            along(LAND, v / hi)
        }
    }
}

/// Bathymetry, deep to shallow (ColorBrewer's blues).
const SEA: &[(f32, [f32; 3])] = &[
    (0.0, [8.0, 48.0, 107.0]),
    (0.6, [33.0, 113.0, 181.0]),
    (1.0, [158.0, 202.0, 225.0]),
];

/// Land from the shore up: the terrain ramp past its blue.
const LAND: &[(f32, [f32; 3])] = &[
    (0.0, [0.0, 153.0, 102.0]),
    (0.24, [153.0, 204.0, 102.0]),
    (0.53, [204.0, 179.0, 102.0]),
    (0.76, [153.0, 102.0, 51.0]),
    (1.0, [255.0, 255.0, 255.0]),
];

/// The colour at `t` (clamped to [0, 1]; NaN is black) along `stops`.
fn along(stops: &[(f32, [f32; 3])], t: f32) -> [f32; 3] {
    if t.is_nan() {
        return [0.0; 3];
    }
    let t = t.clamp(0.0, 1.0);
    for w in stops.windows(2) {
        let ((t0, c0), (t1, c1)) = (w[0], w[1]);
        if t <= t1 {
            let f = if t1 > t0 { (t - t0) / (t1 - t0) } else { 0.0 };
            return [0, 1, 2].map(|k| c0[k] + (c1[k] - c0[k]) * f);
        }
    }
    stops[stops.len() - 1].1
}

/// Hillshade in [0, 1] of the inner `w x h` cells of a `(w + 2) x (h + 2)` height grid (one cell
/// of margin all round, row 0 north), cell size `spacing` (x, y) in the heights' units, sun at
/// `azimuth` degrees clockwise from north and `altitude` degrees above the horizon.
pub fn hillshade(
    heights: &[f32],
    w: usize,
    h: usize,
    spacing: [f32; 2],
    azimuth: f32,
    altitude: f32,
) -> Vec<f32> {
    let stride = w + 2;
    let zenith = (90.0 - altitude).to_radians();
    let az = (360.0 - azimuth + 90.0).to_radians();
    let at = |x: usize, y: usize| {
        let v = heights[y * stride + x];
        if v.is_finite() {
            v
        } else {
            heights[(y.clamp(1, h)) * stride + x.clamp(1, w)]
        }
    };
    let mut out = Vec::with_capacity(w * h);
    for y in 1..=h {
        for x in 1..=w {
            let (a, b, c) = (at(x - 1, y - 1), at(x, y - 1), at(x + 1, y - 1));
            let (d, f) = (at(x - 1, y), at(x + 1, y));
            let (g, hh, i) = (at(x - 1, y + 1), at(x, y + 1), at(x + 1, y + 1));
            let dzdx = ((c + 2.0 * f + i) - (a + 2.0 * d + g)) / (8.0 * spacing[0]);
            let dzdy = ((g + 2.0 * hh + i) - (a + 2.0 * b + c)) / (8.0 * spacing[1]);
            let slope = (dzdx * dzdx + dzdy * dzdy).sqrt().atan();
            let aspect = dzdy.atan2(-dzdx);
            let v = zenith.cos() * slope.cos() + zenith.sin() * slope.sin() * (az - aspect).cos();
            out.push(if v.is_finite() { v.max(0.0) } else { 0.0 });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_ground_is_lit_by_the_sun_altitude_and_slopes_facing_the_sun_are_brighter() {
        let flat = vec![100.0f32; 25];
        let hs = hillshade(&flat, 3, 3, [10.0, 10.0], 315.0, 45.0);
        assert!(
            hs.iter()
                .all(|&v| (v - 45f32.to_radians().sin()).abs() < 1e-5),
            "{hs:?}"
        );
        // A plane rising to the east faces west; with the sun in the north-west it is brighter
        // than one rising to the west.
        let east: Vec<f32> = (0..25).map(|k| (k % 5) as f32 * 5.0).collect();
        let west: Vec<f32> = (0..25).map(|k| (4 - k % 5) as f32 * 5.0).collect();
        let (e, w) = (
            hillshade(&east, 3, 3, [10.0, 10.0], 315.0, 45.0)[4],
            hillshade(&west, 3, 3, [10.0, 10.0], 315.0, 45.0)[4],
        );
        assert!(e > w, "east-rising {e} vs west-rising {w}");
    }

    #[test]
    fn terrain_puts_sea_level_at_zero_metres() {
        let range = (-5000.0, 2000.0);
        let [r, g, b] = Colormap::Terrain.rgb_height(-10.0, range);
        assert!(b > r && b > g, "just under the sea is blue: {r} {g} {b}");
        let [r, g, b] = Colormap::Terrain.rgb_height(10.0, range);
        assert!(g > b && g > r, "just above it is green: {r} {g} {b}");
        let deep = Colormap::Terrain.rgb_height(-5000.0, range);
        let shallow = Colormap::Terrain.rgb_height(-100.0, range);
        assert!(deep[2] < shallow[2], "deeper is darker");
        // A land-only range keeps the plain ramp.
        assert_eq!(
            Colormap::Terrain.rgb_height(150.0, (100.0, 200.0)),
            Colormap::Terrain.rgb(0.5)
        );
    }

    #[test]
    fn colormaps_span_their_stops() {
        assert_eq!(Colormap::Gray.rgb(0.0), [0.0; 3]);
        assert_eq!(Colormap::Gray.rgb(1.0), [255.0; 3]);
        assert_eq!(Colormap::Viridis.rgb(2.0), Colormap::Viridis.rgb(1.0));
        assert!(Colormap::parse("magma").is_none());
    }
}
