//! Where the pixels of a raster (a tile, a region, a mesh's vertices) fall on an asset
//! ([`Pixels`]): unit points, their footprint, and patches where a reprojection is smooth.

use std::f64::consts::PI;

use crate::core::decode::Patch;

/// Metres per degree of longitude and of latitude at latitude `lat` (spherical Earth of the
/// WGS84 equatorial radius; good to about 0.5% for local meshes).
pub fn metres_per_degree(lat: f64) -> [f64; 2] {
    let m = 6_378_137.0 * PI / 180.0;
    [m * lat.to_radians().cos(), m]
}

/// Where the pixels of a raster (a tile, a region, a mesh's vertices) fall on an asset.
#[derive(Clone, Debug, PartialEq)]
pub struct Pixels {
    /// The unit points.
    pub sites: Sites,
    /// Size of one pixel in unit coordinates (at the raster's centre: Mercator stretches
    /// latitude away from it).
    pub footprint: [f32; 2],
}

/// The unit points of a raster's pixels, row-major.
#[derive(Clone, Debug, PartialEq)]
pub enum Sites {
    /// Pixel (i, j) at `(xs[i], ys[j])`: the asset's u depends on the column alone and v on the
    /// row alone (geographic assets, non-georeferenced ones). Decoders use the structure
    /// ([`crate::core::decode::grid`]). `None`: the column or row is outside the asset.
    Grid {
        /// Unit x of each column.
        xs: Vec<Option<f32>>,
        /// Unit y of each row.
        ys: Vec<Option<f32>>,
    },
    /// A point per pixel (projected assets); `None` outside the asset.
    List {
        /// Pixels a row.
        width: usize,
        /// The points, row-major.
        points: Vec<Option<[f32; 2]>>,
        /// Disjoint blocks of pixels whose points are bilinear patches (the same points as in
        /// `points`, in a form decoders step together); pixels in none are decoded one by one.
        patches: Vec<PatchAt>,
    },
}

/// A [`Patch`] of a raster's pixels: pixel `(col + i, row + j)` is the patch's point (i, j).
#[derive(Clone, Debug, PartialEq)]
pub struct PatchAt {
    /// The raster column of the patch's first column.
    pub col: usize,
    /// The raster row of the patch's first row.
    pub row: usize,
    /// The points.
    pub patch: Patch,
}

impl Pixels {
    /// The separable grid of columns `xs` and rows `ys`.
    pub fn grid(xs: Vec<Option<f32>>, ys: Vec<Option<f32>>, footprint: [f32; 2]) -> Pixels {
        Pixels {
            sites: Sites::Grid { xs, ys },
            footprint,
        }
    }

    /// Pixels a row.
    pub fn width(&self) -> usize {
        match &self.sites {
            Sites::Grid { xs, .. } => xs.len(),
            Sites::List { width, .. } => *width,
        }
    }

    /// How many pixels.
    pub fn len(&self) -> usize {
        match &self.sites {
            Sites::Grid { xs, ys } => xs.len() * ys.len(),
            Sites::List { points, .. } => points.len(),
        }
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether no pixel falls on the asset.
    pub fn is_outside(&self) -> bool {
        match &self.sites {
            Sites::Grid { xs, ys } => {
                xs.iter().all(Option::is_none) || ys.iter().all(Option::is_none)
            }
            Sites::List { points, .. } => points.iter().all(Option::is_none),
        }
    }

    /// The points, row-major; `None` outside the asset.
    pub fn points(&self) -> Vec<Option<[f32; 2]>> {
        match &self.sites {
            Sites::Grid { xs, ys } => ys
                .iter()
                .flat_map(|&v| xs.iter().map(move |&u| Some([u?, v?])))
                .collect(),
            Sites::List { points, .. } => points.clone(),
        }
    }
}
