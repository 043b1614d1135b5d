//! Volume assets (IFS3D) end to end: a mesh becomes a signed distance field ([`crate::sdf`]),
//! the field an octree IFS ([`crate::octree`]), the asset answers signed distances at any world
//! point, boxes of samples at any resolution, and meshes of any region ([`crate::isosurface`]).
//!
//! Coordinates: the asset keeps the world placement of its grid ([`Placement`]); requests speak
//! world units (those of the source mesh). Unit coordinates `[0, 1]^3` span the grid's cube, as
//! they span the frame in 2D.

use fractile_proto::{AssetKind, AssetMeta, ColourModel, EncodeStats, SampleFormat};
use serde::{Deserialize, Serialize};

use crate::Error;
use crate::asset::Asset;
use crate::decode::{self, DiscreteOptions};
use crate::isosurface;
use crate::mesh::Mesh;
use crate::octree::{OctreeHeader, OctreeOperator, VolumeSettings};
use crate::sdf::DistanceField;

/// Where a volume's grid lies in world units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Placement {
    /// Outer corner of the grid (the minimum of every axis).
    pub origin: [f64; 3],
    /// Side of a voxel.
    pub voxel: f64,
}

impl Placement {
    /// Rejects placements no encoder writes.
    pub fn validate(&self) -> Result<(), String> {
        if self.origin.iter().all(|v| v.is_finite()) && self.voxel.is_finite() && self.voxel > 0.0 {
            Ok(())
        } else {
            Err(format!("bad placement {self:?}"))
        }
    }
}

/// A coded volume: header and stream as stored, the decoding operator, the placement.
#[derive(Clone, Debug)]
pub struct Volume {
    /// Frame, sizes, quantiser.
    pub header: OctreeHeader,
    /// The transform stream.
    pub stream: Vec<u8>,
    /// The decoding operator.
    pub operator: OctreeOperator,
    /// The grid in world units.
    pub placement: Placement,
}

impl Volume {
    /// Samples per side of the source grid.
    pub fn size(&self) -> usize {
        self.header.valid as usize
    }

    /// World bounds of the grid's cube: (min, max).
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let o = self.placement.origin;
        let side = self.size() as f64 * self.placement.voxel;
        (o, o.map(|v| v + side))
    }

    /// Unit coordinates of a world point; `None` outside the grid's cube (or not finite).
    pub fn unit(&self, p: [f64; 3]) -> Option<[f32; 3]> {
        let (lo, hi) = self.bounds();
        let u: [f64; 3] = std::array::from_fn(|a| (p[a] - lo[a]) / (hi[a] - lo[a]));
        u.iter()
            .all(|v| (0.0..=1.0).contains(v))
            .then(|| u.map(|v| v as f32))
    }
}

/// Settings of `fractile encode` for a mesh.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshSettings {
    /// Samples per side of the distance grid (the seed: 64 and 128).
    pub grid: usize,
    /// Half-width of the narrow band in voxels: distances are clamped to it.
    pub band: f64,
    /// The octree codec.
    pub codec: VolumeSettings,
}

impl Default for MeshSettings {
    fn default() -> Self {
        MeshSettings {
            grid: 64,
            band: 4.0,
            codec: VolumeSettings::default(),
        }
    }
}

/// What encoding a mesh produced and measured.
#[derive(Clone, Debug)]
pub struct EncodedVolume {
    /// The asset (its metadata holds the stats).
    pub asset: Asset,
    /// The file's bytes.
    pub bytes: Vec<u8>,
    /// The source field the codec saw.
    pub field: DistanceField,
    /// Seconds spent on the distance field.
    pub field_seconds: f64,
    /// Wall time of the whole encode, field included.
    pub seconds: f64,
}

impl EncodedVolume {
    /// PSNR of the decoded field, peak = the field's range (2 band), as the seed.
    pub fn psnr(&self) -> f64 {
        self.asset.meta.stats.psnr
    }

    /// Ratio against the signed-byte volume of the same grid (the seed's baseline).
    pub fn ratio_i8(&self) -> f64 {
        (self.field.size as f64).powi(3) / self.bytes.len() as f64
    }

    /// Ratio against the float32 volume of the same grid.
    pub fn ratio_f32(&self) -> f64 {
        4.0 * self.ratio_i8()
    }
}

/// Encodes a mesh as an IFS3D volume asset. `source` names the input, for provenance.
pub fn encode_mesh(mesh: &Mesh, s: &MeshSettings, source: &str) -> Result<EncodedVolume, Error> {
    let start = std::time::Instant::now();
    let field = DistanceField::from_mesh(mesh, s.grid, s.band)?;
    let field_seconds = start.elapsed().as_secs_f64();
    let n = field.size;
    let (header, stream, operator) =
        crate::octree::encode_field(&field.normalised(), n, &s.codec).map_err(Error::Settings)?;
    let transforms = operator.leaves().len();
    // Measure what a reader decodes: the native grid, discrete, as the encoder fitted it.
    let (decoded, _) = decode::discrete_volume(&operator, [n; 3], DiscreteOptions::fixed(24));
    let span = 2.0 * field.band;
    let world: Vec<f32> = decoded
        .iter()
        .map(|&d| (-field.band + d as f64 * span) as f32)
        .collect();
    let errors = crate::metrics::compare(std::slice::from_ref(&field.values), &[world], None, span);
    let meta = AssetMeta {
        kind: AssetKind::Volume,
        width: n as u32,
        height: n as u32,
        channels: 1,
        colour: ColourModel::Grey,
        sample: SampleFormat::I8,
        units: None,
        value_min: -field.band,
        value_max: field.band,
        nodata: None,
        georef: None,
        encoder: format!(
            "fractile {} ifs3d-octree source={source} grid={n} band={} voxels min_range={} levels={} contrast_bits={} offset_bits={} partition={:?}",
            env!("CARGO_PKG_VERSION"),
            s.band,
            s.codec.min_size,
            s.codec.levels,
            s.codec.quantiser.contrast_bits,
            s.codec.quantiser.offset_bits,
            s.codec.partition
        ),
        stats: EncodeStats {
            transforms: transforms as u64,
            rmse: errors.rmse,
            psnr: errors.psnr,
            max_error: errors.max_error,
            seconds: 0.0,
        },
    };
    let placement = Placement {
        origin: field.origin,
        voxel: field.voxel,
    };
    let mut asset = Asset::from_volume_parts(meta, header, stream, placement)?;
    asset.meta.stats.seconds = start.elapsed().as_secs_f64();
    let bytes = asset.to_bytes();
    Ok(EncodedVolume {
        asset,
        bytes,
        field,
        field_seconds,
        seconds: start.elapsed().as_secs_f64(),
    })
}

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
        self.volume
            .as_ref()
            .ok_or_else(|| Error::Settings("this asset is not a volume".into()))
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
            return Err(Error::Settings(format!(
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
            return Err(Error::Settings(
                "bbox must have max > min on every axis".into(),
            ));
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

/// Distances between two surfaces, world units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceDistance {
    /// Symmetric Chamfer distance: the mean of the two mean nearest distances.
    pub chamfer: f64,
    /// Symmetric Hausdorff distance: the larger of the two largest nearest distances.
    pub hausdorff: f64,
}

/// Chamfer and Hausdorff distances between the surfaces of `a` and `b`, each sampled with
/// `samples` area-weighted points plus its vertices; nearest neighbours through a k-d tree of
/// the other's samples. The sampling adds at most the sample spacing to each distance, so
/// callers take enough samples for their precision (the bench: 200,000 per mesh).
pub fn surface_distance(a: &Mesh, b: &Mesh, samples: usize) -> SurfaceDistance {
    use kiddo::{ImmutableKdTree, SquaredEuclidean};
    use rayon::prelude::*;
    let (pa, pb) = (a.surface_samples(samples), b.surface_samples(samples));
    if pa.is_empty() || pb.is_empty() {
        return SurfaceDistance {
            chamfer: f64::INFINITY,
            hausdorff: f64::INFINITY,
        };
    }
    let one_way = |from: &[[f32; 3]], to: &[[f32; 3]]| -> (f64, f64) {
        let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(to);
        let d: Vec<f64> = from
            .par_iter()
            .map(|p| (tree.nearest_one::<SquaredEuclidean>(p).distance as f64).sqrt())
            .collect();
        (
            d.iter().sum::<f64>() / d.len() as f64,
            d.iter().cloned().fold(0.0, f64::max),
        )
    };
    let (ma, xa) = one_way(&pa, &pb);
    let (mb, xb) = one_way(&pb, &pa);
    SurfaceDistance {
        chamfer: 0.5 * (ma + mb),
        hausdorff: xa.max(xb),
    }
}
