//! A volume asset's answers: signed distances at any world point, boxes of samples at any
//! resolution, and meshes of any region (`crate::codecs::ifs3d::isosurface`).

use crate::Error;
use crate::codecs::ifs3d::isosurface;
use crate::codecs::ifs3d::volume::Volume;
use crate::core::decode::{self, DiscreteOptions};
use crate::io::asset::Asset;
use crate::mesh::Mesh;

/// The signed distance at one world point (continuous decoding) and its bound, world units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DistanceSample {
    /// Signed distance (negative inside), clamped to the band.
    pub distance: f32,
    /// Bound on |distance - attractor| after the steps taken.
    pub error_bound: f32,
    /// Inverse steps taken.
    pub iterations: u32,
}

/// Continuous decoding of a box elsewhere (a GPU): `(lo, hi, dims, iterations, tolerance)` in
/// unit coordinates and normalised units -> normalised values (x fastest) and their largest
/// bound, or `None` for the CPU to decode.
pub type VolumeGridHook<'a> =
    dyn Fn([f32; 3], [f32; 3], [usize; 3], u32, f32) -> Option<(Vec<f32>, f32)> + Sync + 'a;

/// Largest number of samples one box or mesh request may decode.
pub const MAX_SAMPLES: usize = 1 << 27;

impl Asset {
    fn volume_or_err(&self) -> Result<&Volume, Error> {
        self.volume()
            .ok_or_else(|| Error::settings("this asset is not a volume"))
    }

    /// Signed distances at world points (continuous decoding, `iterations` steps, each chain
    /// stopping once its bound is under `tolerance` world units); `None` outside the grid.
    pub fn distances(
        &self,
        points: &[[f64; 3]],
        iterations: u32,
        tolerance: f32,
    ) -> Result<Vec<Option<DistanceSample>>, Error> {
        let v = self.volume_or_err()?;
        let (lo, span) = (self.meta.value_min as f32, self.span_f32());
        let units: Vec<Option<[f32; 3]>> = points.iter().map(|&p| v.unit(p)).collect();
        let inside: Vec<[f32; 3]> = units.iter().map(|u| u.unwrap_or([0.0; 3])).collect();
        let pv = decode::points(&v.operator, &inside, iterations, tolerance / span);
        Ok(units
            .iter()
            .zip(pv)
            .map(|(u, p)| {
                u.map(|_| DistanceSample {
                    distance: lo + p.value * span,
                    error_bound: p.error_bound * span,
                    iterations: p.iterations,
                })
            })
            .collect())
    }

    fn span_f32(&self) -> f32 {
        (self.meta.value_max - self.meta.value_min) as f32
    }

    /// Signed distances on a box `[lo, hi]` (world units) at `dims` samples per axis, corners
    /// included (x fastest), and the largest error bound. Parts of the box outside the grid read
    /// the nearest face of the grid. The box's continuous decoding is offered to `hook` (a GPU)
    /// first: it gets the box in unit coordinates, the samples, the steps and the normalised
    /// tolerance, and answers normalised values and their largest bound, or `None` to let the
    /// CPU decode.
    pub fn distance_grid_with(
        &self,
        lo: [f64; 3],
        hi: [f64; 3],
        dims: [usize; 3],
        iterations: u32,
        tolerance: f32,
        hook: Option<&VolumeGridHook>,
    ) -> Result<(Vec<f32>, f32), Error> {
        let v = self.volume_or_err()?;
        if dims.iter().any(|&d| d < 2) || dims.iter().product::<usize>() > MAX_SAMPLES {
            return Err(Error::settings(format!(
                "{dims:?} samples: each side at least 2, at most {MAX_SAMPLES} in all"
            )));
        }
        let (glo, ghi) = v.bounds();
        let unit = |p: [f64; 3]| -> [f32; 3] {
            std::array::from_fn(|a| ((p[a] - glo[a]) / (ghi[a] - glo[a])) as f32)
        };
        let span = self.span_f32();
        let (ulo, uhi, t) = (unit(lo), unit(hi), tolerance / span);
        let (values, bound) = hook
            .and_then(|h| h(ulo, uhi, dims, iterations, t))
            .unwrap_or_else(|| decode::volume_window(&v.operator, ulo, uhi, dims, iterations, t));
        let base = self.meta.value_min as f32;
        Ok((
            values.into_iter().map(|x| base + x * span).collect(),
            bound * span,
        ))
    }

    /// The decoded field on its native grid (discrete decoding), world units.
    pub fn distance_field_native(&self) -> Result<Vec<f32>, Error> {
        let v = self.volume_or_err()?;
        let n = v.size();
        let (values, _) = decode::discrete_volume(&v.operator, [n; 3], DiscreteOptions::fixed(24));
        let (base, span) = (self.meta.value_min as f32, self.span_f32());
        Ok(values.into_iter().map(|x| base + x * span).collect())
    }

    /// The surface of a volume asset inside `bbox` (world min and max; the whole grid when
    /// `None`), with `resolution` samples along the box's longest side (the others in
    /// proportion), by continuous decoding: a resolution above the encoded grid evaluates the
    /// fractal between the source samples. Returns the mesh (world units, outward normals) and
    /// the largest error bound of the sampled distances.
    pub fn volume_mesh(
        &self,
        bbox: Option<([f64; 3], [f64; 3])>,
        resolution: usize,
        iterations: u32,
        tolerance: f32,
    ) -> Result<(Mesh, f32), Error> {
        self.volume_mesh_with(bbox, resolution, iterations, tolerance, None)
    }

    /// [`Asset::volume_mesh`] with the sampling of the box handed to `hook` (see
    /// [`Asset::distance_grid_with`]).
    pub fn volume_mesh_with(
        &self,
        bbox: Option<([f64; 3], [f64; 3])>,
        resolution: usize,
        iterations: u32,
        tolerance: f32,
        hook: Option<&VolumeGridHook>,
    ) -> Result<(Mesh, f32), Error> {
        let v = self.volume_or_err()?;
        let (lo, hi) = bbox.unwrap_or_else(|| v.bounds());
        if (0..3).any(|a| !lo[a].is_finite() || !hi[a].is_finite() || hi[a] <= lo[a]) {
            return Err(Error::settings("bbox must have max > min on every axis"));
        }
        let longest = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        let step = longest / (resolution.max(2) - 1) as f64;
        let dims: [usize; 3] =
            std::array::from_fn(|a| (((hi[a] - lo[a]) / step).round() as usize + 1).max(2));
        let (values, bound) = self.distance_grid_with(lo, hi, dims, iterations, tolerance, hook)?;
        let spacing: [f64; 3] = std::array::from_fn(|a| (hi[a] - lo[a]) / (dims[a] - 1) as f64);
        Ok((isosurface::extract(&values, dims, 0.0, lo, spacing), bound))
    }
}
