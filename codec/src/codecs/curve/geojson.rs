//! GeoJSON in and out (RFC 7946), through the `geojson` crate for reading.
//!
//! Every line geometry of the input becomes one polyline, in document order: a LineString
//! (closed when its last position repeats its first), each part of a MultiLineString, each
//! linear ring of a Polygon or MultiPolygon, recursively through GeometryCollections.
//! Altitudes are dropped (curves are 2D); other properties are not kept (the asset stores
//! geometry only). Output is one Feature per polyline, in the same order.

use super::{CurveLevel, Pt};
use geojson::{GeoJson, Geometry, GeometryValue};

/// One input polyline.
#[derive(Clone, Debug, PartialEq)]
pub struct Polyline {
    /// Its vertices, a ring's first one not repeated at the end.
    pub points: Vec<Pt>,
    /// Whether it is a closed ring.
    pub closed: bool,
}

/// Parses GeoJSON text into polylines.
pub fn read(text: &str) -> Result<Vec<Polyline>, String> {
    let doc: GeoJson = text.parse().map_err(|e| format!("GeoJSON: {e}"))?;
    let mut out = Vec::new();
    match doc {
        GeoJson::FeatureCollection(fc) => {
            for f in fc.features {
                if let Some(g) = f.geometry {
                    geometry(&g, &mut out)?;
                }
            }
        }
        GeoJson::Feature(f) => {
            if let Some(g) = f.geometry {
                geometry(&g, &mut out)?;
            }
        }
        GeoJson::Geometry(g) => geometry(&g, &mut out)?,
    }
    if out.is_empty() {
        return Err("GeoJSON: no LineString, MultiLineString or Polygon to encode".into());
    }
    Ok(out)
}

fn line(
    positions: &[geojson::Position],
    ring: bool,
    out: &mut Vec<Polyline>,
) -> Result<(), String> {
    let mut points = Vec::with_capacity(positions.len());
    for p in positions {
        if p.len() < 2 {
            return Err("GeoJSON: a position has fewer than 2 coordinates".into());
        }
        let q = [p[0], p[1]];
        if !(q[0].is_finite() && q[1].is_finite()) {
            return Err(format!("GeoJSON: position {q:?} is not finite"));
        }
        points.push(q);
    }
    let closed = ring || (points.len() >= 4 && points.first() == points.last());
    if closed && points.len() > 1 && points.first() == points.last() {
        points.pop();
    }
    out.push(Polyline { points, closed });
    Ok(())
}

fn geometry(g: &Geometry, out: &mut Vec<Polyline>) -> Result<(), String> {
    match &g.value {
        GeometryValue::LineString { coordinates } => line(coordinates, false, out),
        GeometryValue::MultiLineString { coordinates } => {
            coordinates.iter().try_for_each(|l| line(l, false, out))
        }
        GeometryValue::Polygon { coordinates } => {
            coordinates.iter().try_for_each(|l| line(l, true, out))
        }
        GeometryValue::MultiPolygon { coordinates } => coordinates
            .iter()
            .flatten()
            .try_for_each(|l| line(l, true, out)),
        GeometryValue::GeometryCollection { geometries } => {
            geometries.iter().try_for_each(|g| geometry(g, out))
        }
        GeometryValue::Point { .. } | GeometryValue::MultiPoint { .. } => Ok(()),
    }
}

/// A decoded level as a GeoJSON FeatureCollection: one LineString Feature per ring, with its
/// index and closedness, and the level and its error bound as a foreign member `fractile`.
pub fn write(level: &CurveLevel, finest: usize, units: &str) -> serde_json::Value {
    let features: Vec<serde_json::Value> = level
        .lines
        .iter()
        .zip(&level.closed)
        .enumerate()
        .map(|(i, (pts, closed))| {
            serde_json::json!({
                "type": "Feature",
                "properties": {"ring": i, "closed": closed, "points": pts.len()},
                "geometry": {"type": "LineString", "coordinates": pts},
            })
        })
        .collect();
    let bound = level.error_bound.is_finite().then_some(level.error_bound);
    serde_json::json!({
        "type": "FeatureCollection",
        "features": features,
        "fractile": {
            "level": level.level,
            "finest_level": finest,
            "error_bound": bound,
            "units": units,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_lines_rings_and_polygons_in_order() {
        let text = r#"{"type":"FeatureCollection","features":[
          {"type":"Feature","properties":{},"geometry":{"type":"LineString","coordinates":[[0,0],[1,0],[1,1],[0,0]]}},
          {"type":"Feature","properties":{},"geometry":{"type":"MultiLineString","coordinates":[[[5,5],[6,6,100]]]}},
          {"type":"Feature","properties":{},"geometry":{"type":"Polygon","coordinates":[[[0,0],[2,0],[2,2],[0,2],[0,0]]]}}
        ]}"#;
        let p = read(text).unwrap();
        assert_eq!(p.len(), 3);
        assert!(p[0].closed && p[0].points.len() == 3);
        assert!(!p[1].closed && p[1].points == vec![[5.0, 5.0], [6.0, 6.0]]);
        assert!(p[2].closed && p[2].points.len() == 4);
    }

    #[test]
    fn refuses_what_it_cannot_encode() {
        assert!(read("{").is_err());
        assert!(read(r#"{"type":"Point","coordinates":[1,2]}"#).is_err());
        assert!(read(r#"{"type":"LineString","coordinates":[[1],[2,3]]}"#).is_err());
    }
}
