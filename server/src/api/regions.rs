//! Regions: a window of an asset at any resolution, as PNG, float32 or GeoTIFF.

use fractile_proto::ErrorCode;
use fractile_proto::query::RegionFormat;

use super::request::*;
use super::state::*;

use crate::error::{Path, Query};
use axum::extract::State;
use axum::response::Response;
use fractile_proto::AssetKind;
use serde::Deserialize;

use crate::encoding::{self};
use crate::error::AppError;
use crate::store::StoredAsset;
use crate::work::{BodyWriter, Head};

#[derive(Deserialize)]
pub(super) struct RegionQuery {
    bbox: String,
    width: usize,
    height: usize,
    iterations: Option<u32>,
    tolerance: Option<f32>,
    backend: Option<String>,
    format: Option<String>,
}

pub(super) async fn region(
    State(state): Shared,
    Path(id): Path<String>,
    Query(q): Query<RegionQuery>,
) -> Result<Response, AppError> {
    let a = planar(state.store.get(&id)?)?;
    let [x0, y0, x1, y1] = parse_bbox(&q.bbox)?;
    if q.width == 0
        || q.height == 0
        || q.width.saturating_mul(q.height) > state.limits.max_region_pixels
    {
        return Err(AppError::bad_request(
            ErrorCode::BadSize,
            format!(
                "width x height must be 1..={} pixels",
                state.limits.max_region_pixels
            ),
        ));
    }
    let (n, tolerance) = iterations_for(&state, q.iterations, q.tolerance)?;
    let format = region_format(&a, q.format.as_deref())?;
    let (w, h) = (q.width, q.height);
    // Pixel centres in the request's coordinates: lon/lat (north up) or unit x/y (y down).
    let geo_ref = a.placement.is_some();
    let grid = box_pixels(
        &a,
        (w, |i| x0 + (i as f64 + 0.5) / w as f64 * (x1 - x0)),
        (h, |j| {
            let fy = (j as f64 + 0.5) / h as f64;
            if geo_ref {
                y1 - fy * (y1 - y0)
            } else {
                y0 + fy * (y1 - y0)
            }
        }),
        cell_size([x0, y0, x1, y1], w, h),
    );
    let (choice, gpu, coarse) = (
        backend_for(&state, q.backend.as_deref())?,
        state.gpu.clone(),
        state.coarse.clone(),
    );
    let channels = a.asset.meta.channels;
    // Sampling, then the encoded body (at most 4 bytes a value).
    let cost = sampling_bytes(w * h, channels) + (w * h) as u64 * 4 * u64::from(channels);
    state
        .lanes
        .stream(cost, move |cancel| {
            let (channels, bound) = sample_on(
                (gpu.as_deref(), &coarse, cancel),
                choice,
                &a,
                &grid,
                n,
                tolerance,
            )?;
            let (content_type, body) =
                encode_region(&a, &channels, (w, h), [x0, y0, x1, y1], format)?;
            let head = Head {
                content_type,
                bounds: bound,
            };
            let writer: BodyWriter =
                Box::new(move |out: &mut dyn std::io::Write| out.write_all(&body));
            Ok((head, writer))
        })
        .await
}

/// `format` (png when absent), if the asset has it.
fn region_format(a: &StoredAsset, format: Option<&str>) -> Result<RegionFormat, AppError> {
    match format
        .map(str::parse)
        .unwrap_or(Ok(RegionFormat::default()))
    {
        Ok(RegionFormat::Tif) if a.asset.meta.kind != AssetKind::HeightField => {
            Err(AppError::bad_request(
                ErrorCode::BadFormat,
                "GeoTIFF regions are for height fields (use png)",
            ))
        }
        Ok(f) => Ok(f),
        Err(_) => Err(AppError::bad_request(
            ErrorCode::BadFormat,
            "format must be png, f32 or tif",
        )),
    }
}

/// The decoded region's body and content type. A GeoTIFF's georeference is the requested box
/// (north-up; lon/lat for georeferenced assets, projected ones included).
fn encode_region(
    a: &StoredAsset,
    channels: &[Vec<f32>],
    (w, h): (usize, usize),
    [x0, y0, x1, y1]: [f64; 4],
    format: RegionFormat,
) -> Result<(&'static str, Vec<u8>), AppError> {
    Ok(match format {
        RegionFormat::Tif => {
            let georef = a
                .asset
                .meta
                .georef
                .as_ref()
                .map(|g| fractile_proto::Georef {
                    epsg: match a.placement.as_ref().and_then(|p| p.epsg()) {
                        Some(_) => Some(4326),
                        None => g.epsg,
                    },
                    origin: [x0, y1],
                    pixel_size: [(x1 - x0) / w as f64, -(y1 - y0) / h as f64],
                });
            let nodata = a.asset.meta.nodata;
            let values: Vec<f32> = match nodata {
                Some(nd) => channels[0]
                    .iter()
                    .map(|&v| if v.is_nan() { nd as f32 } else { v })
                    .collect(),
                None => channels[0].clone(),
            };
            let tif = fractile_codec::raster::geotiff_f32(w, h, &values, georef.as_ref(), nodata)
                .map_err(|e| AppError::internal(e.to_string()))?;
            ("image/tiff", tif)
        }
        RegionFormat::F32 => (
            "application/octet-stream",
            channels
                .iter()
                .flat_map(|c| c.iter().flat_map(|v| v.to_le_bytes()))
                .collect(),
        ),
        RegionFormat::Png => {
            let fmt = if a.asset.meta.kind == AssetKind::HeightField {
                encoding::TileFormat::Visual(Some((
                    a.asset.meta.value_min as f32,
                    a.asset.meta.value_max as f32,
                )))
            } else {
                encoding::TileFormat::Visual(None)
            };
            encoding::encode_raster(&a.asset.meta, channels, w, h, fmt, None)
        }
    })
}
