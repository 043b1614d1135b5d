//! Meshes: a terrain grid or adaptive triangulation of a region, or the surface of a volume in a box.

use fractile_proto::ErrorCode;
use fractile_proto::query::MeshFormat;

use super::request::*;
use super::state::*;
use std::sync::Arc;

use crate::error::{Path, Query};
use axum::extract::State;
use axum::response::Response;
use fractile_codec::geo;
use fractile_proto::AssetKind;
use serde::Deserialize;

use crate::error::AppError;
use crate::store::StoredAsset;
use crate::work::{BodyWriter, Bounds, Head};

#[derive(Deserialize)]
pub(super) struct MeshQuery {
    bbox: Option<String>,
    resolution: Option<usize>,
    /// Height fields: an adaptive triangulation whose surface stays within this many height
    /// units of the decoded grid (absent: the regular grid).
    max_error: Option<f32>,
    iterations: Option<u32>,
    tolerance: Option<f32>,
    backend: Option<String>,
    format: Option<String>,
}

/// A terrain mesh of a region: a regular grid of `resolution x resolution` vertices, or with
/// `max_error` an adaptive triangulation (RTIN) of the grid of the next `2^k + 1` vertices a
/// side whose surface stays within `max_error` of every decoded height. For georeferenced
/// assets x and y are metres east and north of the box's south-west corner (a local tangent
/// plane) and z is the height; otherwise x and y are source pixels. `X-Error-Bound` is the
/// decoding bound, plus `max_error` for adaptive meshes.
pub(super) async fn mesh(
    State(state): Shared,
    Path(id): Path<String>,
    Query(q): Query<MeshQuery>,
) -> Result<Response, AppError> {
    let a = state.store.get(&id)?;
    if a.asset.meta.kind == AssetKind::Volume {
        return volume_mesh(&state, a, q).await;
    }
    if a.asset.meta.kind != AssetKind::HeightField {
        return Err(AppError::bad_request(
            ErrorCode::NotTerrain,
            "meshes are made of height fields and volumes",
        ));
    }
    let n = q.resolution.unwrap_or(256);
    if !(2..=2048).contains(&n) {
        return Err(AppError::bad_request(
            ErrorCode::BadResolution,
            "resolution must be 2..=2048 vertices a side",
        ));
    }
    let max_error = q.max_error;
    if max_error.is_some_and(|e| !(e.is_finite() && e >= 0.0)) {
        return Err(AppError::bad_request(
            ErrorCode::BadMaxError,
            "max_error must be a number >= 0 (height units)",
        ));
    }
    // The network splits squares in halves down to single cells: 2^k + 1 vertices a side.
    let n = match max_error {
        Some(_) => (n - 1).next_power_of_two() + 1,
        None => n,
    };
    let format = mesh_format(q.format.as_deref())?;
    let [x0, y0, x1, y1] = match &q.bbox {
        Some(b) => parse_bbox(b)?,
        None => match &a.placement {
            Some(p) => p.bounds(),
            None => [0.0, 0.0, 1.0, 1.0],
        },
    };
    let (iterations, tolerance) = iterations_for(&state, q.iterations, q.tolerance)?;
    let geo_ref = a.placement.is_some();
    // Vertex (i, j): i east, j south, corners included.
    let frac = |k: usize| k as f64 / (n - 1) as f64;
    let grid = box_pixels(
        &a,
        (n, |i| x0 + frac(i) * (x1 - x0)),
        (n, |j| {
            if geo_ref {
                y1 - frac(j) * (y1 - y0)
            } else {
                y0 + frac(j) * (y1 - y0)
            }
        }),
        cell_size([x0, y0, x1, y1], n - 1, n - 1),
    );
    if grid.is_outside() {
        return Err(AppError::not_found(
            ErrorCode::Outside,
            "the box is outside the asset",
        ));
    }
    let (extent_x, extent_y) = if geo_ref {
        let m = geo::metres_per_degree(0.5 * (y0 + y1));
        ((x1 - x0) * m[0], (y1 - y0) * m[1])
    } else {
        (
            (x1 - x0) * a.asset.meta.width as f64,
            (y1 - y0) * a.asset.meta.height as f64,
        )
    };
    let (choice, gpu, coarse) = (
        backend_for(&state, q.backend.as_deref())?,
        state.gpu.clone(),
        state.coarse.clone(),
    );
    // Samples, then the mesh (a vertex and two triangles a sample, with normals) and its
    // writer's buffers: about 96 bytes a vertex.
    let cost = sampling_bytes(n * n, 1) + (n * n) as u64 * 96;
    state
        .lanes
        .stream(cost, move |cancel| {
            let (channels, bound) = sample_on(
                (gpu.as_deref(), &coarse, cancel),
                choice,
                &a,
                &grid,
                iterations,
                tolerance,
            )?;
            let spacing = [
                (extent_x / (n - 1) as f64) as f32,
                (extent_y / (n - 1) as f64) as f32,
            ];
            let origin = [0.0, extent_y as f32];
            let m = match max_error {
                Some(e) => {
                    fractile_codec::mesh::Mesh::adaptive(&channels[0], n, origin, spacing, e)
                        .map_err(|e| AppError::internal(e.to_string()))?
                }
                None => fractile_codec::mesh::Mesh::grid(&channels[0], n, n, origin, spacing),
            };
            Ok(mesh_body(m, format, bound.plus(max_error.unwrap_or(0.0))))
        })
        .await
}

/// `format` (glb when absent).
fn mesh_format(format: Option<&str>) -> Result<MeshFormat, AppError> {
    format
        .map(str::parse)
        .unwrap_or(Ok(MeshFormat::default()))
        .map_err(|_: String| {
            AppError::bad_request(ErrorCode::BadFormat, "format must be obj, ply or glb")
        })
}

/// The head and writer of a mesh answer in `format` (obj, ply or glb): text and PLY are
/// written as they stream; GLB, whose header holds its length, is built whole (it is the
/// compact one, about 24 bytes a vertex).
fn mesh_body(
    m: fractile_codec::mesh::Mesh,
    format: MeshFormat,
    bounds: Bounds,
) -> (Head, BodyWriter) {
    let (content_type, writer): (&'static str, BodyWriter) = match format {
        MeshFormat::Obj => ("text/plain", Box::new(move |w| m.write_obj(w))),
        MeshFormat::Ply => (
            "application/octet-stream",
            Box::new(move |w| m.write_ply(w)),
        ),
        MeshFormat::Glb => (
            "model/gltf-binary",
            Box::new(move |w: &mut dyn std::io::Write| w.write_all(&m.to_glb())),
        ),
    };
    (
        Head {
            content_type,
            bounds,
        },
        writer,
    )
}

/// Largest samples a volume mesh request decodes (256^3).
const MAX_VOLUME_SAMPLES: usize = 1 << 24;

/// The surface of a volume inside `bbox=x0,y0,z0,x1,y1,z1` (world units; default the whole
/// grid) with `resolution` samples along the box's longest side (default the encoded grid).
async fn volume_mesh(
    state: &Arc<AppState>,
    a: Arc<StoredAsset>,
    q: MeshQuery,
) -> Result<Response, AppError> {
    if q.max_error.is_some() {
        return Err(AppError::bad_request(
            ErrorCode::BadMaxError,
            "max_error (an adaptive triangulation) is for height fields",
        ));
    }
    let grid = a.asset.volume().map_or(64, |v| v.size());
    let n = q.resolution.unwrap_or(grid);
    if !(2..=512).contains(&n) {
        return Err(AppError::bad_request(
            ErrorCode::BadResolution,
            "resolution must be 2..=512 samples along the box's longest side",
        ));
    }
    let format = mesh_format(q.format.as_deref())?;
    let bbox = match &q.bbox {
        None => None,
        Some(b) => {
            let v: Vec<f64> = b.split(',').filter_map(|s| s.trim().parse().ok()).collect();
            match v[..] {
                [x0, y0, z0, x1, y1, z1]
                    if x1 > x0 && y1 > y0 && z1 > z0 && v.iter().all(|c| c.is_finite()) =>
                {
                    Some(([x0, y0, z0], [x1, y1, z1]))
                }
                _ => {
                    return Err(AppError::bad_request(
                        ErrorCode::BadBbox,
                        "a volume's bbox is x0,y0,z0,x1,y1,z1 with max > min on every axis",
                    ));
                }
            }
        }
    };
    // The samples the box will take, refused before any decoding.
    if let Some((lo, hi)) = bbox {
        let longest = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
        let samples: f64 = (0..3)
            .map(|k| ((hi[k] - lo[k]) / longest * (n - 1) as f64).round() + 1.0)
            .product();
        if samples > MAX_VOLUME_SAMPLES as f64 {
            return Err(AppError::bad_request(
                ErrorCode::TooManySamples,
                format!("the box takes {samples} samples, over {MAX_VOLUME_SAMPLES}"),
            ));
        }
    } else if n.pow(3) > MAX_VOLUME_SAMPLES {
        return Err(AppError::bad_request(
            ErrorCode::TooManySamples,
            format!(
                "resolution {n} takes {} samples, over {MAX_VOLUME_SAMPLES}",
                n.pow(3)
            ),
        ));
    }
    let (iterations, tolerance) = iterations_for(state, q.iterations, q.tolerance)?;
    let (choice, gpu) = (backend_for(state, q.backend.as_deref())?, state.gpu.clone());
    let samples = match bbox {
        Some((lo, hi)) => {
            let longest = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
            (0..3)
                .map(|k| ((hi[k] - lo[k]) / longest * (n - 1) as f64).round() + 1.0)
                .product::<f64>() as u64
        }
        None => (n as u64).pow(3),
    };
    // A distance a sample, and a surface of up to a few vertices per surface cell.
    let cost = samples * 16 + (n as u64).pow(2) * 256;
    state
        .lanes
        .stream(cost, move |cancel| {
            let on_gpu = |lo, hi, dims: [usize; 3], n, t| {
                gpu.as_deref()
                    .filter(|g| g.takes(choice, &a, dims.iter().product()))
                    .and_then(|g| cancel.off_core(|| g.volume_grid(&a, (lo, hi, dims), n, t)))
            };
            let (m, bound) = a
                .asset
                .volume_mesh_with(bbox, n, iterations, tolerance.anywhere(&a), Some(&on_gpu))
                .map_err(|e| AppError::bad_request(ErrorCode::BadRequest, e.to_string()))?;
            // Volumes hold no source-error map.
            let bounds = Bounds {
                attractor: bound,
                source: None,
            };
            Ok(mesh_body(m, format, bounds))
        })
        .await
}
