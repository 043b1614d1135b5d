//! GeoJSON in and out (RFC 7946), through the `geojson` crate for reading.
//!
//! Every line geometry of the input becomes one polyline, in document order: a LineString
//! (closed when its last position repeats its first), each part of a MultiLineString, each
//! linear ring of a Polygon or MultiPolygon, recursively through GeometryCollections.
//! Altitudes are dropped (curves are 2D); other properties are not kept (the asset stores
//! geometry only). Output is one Feature per polyline, in the same order.

use super::distance::Pt;
use super::model::CurveLevel;
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
pub fn read(text: &str) -> Result<Vec<Polyline>, crate::Error> {
    let doc: GeoJson = text
        .parse()
        .map_err(|e| crate::Error::input(format!("GeoJSON: {e}")))?;
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
        return Err(crate::Error::input(
            "GeoJSON: no LineString, MultiLineString or Polygon to encode",
        ));
    }
    Ok(out)
}

fn line(
    positions: &[geojson::Position],
    ring: bool,
    out: &mut Vec<Polyline>,
) -> Result<(), crate::Error> {
    let mut points = Vec::with_capacity(positions.len());
    for p in positions {
        if p.len() < 2 {
            return Err(crate::Error::input(
                "GeoJSON: a position has fewer than 2 coordinates",
            ));
        }
        let q = [p[0], p[1]];
        if !(q[0].is_finite() && q[1].is_finite()) {
            return Err(crate::Error::input(format!(
                "GeoJSON: position {q:?} is not finite"
            )));
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

fn geometry(g: &Geometry, out: &mut Vec<Polyline>) -> Result<(), crate::Error> {
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

/// A decoded level as GeoJSON text: a FeatureCollection of one LineString Feature per ring,
/// with its index and closedness, and the level and its error bound as a foreign member
/// `fractile`. Serialised straight from the points (serde's derive over borrowed rings): a
/// `serde_json::Value` tree of 4 million points held about 6 times the text's 97 MB.
pub fn write(level: &CurveLevel, finest: usize, units: &str) -> Vec<u8> {
    let mut out = Vec::new();
    write_to(level, finest, units, &mut out).expect("GeoJSON of finite numbers serialises");
    out
}

/// [`write()`] into `out` as it goes (a server streams it: the text is never held whole).
pub fn write_to(
    level: &CurveLevel,
    finest: usize,
    units: &str,
    out: &mut dyn std::io::Write,
) -> std::io::Result<()> {
    #[derive(serde::Serialize)]
    struct Collection<'a> {
        #[serde(rename = "type")]
        kind: &'static str,
        features: Vec<Feature<'a>>,
        fractile: Member<'a>,
    }
    #[derive(serde::Serialize)]
    struct Feature<'a> {
        #[serde(rename = "type")]
        kind: &'static str,
        properties: Properties,
        geometry: Line<'a>,
    }
    #[derive(serde::Serialize)]
    struct Properties {
        ring: usize,
        closed: bool,
        points: usize,
    }
    #[derive(serde::Serialize)]
    struct Line<'a> {
        #[serde(rename = "type")]
        kind: &'static str,
        coordinates: &'a [Pt],
    }
    #[derive(serde::Serialize)]
    struct Member<'a> {
        level: usize,
        finest_level: usize,
        error_bound: Option<f64>,
        units: &'a str,
    }
    let features = level
        .lines
        .iter()
        .zip(&level.closed)
        .enumerate()
        .map(|(ring, (pts, &closed))| Feature {
            kind: "Feature",
            properties: Properties {
                ring,
                closed,
                points: pts.len(),
            },
            geometry: Line {
                kind: "LineString",
                coordinates: pts,
            },
        })
        .collect();
    let doc = Collection {
        kind: "FeatureCollection",
        features,
        fractile: Member {
            level: level.level,
            finest_level: finest,
            error_bound: level.error_bound.is_finite().then_some(level.error_bound),
            units,
        },
    };
    let mut out = std::io::BufWriter::new(out);
    serde_json::to_writer(&mut out, &doc).map_err(std::io::Error::other)?;
    std::io::Write::flush(&mut out)
}

/// Bytes a level of `points` points holds while [`write_to`] streams it: the decoded points
/// (16 bytes each) and their rings' bookkeeping; the text is not held.
pub fn write_bytes(points: u128) -> u64 {
    u64::try_from(points.saturating_mul(20)).unwrap_or(u64::MAX)
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
