//! Meshes into IFS3D volume assets: a mesh becomes a signed distance field
//! (`crate::codecs::ifs3d::sdf`), the field an octree IFS ([`crate::codecs::ifs3d::OctreeOperator`]).

use fractile_proto::{AssetKind, AssetMeta, ColourModel, EncodeStats, SampleFormat};

use crate::Error;
use crate::codecs::ifs3d::fit::VolumeSettings;
use crate::codecs::ifs3d::sdf::DistanceField;
use crate::codecs::ifs3d::volume::Placement;
use crate::core::decode::{self, DiscreteOptions};
use crate::io::asset::Asset;
use crate::mesh::Mesh;

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
        crate::codecs::ifs3d::fit::encode_field(&field.normalised(), n, &s.codec)?;
    let transforms = operator.leaves().len();
    // Measure what a reader decodes: the native grid, discrete, as the encoder fitted it.
    let (decoded, _) = decode::discrete_volume(&operator, [n; 3], DiscreteOptions::fixed(24));
    let span = 2.0 * field.band;
    let world: Vec<f32> = decoded
        .iter()
        .map(|&d| (-field.band + d as f64 * span) as f32)
        .collect();
    let errors =
        crate::core::metrics::compare(std::slice::from_ref(&field.values), &[world], None, span);
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
